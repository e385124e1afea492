"""The torch-free labeler: one paired frame in, DetMatch labels out.

numpy + scipy + onnxruntime only. A frame goes through:
1. the 2D graph, which takes the original (H, W, 3) uint8 RGB image and does training's
   preprocessing itself (bilinear resize to the model's input size exactly as torch's
   F.interpolate(align_corners=False) does, normalisation), decodes, and returns boxes in the
   original image's pixels;
2. `detmatch.models.pillars.pillarize` (the numpy function training uses) and the 3D graph,
   which decodes LiDAR-frame boxes;
3. each detector's score threshold (the manifest's, or the call's), then
   `detmatch.pseudo_labels.match_detections` under the manifest's matching policy with the
   call's overrides: projection, Hungarian matching with tau_hung and the fallbacks to
   confident LiDAR-only labels.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from detmatch.matching_policy import MatchingPolicy, probability_threshold
from detmatch.models.pillars import batch_pillars, pillarize
from detmatch.pseudo_labels import MatchedLabels, match_detections
from detmatch.structures import Calibration, Detections
from serving.repository import (
    BATCH_AXIS,
    CHECKPOINT_FILE,
    DECODED_OUTPUTS,
    INPUTS_2D,
    INPUTS_3D,
    RepositoryError,
    load_manifest,
    served_version,
    verify_version,
    version_dir,
)
from serving.sessions import SessionSettings, make_session


@dataclass(frozen=True)
class Overrides:
    """A frame's overrides of the manifest's thresholds, all that `Labeler.label` takes (the
    wire's `serving.request.LabelOptions` carries three of them); None: the manifest's."""

    tau_hung: float | None = None
    score_threshold_2d: float | None = None
    score_threshold_3d: float | None = None
    tau_3d_outside_view: float | None = None
    outside_view_fallback: bool = True
    tau_3d_unmatched: float | None = None


@dataclass(frozen=True)
class Frame:
    """One paired frame to label: image (H, W, 3) uint8 RGB, points (N, 4) float32, its
    calibration, and its options."""

    image: np.ndarray
    points: np.ndarray
    calib: Calibration
    options: Overrides = Overrides()


@dataclass(frozen=True)
class FrameLabels:
    """The labeler's answer for one frame.

    labels: the matched labels (see MatchedLabels: LiDAR-frame 3D boxes, original-pixel 2D
    boxes, both classes and scores, cost, provenance); detections_2d / detections_3d: each
    detector's detections above its score threshold (labels index into them);
    thresholds: the values used; timings: seconds per stage ('detector2d', 'pillarize',
    'detector3d', 'matching') and in all ('total', input checks included); batch_size: the
    frames labeled in the same graph calls (`Labeler.label_batch`).
    """

    model_version: str
    classes: tuple[str, ...]
    image_size: tuple[int, int]
    labels: MatchedLabels
    detections_2d: Detections
    detections_3d: Detections
    thresholds: dict[str, float | None]
    timings: dict[str, float] = field(default_factory=dict)
    batch_size: int = 1

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def names(self) -> list[str]:
        """Class name of each label: the 3D detector's class (the 3D label's class)."""
        return [self.classes[c] for c in self.labels.class_3d]


class Labeler:
    """Both ONNX models of one repository version and the manifest that describes them."""

    def __init__(
        self,
        path: str | os.PathLike,
        settings: SessionSettings | None = None,
        check_files: bool = True,
    ) -> None:
        """path: a version directory; check_files: verify it first (`verify_version`: the
        manifest names this version, the files match their checksums)."""
        self.path = Path(path)
        self.manifest = load_manifest(self.path)
        if check_files:
            verify_version(self.path, self.manifest)
        spec_2d, spec_3d = self.manifest.model_2d, self.manifest.model_3d
        self.version: str = self.manifest.version
        self.classes: tuple[str, ...] = self.manifest.classes
        self.grid = spec_3d.preprocessing.grid.grid()
        self.score_threshold_2d = spec_2d.score_threshold
        self.score_threshold_3d = spec_3d.score_threshold
        self.policy: MatchingPolicy = self.manifest.matching.policy
        self.settings = settings or SessionSettings()
        self.session_2d = make_session(self.path / spec_2d.file, self.settings)
        self.session_3d = make_session(self.path / spec_3d.file, self.settings)
        for session, inputs, name in (
            (self.session_2d, INPUTS_2D, "detector2d"),
            (self.session_3d, INPUTS_3D, "detector3d"),
        ):
            got_inputs = tuple(i.name for i in session.get_inputs())
            got_outputs = {o.name for o in session.get_outputs()}
            if got_inputs != inputs or not set(DECODED_OUTPUTS) <= got_outputs:
                raise RepositoryError(
                    f"{name} of {self.path} has inputs {got_inputs} and outputs "
                    f"{sorted(got_outputs)}; expected {inputs} and {DECODED_OUTPUTS}"
                )
            if session.get_inputs()[0].shape[0] != BATCH_AXIS:
                raise RepositoryError(
                    f"{name} of {self.path} takes one frame, without a leading batch axis: it "
                    "was exported before batched graphs (2026-12); export its checkpoint "
                    f"again: detmatch-export --checkpoint {self.path / CHECKPOINT_FILE} "
                    f"--repository {self.path.parent}"
                )

    @classmethod
    def from_repository(
        cls,
        root: str | os.PathLike,
        version: str | int | None = None,
        settings: SessionSettings | None = None,
    ) -> Labeler:
        """A version of a repository; by default the served one (the newest promoted)."""
        if version is None:
            version = served_version(root)
            if version is None:
                raise FileNotFoundError(
                    f"model repository {root} has no promoted version; promote one "
                    "(detmatch-export --repository ROOT --promote VERSION) or name a version"
                )
        return cls(version_dir(root, version), settings)

    @property
    def tau_hung(self) -> float:
        return self.policy.tau_hung

    @property
    def tau_3d_outside_view(self) -> float | None:
        return self.policy.tau_3d_outside_view

    @property
    def tau_3d_unmatched(self) -> float | None:
        return self.policy.tau_3d_unmatched

    # --- the two models ------------------------------------------------------------------------

    def detect_2d(self, image: np.ndarray) -> Detections:
        """(H, W, 3) uint8 RGB -> the 2D graph's top-k detections (unthresholded), boxes in the
        image's pixels."""
        return self.detect_2d_batch([image])[0]

    def detect_2d_batch(self, images: Sequence[np.ndarray]) -> list[Detections]:
        """Images of one size, (H, W, 3) uint8 RGB each, in one graph call -> each image's
        top-k detections (unthresholded), boxes in its pixels."""
        if len({image.shape for image in images}) != 1:
            raise ValueError("a 2D batch holds images of one size")
        batch = np.ascontiguousarray(images[0][None] if len(images) == 1 else np.stack(images))
        return _detections(self.session_2d.run(list(DECODED_OUTPUTS), {"image": batch}))

    def detect_3d(self, points: np.ndarray) -> tuple[Detections, float, float]:
        """(N, 4) float32 LiDAR points -> (the 3D graph's top-k detections (unthresholded),
        seconds in pillarize, seconds in the graph)."""
        detections, pillarize_s, graph_s = self.detect_3d_batch([points])
        return detections[0], pillarize_s[0], graph_s

    def detect_3d_batch(
        self, clouds: Sequence[np.ndarray]
    ) -> tuple[list[Detections], list[float], float]:
        """(N, 4) float32 LiDAR point clouds in one graph call -> (each cloud's top-k
        detections (unthresholded), seconds each spent in pillarize, seconds in the graph)."""
        pillars, pillarize_s = [], []
        for points in clouds:
            mark = time.perf_counter()
            pillars.append(pillarize(points, self.grid))
            pillarize_s.append(time.perf_counter() - mark)
        mark = time.perf_counter()
        inputs = dict(zip(INPUTS_3D, batch_pillars(pillars), strict=True))
        outputs = self.session_3d.run(list(DECODED_OUTPUTS), inputs)
        return _detections(outputs), pillarize_s, time.perf_counter() - mark

    def warm_up(self, image_size: tuple[int, int] = (1242, 375)) -> None:
        """Run both graphs once on an empty frame (first runs allocate and tune kernels)."""
        self.detect_2d(np.zeros((image_size[1], image_size[0], 3), dtype=np.uint8))
        self.detect_3d(np.zeros((0, 4), dtype=np.float32))

    # --- frames ----------------------------------------------------------------------------------

    def label(
        self,
        image: np.ndarray,
        points: np.ndarray,
        calib: Calibration,
        *,
        tau_hung: float | None = None,
        score_threshold_2d: float | None = None,
        score_threshold_3d: float | None = None,
        tau_3d_outside_view: float | None = None,
        outside_view_fallback: bool = True,
        tau_3d_unmatched: float | None = None,
    ) -> FrameLabels:
        """Label one paired frame.

        image: (H, W, 3) uint8 RGB; points: (N, 4) float32 LiDAR x, y, z, intensity;
        calib: the frame's calibration. Score thresholds default to the manifest's; the
        matching thresholds are the manifest's policy with this call's overrides
        (`MatchingPolicy.with_overrides`: outside_view_fallback False makes no LiDAR-only labels
        outside the view). Raises ValueError naming the input and the problem for malformed
        inputs.
        """
        options = Overrides(
            tau_hung, score_threshold_2d, score_threshold_3d, tau_3d_outside_view,
            outside_view_fallback, tau_3d_unmatched,
        )  # fmt: skip
        (result,) = self.label_batch([Frame(image, points, calib, options)])
        if isinstance(result, Exception):
            raise result
        return result

    def label_batch(self, frames: Sequence[Frame]) -> list[FrameLabels | ValueError]:
        """Label frames together: one 2D graph call per image size and one 3D graph call for
        them all, then each frame's thresholds and matching. Each frame's answer is its own:
        the labels `label` gives it alone (to float rounding: a batch is one kernel call), or
        the ValueError its malformed input or option raises, which fails no other frame.
        Timings are per frame: the graphs' time is the batch call's divided among its frames,
        and 'total' is the batch's."""
        start = time.perf_counter()
        results: list[FrameLabels | ValueError | None] = [None] * len(frames)
        accepted: dict[int, tuple] = {}
        for i, frame in enumerate(frames):
            try:
                validate_frame(frame.image, frame.points, frame.calib)
                accepted[i] = self._thresholds(frame.options)
            except ValueError as error:
                results[i] = error
        if not accepted:
            return results
        timings: dict[int, dict[str, float]] = {i: {} for i in accepted}
        detections_2d: dict[int, Detections] = {}
        by_size: dict[tuple, list[int]] = {}
        for i in accepted:
            by_size.setdefault(frames[i].image.shape, []).append(i)
        for group in by_size.values():
            mark = time.perf_counter()
            found = self.detect_2d_batch([frames[i].image for i in group])
            share = (time.perf_counter() - mark) / len(group)
            for i, detections in zip(group, found, strict=True):
                detections_2d[i], timings[i]["detector2d"] = detections, share
        found_3d, pillarize_s, graph_s = self.detect_3d_batch([frames[i].points for i in accepted])
        for i, detections_3d, seconds in zip(accepted, found_3d, pillarize_s, strict=True):
            mark = time.perf_counter()
            frame, (policy, threshold_2d, threshold_3d) = frames[i], accepted[i]
            kept_2d = detections_2d[i][detections_2d[i].scores > threshold_2d]
            kept_3d = detections_3d[detections_3d.scores > threshold_3d]
            image_size = (int(frame.image.shape[1]), int(frame.image.shape[0]))
            labels = match_detections(kept_3d, kept_2d, frame.calib, image_size, policy)
            timings[i].update(pillarize=seconds, detector3d=graph_s / len(accepted),
                              matching=time.perf_counter() - mark)  # fmt: skip
            results[i] = FrameLabels(
                model_version=self.version,
                classes=self.classes,
                image_size=image_size,
                labels=labels,
                detections_2d=kept_2d,
                detections_3d=kept_3d,
                thresholds={
                    "tau_hung": policy.tau_hung,
                    "score_threshold_2d": threshold_2d,
                    "score_threshold_3d": threshold_3d,
                    "tau_3d_outside_view": policy.tau_3d_outside_view,
                    "tau_3d_unmatched": policy.tau_3d_unmatched,
                },
                timings=timings[i],
                batch_size=len(accepted),
            )
        end = time.perf_counter()
        for i in accepted:
            timings[i]["total"] = end - start
        return results

    def _thresholds(self, options: Overrides) -> tuple[MatchingPolicy, float, float]:
        """The matching policy and both score thresholds a frame's options give (ValueError
        naming the option for a bad value)."""
        policy = self.policy.with_overrides(
            tau_hung=options.tau_hung,
            tau_3d_outside_view=options.tau_3d_outside_view,
            tau_3d_unmatched=options.tau_3d_unmatched,
            outside_view_fallback=options.outside_view_fallback,
        )
        threshold_2d = probability_threshold(
            "score_threshold_2d",
            self.score_threshold_2d
            if options.score_threshold_2d is None
            else options.score_threshold_2d,
        )
        threshold_3d = probability_threshold(
            "score_threshold_3d",
            self.score_threshold_3d
            if options.score_threshold_3d is None
            else options.score_threshold_3d,
        )
        return policy, threshold_2d, threshold_3d


