"""Pictures of a frame: the image with 2D boxes and projected LiDAR points above a bird's-eye view
with points and 3D boxes. Ground truth is drawn solid (and filled in the bird's-eye view),
predictions dashed; classes are coloured; no text overlaps another (`TextLayout`)."""

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


# Short class names for labels drawn beside boxes (the legend spells them out).
SHORT_NAMES = {"Pedestrian": "Ped", "Person_sitting": "Sit", "Cyclist": "Cyc", "DontCare": "DC"}
# Ground truth is drawn solid and, in the bird's-eye view, filled with this opacity (0-255);
# predictions are dashed outlines, never filled.
GROUND_TRUTH_FILL_ALPHA = 70
STRIP_ROW = 14  # pixels per text row of the strip between the panels


class TextLayout:
    """Places text so that no two texts overlap and none leaves the picture: each text takes the
    first of its candidate anchors that is free, or is left out (never drawn over another).
    `boxes` holds every placed text's (x1, y1, x2, y2) in the picture's pixels."""

    def __init__(self, size: tuple[int, int], offset: tuple[int, int] = (0, 0)) -> None:
        self.size = size
        self.offset = offset
        self.boxes: list[tuple[int, int, int, int]] = []

    def place(self, draw: ImageDraw.ImageDraw, anchors, text: str, fill, font) -> bool:
        width, height = self.size
        dx, dy = self.offset
        for x, y in anchors:
            x1, y1, x2, y2 = draw.textbbox((x, y), text, font=font)
            shift_x = min(max(0, -x1), width - x2) if x2 > width or x1 < 0 else 0
            shift_y = min(max(0, -y1), height - y2) if y2 > height or y1 < 0 else 0
            box = (x1 + shift_x, y1 + shift_y, x2 + shift_x, y2 + shift_y)
            if box[0] < 0 or box[1] < 0 or box[2] > width or box[3] > height:
                continue
            placed = (box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy)
            if any(_overlap(placed, other) for other in self.boxes):
                continue
            draw.text((x + shift_x, y + shift_y), text, fill=fill, font=font)
            self.boxes.append(placed)
            return True
        return False

    def child(self, size: tuple[int, int], offset: tuple[int, int]) -> TextLayout:
        """A panel's layout that shares this picture's placed boxes, at `offset` in it."""
        panel = TextLayout(size, (self.offset[0] + offset[0], self.offset[1] + offset[1]))
        panel.boxes = self.boxes
        return panel


def _overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _box_label_anchors(x1: float, y1: float, x2: float, y2: float, line: int = 11):
    """Above the box, below it, inside its top, then further above and below, left-aligned."""
    anchors = [(x1 + 2, y1 - line), (x1 + 2, y2 + 1), (x1 + 2, y1 + 1)]
    for k in range(1, 5):
        anchors += [(x1 + 2, y1 - line * (k + 1)), (x1 + 2, y2 + 1 + line * k)]
    return anchors


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
    """A closed outline; dashed outlines scale their dash to the polygon (at least three gaps a
    side), so a small prediction still reads as dashed beside a solid ground-truth box."""
    closed = np.concatenate([points, points[:1]], axis=0)
    sides = np.hypot(*(closed[1:] - closed[:-1]).T)
    dash = float(np.clip(sides.min() / 6.0, 1.5, 6.0)) if len(sides) else 6.0
    for a, b in zip(closed[:-1], closed[1:], strict=True):
        if dashed:
            _dashed_line(draw, a, b, fill, max(width - 1, 1), dash)
        else:
            draw.line([tuple(a), tuple(b)], fill=fill, width=width)


def _label_text(name: str, score: float | None) -> str:
    text = SHORT_NAMES.get(name, name)
    return text if score is None else f"{text} {score:.2f}"


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


def draw_image_panel(
    frame: Frame, predictions: Labels | None, layout: TextLayout | None = None
) -> Image.Image:
    """The camera image with projected LiDAR points (coloured by depth) and 2D boxes: ground
    truth solid, predictions dashed, each with a short class label (and the prediction's score)
    placed where it overlaps no other text."""
    image = frame.image.copy()
    width, height = frame.image_size
    layout = layout or TextLayout((width, height))
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
            score = None if labels.scores is None else float(labels.scores[i])
            text = _label_text(str(labels.names[i]), score)
            layout.place(draw, _box_label_anchors(x1, y1, x2, y2), text, colour, font)
    return picture


