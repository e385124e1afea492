"""Pictures of a frame: the image with 2D boxes and projected LiDAR points above a bird's-eye view
with points and 3D boxes. Ground truth is drawn solid, predictions dashed; classes are coloured."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from detmatch.data.kitti import KittiObjects, objects_to_labels
from detmatch.files import atomic_write_bytes
from detmatch.geometry import bev_corners, lidar_to_image, points_in_image
from detmatch.structures import Frame, Labels

CLASS_COLOURS = {
    "Car": (40, 140, 255),
    "Van": (0, 210, 210),
    "Truck": (120, 120, 255),
    "Pedestrian": (255, 60, 60),
    "Person_sitting": (255, 140, 140),
    "Cyclist": (60, 220, 60),
    "Tram": (200, 120, 255),
    "Misc": (255, 200, 0),
    "DontCare": (150, 150, 150),
}
OTHER_COLOUR = (255, 200, 0)

# Bird's-eye-view extent in metres (LiDAR frame): forward x, lateral y.
BEV_X_RANGE = (-5.0, 75.0)
BEV_Y_RANGE = (-40.0, 40.0)


def class_colour(name: str) -> tuple[int, int, int]:
    return CLASS_COLOURS.get(str(name), OTHER_COLOUR)


def _dashed_line(
    draw: ImageDraw.ImageDraw, start, end, fill, width: int = 2, dash: float = 6.0
) -> None:
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    length = float(np.hypot(*(end - start)))
    if length == 0:
        return
    steps = np.arange(0.0, length, 2 * dash)
    direction = (end - start) / length
    for s in steps:
        a = start + direction * s
        b = start + direction * min(s + dash, length)
        draw.line([tuple(a), tuple(b)], fill=fill, width=width)


def _polygon(
    draw: ImageDraw.ImageDraw, points: np.ndarray, fill, dashed: bool, width: int = 2
) -> None:
    closed = np.concatenate([points, points[:1]], axis=0)
    for a, b in zip(closed[:-1], closed[1:], strict=True):
        if dashed:
            _dashed_line(draw, a, b, fill, width)
        else:
            draw.line([tuple(a), tuple(b)], fill=fill, width=width)


def _depth_colours(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """(N,) values -> (N, 3) uint8 colours on a blue-green-yellow-red ramp."""
    t = np.clip((values - low) / (high - low), 0.0, 1.0)
    ramp = np.array(
        [[40, 60, 255], [0, 200, 200], [80, 230, 60], [255, 220, 0], [255, 40, 40]], float
    )
    position = t * (len(ramp) - 1)
    index = np.minimum(position.astype(int), len(ramp) - 2)
    frac = (position - index)[:, None]
    return ((1 - frac) * ramp[index] + frac * ramp[index + 1]).astype(np.uint8)


def draw_image_panel(frame: Frame, predictions: Labels | None) -> Image.Image:
    """The camera image with projected LiDAR points (coloured by depth) and 2D boxes."""
    image = frame.image.copy()
    width, height = frame.image_size
    uv, depth = lidar_to_image(frame.points[:, :3], frame.calib)
    visible = points_in_image(frame.points[:, :3], frame.calib, frame.image_size, min_depth=1.0)
    pixels = uv[visible].astype(int)
    colours = _depth_colours(depth[visible], 2.0, 60.0)
    image[pixels[:, 1], pixels[:, 0]] = (
        0.35 * image[pixels[:, 1], pixels[:, 0]] + 0.65 * colours
    ).astype(np.uint8)
    picture = Image.fromarray(image)
    draw = ImageDraw.Draw(picture)
    font = ImageFont.load_default()
    for labels, dashed in ((frame.labels, False), (predictions, True)):
        if labels is None:
            continue
        for i in range(len(labels)):
            x1, y1, x2, y2 = labels.boxes_2d.xyxy[i]
            colour = class_colour(labels.names[i])
            _polygon(draw, np.array([[x1, y1], [x2, y1], [x2, y2], [x1, y2]]), colour, dashed)
            text = str(labels.names[i])
            if labels.scores is not None:
                text += f" {labels.scores[i]:.2f}"
            draw.text((x1 + 2, max(y1 - 11, 0)), text, fill=colour, font=font)
    return picture


def draw_bev_panel(frame: Frame, predictions: Labels | None, size: int) -> Image.Image:
    """Bird's-eye view, forward up: points coloured by height, 3D boxes with a heading tick,
    and the camera's field of view."""
    x_low, x_high = BEV_X_RANGE
    y_low, y_high = BEV_Y_RANGE
    scale = size / max(x_high - x_low, y_high - y_low)

    def to_pixels(xy: np.ndarray) -> np.ndarray:
        return np.stack([(y_high - xy[..., 1]) * scale, (x_high - xy[..., 0]) * scale], axis=-1)

    canvas = np.full((size, size, 3), 16, dtype=np.uint8)
    points = frame.points
    pixels = to_pixels(points[:, :2]).astype(int)
    inside = (
        (pixels[:, 0] >= 0) & (pixels[:, 0] < size) & (pixels[:, 1] >= 0) & (pixels[:, 1] < size)
    )
    canvas[pixels[inside, 1], pixels[inside, 0]] = _depth_colours(points[inside, 2], -2.0, 1.5)
    picture = Image.fromarray(canvas)
    draw = ImageDraw.Draw(picture)
    font = ImageFont.load_default()

    # Camera field of view: the image's left and right edges back-projected at 80 m depth.
    width, _ = frame.image_size
    origin = to_pixels(np.zeros(2))
    p2 = frame.calib.P2
    for u in (0.0, float(width)):
        ray_x = (u - p2[0, 2]) / p2[0, 0]
        lidar_xy = np.array([80.0, -80.0 * ray_x])
        draw.line([tuple(origin), tuple(to_pixels(lidar_xy))], fill=(90, 90, 90), width=1)
    for metres in range(10, int(x_high) + 1, 10):
        y = (x_high - metres) * scale
        draw.text((4, y - 6), f"{metres} m", fill=(110, 110, 110), font=font)
        draw.line([(40, y), (size, y)], fill=(40, 40, 40), width=1)

    for labels, dashed in ((frame.labels, False), (predictions, True)):
        if labels is None:
            continue
        real = (labels.names != "DontCare") & np.all(labels.boxes_3d.dims > 0, axis=1)
        boxes = labels.boxes_3d.data[real]
        names = labels.names[real]
        for corners, box, name in zip(bev_corners(boxes), boxes, names, strict=True):
            colour = class_colour(name)
            polygon = to_pixels(corners)
            _polygon(draw, polygon, colour, dashed)
            front = to_pixels(box[:2] + 0.5 * box[3] * np.array([np.cos(box[6]), np.sin(box[6])]))
            draw.line([tuple(to_pixels(box[:2])), tuple(front)], fill=colour, width=2)
    return picture