def validate_frame(image: np.ndarray, points: np.ndarray, calib: Calibration) -> None:
    """ValueError naming the field and the problem for anything the models cannot take."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image: expected a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected shape (H, W, 3) RGB, got {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"image: expected dtype uint8, got {image.dtype}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"image: empty image of shape {image.shape}")
    if not isinstance(points, np.ndarray):
        raise ValueError(f"points: expected a numpy array, got {type(points).__name__}")
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points: expected shape (N, 4) x, y, z, intensity, got {points.shape}")
    if points.dtype != np.float32:
        raise ValueError(f"points: expected dtype float32, got {points.dtype}")
    if not np.isfinite(points).all():
        bad = int(np.count_nonzero(~np.isfinite(points).all(axis=1)))
        raise ValueError(f"points: {bad} points hold NaN or Inf")
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib: expected a Calibration, got {type(calib).__name__}")


def _detections(outputs: list[np.ndarray]) -> list[Detections]:
    """A graph's batched decoded outputs -> each frame's detections."""
    boxes, scores, classes, probabilities = outputs
    return [
        Detections(
            boxes[i].astype(np.float64),
            scores[i].astype(np.float64),
            classes[i].astype(np.int64),
            probabilities[i].astype(np.float64),
        )
        for i in range(len(boxes))
    ]