def draw_bev_panel(
    frame: Frame, predictions: Labels | None, size: int, layout: TextLayout | None = None
) -> Image.Image:
    """Bird's-eye view, forward up: points coloured by height, 3D boxes with a heading tick
    (ground truth filled and solid, predictions dashed), and the camera's field of view."""
    layout = layout or TextLayout((size, size))
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
        layout.place(draw, [(4, y - 6)], f"{metres} m", (110, 110, 110), font)
        draw.line([(40, y), (size, y)], fill=(40, 40, 40), width=1)

    fill = Image.new("RGBA", picture.size, (0, 0, 0, 0))
    fill_draw = ImageDraw.Draw(fill)
    outlines = []
    for labels, dashed in ((frame.labels, False), (predictions, True)):
        if labels is None:
            continue
        real = (labels.names != "DontCare") & np.all(labels.boxes_3d.dims > 0, axis=1)
        boxes = labels.boxes_3d.data[real]
        names = labels.names[real]
        for corners, box, name in zip(bev_corners(boxes), boxes, names, strict=True):
            colour = class_colour(name)
            polygon = to_pixels(corners)
            if not dashed:
                fill_draw.polygon(
                    [tuple(p) for p in polygon], fill=(*colour, GROUND_TRUTH_FILL_ALPHA)
                )
            front = to_pixels(box[:2] + 0.5 * box[3] * np.array([np.cos(box[6]), np.sin(box[6])]))
            outlines.append((polygon, colour, dashed, to_pixels(box[:2]), front))
    picture = Image.alpha_composite(picture.convert("RGBA"), fill).convert("RGB")
    draw = ImageDraw.Draw(picture)
    for polygon, colour, dashed, centre, front in outlines:
        _polygon(draw, polygon, colour, dashed)
        draw.line([tuple(centre), tuple(front)], fill=colour, width=1 if dashed else 2)
    return picture


def render_frame_picture(
    frame: Frame, predictions: KittiObjects | None = None, layout: TextLayout | None = None
) -> Image.Image:
    """The image panel above a square bird's-eye-view panel of the same width, with a strip
    between them: the caption on its first row, the legend (classes, and with predictions the
    line styles) on the rows below. `layout` collects every text's box (no two overlap)."""
    prediction_labels = None if predictions is None else objects_to_labels(predictions, frame.calib)
    width, height = frame.image_size
    font = ImageFont.load_default()
    names = {str(n) for n in frame.labels.names} if frame.labels is not None else set()
    if prediction_labels is not None:
        names |= {str(n) for n in prediction_labels.names}
    legend = [n for n in CLASS_COLOURS if n in names] + sorted(names - set(CLASS_COLOURS))
    styles = ["ground truth: solid", "predictions: dashed"] if prediction_labels is not None else []
    rows = _legend_rows(legend + styles, width, font)
    strip = STRIP_ROW * (1 + len(rows)) + 4

    picture = Image.new("RGB", (width, height + strip + width), (0, 0, 0))
    layout = layout or TextLayout(picture.size)
    top = draw_image_panel(frame, prediction_labels, layout.child((width, height), (0, 0)))
    bottom = draw_bev_panel(
        frame, prediction_labels, width, layout.child((width, width), (0, height + strip))
    )
    caption = Image.new("RGB", (width, strip), (0, 0, 0))
    draw = ImageDraw.Draw(caption)
    strip_layout = layout.child((width, strip), (0, height))
    title = f"frame {frame.frame_id}  {len(frame.points)} points"
    strip_layout.place(draw, [(4, 2)], title, (220, 220, 220), font)
    for row, entries in enumerate(rows, start=1):
        x = 4
        for entry, entry_width in entries:
            y = 2 + STRIP_ROW * row
            if entry in names:
                draw.rectangle([x, y + 2, x + 10, y + 10], fill=class_colour(entry))
                strip_layout.place(draw, [(x + 14, y)], entry, (220, 220, 220), font)
            else:
                strip_layout.place(draw, [(x, y)], entry, (220, 220, 220), font)
            x += entry_width
    for panel, y in ((top, 0), (caption, height), (bottom, height + strip)):
        picture.paste(panel, (0, y))
    return picture


def _legend_rows(entries: list[str], width: int, font) -> list[list[tuple[str, int]]]:
    """Legend entries (a colour swatch and a name) in rows that fit `width` pixels."""
    rows: list[list[tuple[str, int]]] = [[]]
    used = 4
    for entry in entries:
        entry_width = 14 + int(font.getlength(entry)) + 16
        if rows[-1] and used + entry_width > width:
            rows.append([])
            used = 4
        rows[-1].append((entry, entry_width))
        used += entry_width
    return [row for row in rows if row]


def save_frame_picture(frame: Frame, out: Path, predictions: KittiObjects | None = None) -> None:
    import io

    buffer = io.BytesIO()
    render_frame_picture(frame, predictions).save(buffer, format="PNG")
    atomic_write_bytes(out, buffer.getvalue())