def render_frame_picture(frame: Frame, predictions: KittiObjects | None = None) -> Image.Image:
    """The image panel above a square bird's-eye-view panel of the same width, with a legend."""
    prediction_labels = None if predictions is None else objects_to_labels(predictions, frame.calib)
    top = draw_image_panel(frame, prediction_labels)
    bottom = draw_bev_panel(frame, prediction_labels, size=top.width)
    picture = Image.new("RGB", (top.width, top.height + bottom.height + 18), (0, 0, 0))
    picture.paste(top, (0, 0))
    picture.paste(bottom, (0, top.height + 18))
    draw = ImageDraw.Draw(picture)
    font = ImageFont.load_default()
    x = 4
    names = {str(n) for n in frame.labels.names} if frame.labels is not None else set()
    if prediction_labels is not None:
        names |= {str(n) for n in prediction_labels.names}
    legend = [n for n in CLASS_COLOURS if n in names] + sorted(names - set(CLASS_COLOURS))
    title = f"frame {frame.frame_id}  {len(frame.points)} points"
    if prediction_labels is not None:
        title += "  (solid: ground truth, dashed: predictions)"
    draw.text((x, top.height + 3), title, fill=(220, 220, 220), font=font)
    x = top.width - 8 - 80 * len(legend)
    for name in legend:
        draw.rectangle([x, top.height + 5, x + 10, top.height + 13], fill=class_colour(name))
        draw.text((x + 14, top.height + 3), name, fill=(220, 220, 220), font=font)
        x += 80
    return picture


def save_frame_picture(frame: Frame, out: Path, predictions: KittiObjects | None = None) -> None:
    import io

    buffer = io.BytesIO()
    render_frame_picture(frame, predictions).save(buffer, format="PNG")
    atomic_write_bytes(out, buffer.getvalue())
