"""onnxruntime against PyTorch on real frames: the check an export must pass to be published.

The PyTorch side is training's own pipeline: `make_sample` (the image resized by
`image_to_tensor`, the points pillarized by `pillarize`), `collate`, the detectors' forward and
decode, and `ImageTransform.invert` for 2D boxes -- exactly what `predict_batch` runs. The
onnxruntime side gets the raw image and the pillars of the same frame.

Agreement, with close(ref, x) meaning |x - ref| <= atol + rtol * |ref| elementwise:
- raw outputs (head maps): same shape, close everywhere;
- decoded detections (the K = max_detections top-k peaks): every PyTorch detection pairs with
  a distinct onnxruntime detection of the same class whose box and score are close, and the
  pair's probability vectors are close. Pairs are found as sets, not by position: peaks whose
  scores tie (exactly or within float rounding) may come out of top-k in another order.
  Decoding is discontinuous, so a detection may stay unpaired only where float rounding
  legitimately decides it:
  (a) near tie at the top-k cut: its score is within tolerance of the other side's lowest
      (K-th) score;
  (b) near tie at the peak test (the 3x3 max-pool "NMS"): on its own side's heatmap its
      pixel differs from the largest of its 8 neighbours by at most twice the largest
      difference between the two sides' heatmaps (probabilities), so which of the two pixels
      is the local maximum is decided by rounding.
  Parity reports how many detections were excused by each rule.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import onnxruntime as ort
import torch

from detmatch.config import ExperimentConfig
from detmatch.data.dataset import collate, make_sample
from detmatch.data.kitti import KittiDataset
from detmatch.models.contract import Detector2D, Detector3D, forward_pillars
from detmatch.models.pillars import batch_pillars, pillarize
from detmatch.structures import Frame
from export.graphs import ExportCheckError
from serving.repository import DECODED_OUTPUTS, INPUTS_3D


class ParityError(ExportCheckError):
    """onnxruntime and PyTorch disagree beyond tolerance; the message lists where."""


@dataclass(frozen=True)
class Tolerance:
    rtol: float = 1e-4
    atol: float = 1e-3

    def __post_init__(self) -> None:
        if self.rtol < 0 or self.atol < 0:
            raise ValueError(f"tolerances must be >= 0, got rtol={self.rtol}, atol={self.atol}")

    def close(self, reference: np.ndarray, value: np.ndarray) -> np.ndarray:
        reference = np.asarray(reference, dtype=np.float64)
        value = np.asarray(value, dtype=np.float64)
        return np.abs(value - reference) <= self.atol + self.rtol * np.abs(reference)


@dataclass
class FrameParity:
    """One frame's comparison. max_abs_error per output ('2d/heatmap', '3d/boxes', ...);
    per model: pairs found, pairs at different top-k positions, unpaired near-ties at the
    cut; problems: every disagreement beyond tolerance (empty when the frame passes)."""

    source: str
    frame_id: str
    image_size: tuple[int, int]
    pillars: int
    max_abs_error: dict[str, float] = field(default_factory=dict)
    paired: dict[str, int] = field(default_factory=dict)
    reordered: dict[str, int] = field(default_factory=dict)
    unpaired_at_cut: dict[str, int] = field(default_factory=dict)
    unpaired_at_peak: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)


@dataclass
class ParityReport:
    tolerance: Tolerance
    frames: list[FrameParity]

    @property
    def passed(self) -> bool:
        return bool(self.frames) and not any(f.problems for f in self.frames)

    def max_abs_error(self) -> dict[str, float]:
        worst: dict[str, float] = {}
        for frame in self.frames:
            for name, error in frame.max_abs_error.items():
                worst[name] = max(worst.get(name, 0.0), error)
        return worst

    def summary(self, limit: int = 10) -> str:
        if not self.frames:
            return "no frames were checked"
        bounds = f"rtol={self.tolerance.rtol}, atol={self.tolerance.atol}"
        problems = [f"{f.source} {f.frame_id}: {p}" for f in self.frames for p in f.problems]
        if not problems:
            excused = {
                "top-k cut": sum(sum(f.unpaired_at_cut.values()) for f in self.frames),
                "peak test": sum(sum(f.unpaired_at_peak.values()) for f in self.frames),
            }
            paired = sum(sum(f.paired.values()) for f in self.frames)
            return (
                f"{len(self.frames)} frames agree within {bounds}: {paired} detections paired, "
                f"near ties excused at the top-k cut {excused['top-k cut']}, at the peak test "
                f"{excused['peak test']}"
            )
        shown = "\n  ".join(problems[:limit])
        more = f"\n  ... and {len(problems) - limit} more" if len(problems) > limit else ""
        return f"{len(problems)} disagreements beyond {bounds}:\n  {shown}{more}"

    def to_json(self) -> dict:
        return {
            "passed": self.passed,
            "rtol": self.tolerance.rtol,
            "atol": self.tolerance.atol,
            "max_abs_error": self.max_abs_error(),
            "frames": [asdict(f) for f in self.frames],
        }


# --- frames --------------------------------------------------------------------------------------


def load_parity_frames(
    synthetic: int, sources: Sequence[str | os.PathLike], per_source: int, seed: int = 0
) -> list[tuple[str, Frame]]:
    """(source, frame) pairs: `synthetic` rendered frames (alternately half and full KITTI
    resolution), then up to `per_source` frames of each KITTI-layout directory."""
    frames: list[tuple[str, Frame]] = []
    if synthetic:
        from detmatch.data.synth.dataset import generate_frame

        for index in range(synthetic):
            resolution = ("half", "full")[index % 2]
            frame = generate_frame(seed, index, resolution).frame
            frames.append((f"synthetic seed {seed} {resolution}", frame))
    for source in sources:
        dataset = KittiDataset(source)
        ids = dataset.ids()[:per_source]
        if not ids:
            raise FileNotFoundError(f"{source} has no frames (training/image_2/*.png)")
        frames.extend((str(source), dataset.load_frame(i, with_labels=False)) for i in ids)
    return frames


# --- comparisons -----------------------------------------------------------------------------


def compare_raw(
    name: str, reference: np.ndarray, value: np.ndarray, tolerance: Tolerance
) -> tuple[float, list[str]]:
    """(max absolute error, problems) of one raw output."""
    if reference.shape != value.shape:
        return float("inf"), [f"{name}: shape {value.shape}, PyTorch has {reference.shape}"]
    error = np.abs(value.astype(np.float64) - reference.astype(np.float64))
    max_error = float(error.max()) if error.size else 0.0
    bad = ~tolerance.close(reference, value)
    if bad.any():
        return max_error, [
            f"{name}: {int(bad.sum())} of {bad.size} values beyond tolerance "
            f"(max abs error {max_error:.3g})"
        ]
    return max_error, []


class PeakTies:
    """Which peaks of a (C, H, W) probability heatmap are near ties at the 3x3 max-pool test:
    the pixel differs from the largest of its 8 neighbours by at most `margin`."""

    def __init__(self, heat: np.ndarray, margin: float) -> None:
        heat = np.asarray(heat, dtype=np.float64)
        padded = np.pad(heat, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
        height, width = heat.shape[1:]
        neighbours = np.full_like(heat, -np.inf)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                if (dy, dx) != (1, 1):
                    shifted = padded[:, dy : dy + height, dx : dx + width]
                    neighbours = np.maximum(neighbours, shifted)
        self.heat = heat.reshape(heat.shape[0], -1)
        self.near_tie = (np.abs(heat - neighbours) <= margin).reshape(heat.shape[0], -1)

    def excuses(self, class_id: int, score: float, rounding: float = 1e-6) -> bool:
        """A detection of this class and score sits on a near-tie pixel."""
        pixels = np.abs(self.heat[class_id] - score) <= rounding
        return bool((pixels & self.near_tie[class_id]).any())


def compare_decoded(
    name: str,
    reference: dict[str, np.ndarray],
    value: dict[str, np.ndarray],
    tolerance: Tolerance,
    ties: tuple[PeakTies, PeakTies] | None = None,
) -> tuple[dict[str, float], list[str]]:
    """Pair decoded detections as sets (see the module docstring); ties are the (PyTorch,
    onnxruntime) peak-test near ties, None to excuse none. Returns counts ('paired',
    'reordered', 'unpaired_at_cut', 'unpaired_at_peak'), the largest differences within
    pairs ('max_abs_error/boxes', '.../scores', '.../probabilities'), and problems."""
    problems = []
    if reference["boxes"].shape != value["boxes"].shape:
        shape = value["boxes"].shape
        return {}, [f"{name}: boxes of shape {shape}, PyTorch has {reference['boxes'].shape}"]
    taken = np.zeros(len(value["scores"]), dtype=bool)
    pairs: list[tuple[int, int]] = []
    unpaired_reference = []
    for i in np.argsort(-reference["scores"], kind="stable"):
        candidates = np.flatnonzero(
            ~taken
            & (value["classes"] == reference["classes"][i])
            & tolerance.close(reference["boxes"][i][None], value["boxes"]).all(axis=1)
            & tolerance.close(reference["scores"][i], value["scores"])
        )
        if not len(candidates):
            unpaired_reference.append(int(i))
            continue
        distance = np.abs(value["boxes"][candidates] - reference["boxes"][i]).max(axis=1)
        j = int(candidates[np.argmin(distance)])
        taken[j] = True
        pairs.append((int(i), j))

    def at_cut(score: float, other_scores: np.ndarray) -> bool:
        cut = float(other_scores.min()) if len(other_scores) else -np.inf
        return score <= cut + tolerance.atol + tolerance.rtol * abs(cut)

    counts = {"paired": len(pairs), "reordered": sum(i != j for i, j in pairs),
              "unpaired_at_cut": 0, "unpaired_at_peak": 0}  # fmt: skip
    ties_reference, ties_value = ties if ties is not None else (None, None)
    unpaired_value = np.flatnonzero(~taken).tolist()
    for side, rows, own, other, own_ties in (
        ("PyTorch", unpaired_reference, reference, value, ties_reference),
        ("onnxruntime", unpaired_value, value, reference, ties_value),
    ):
        for row in rows:
            class_id, score = int(own["classes"][row]), float(own["scores"][row])
            if at_cut(score, other["scores"]):
                counts["unpaired_at_cut"] += 1
            elif own_ties is not None and own_ties.excuses(class_id, score):
                counts["unpaired_at_peak"] += 1
            else:
                problems.append(
                    f"{name}: {side} detection {row} (class {class_id}, score {score:.6f}, box "
                    f"{np.round(own['boxes'][row], 3).tolist()}) has no counterpart"
                )
    for i, j in pairs:
        if not tolerance.close(reference["probabilities"][i], value["probabilities"][j]).all():
            problems.append(f"{name}: probabilities of detection {i} differ beyond tolerance")
    paired = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    rows, cols = paired[:, 0], paired[:, 1]
    for key in ("boxes", "scores", "probabilities"):
        difference = np.abs(value[key][cols].astype(np.float64) - reference[key][rows])
        counts[f"max_abs_error/{key}"] = float(difference.max()) if difference.size else 0.0
    return counts, problems


# --- both models on frames ---------------------------------------------------------------------


def torch_reference(
    model_2d: Detector2D, model_3d: Detector3D, config: ExperimentConfig, frame: Frame
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], int]:
    """Training's pipeline on one frame: (2D outputs, 3D outputs, number of pillars). 2D boxes
    are mapped back to original pixels."""
    sample = make_sample(
        frame, config.data.classes, config.data.image_size, model_3d.grid, flip=False
    )
    batch = collate([sample])
    model_2d.eval()
    model_3d.eval()
    with torch.no_grad():
        maps_2d = model_2d(batch.images)
        decoded_2d = model_2d.decode(maps_2d)
        maps_3d = forward_pillars(model_3d, batch.pillars)
        decoded_3d = model_3d.decode(maps_3d)
    out_2d = {n: t[0].numpy() for n, t in zip(DECODED_OUTPUTS, decoded_2d, strict=True)}
    out_2d["boxes"] = sample.image_transform.to_image(out_2d["boxes"].astype(np.float64))
    out_2d.update({n: t.numpy() for n, t in zip(model_2d.output_names, maps_2d, strict=True)})
    out_3d = {n: t[0].numpy() for n, t in zip(DECODED_OUTPUTS, decoded_3d, strict=True)}
    out_3d.update({n: t.numpy() for n, t in zip(model_3d.output_names, maps_3d, strict=True)})
    return out_2d, out_3d, len(sample.pillars)


def check_parity(
    session_2d: ort.InferenceSession,
    session_3d: ort.InferenceSession,
    model_2d: Detector2D,
    model_3d: Detector3D,
    config: ExperimentConfig,
    frames: Sequence[tuple[str, Frame]],
    tolerance: Tolerance,
) -> ParityReport:
    """Compare both graphs with PyTorch on every frame."""
    names_2d = DECODED_OUTPUTS + model_2d.output_names
    names_3d = DECODED_OUTPUTS + model_3d.output_names
    results = []
    for source, frame in frames:
        reference_2d, reference_3d, pillars = torch_reference(model_2d, model_3d, config, frame)
        # A batch of one frame: the decoded outputs' batch axis dropped, the raw maps' kept
        # (the reference's have theirs).
        outputs_2d = session_2d.run(list(names_2d), {"image": frame.image[None]})
        arrays = batch_pillars([pillarize(frame.points, model_3d.grid)])
        outputs_3d = session_3d.run(list(names_3d), dict(zip(INPUTS_3D, arrays, strict=True)))
        got_2d = {n: o[0] if n in DECODED_OUTPUTS else o
                  for n, o in zip(names_2d, outputs_2d, strict=True)}  # fmt: skip
        got_3d = {n: o[0] if n in DECODED_OUTPUTS else o
                  for n, o in zip(names_3d, outputs_3d, strict=True)}  # fmt: skip
        result = FrameParity(source, frame.frame_id, frame.image_size, pillars)
        for model, reference, got, raw in (
            ("2d", reference_2d, got_2d, model_2d.output_names),
            ("3d", reference_3d, got_3d, model_3d.output_names),
        ):
            for name in raw:
                error, problems = compare_raw(f"{model}/{name}", reference[name], got[name],
                                              tolerance)  # fmt: skip
                result.max_abs_error[f"{model}/{name}"] = error
                result.problems.extend(problems)
            ties = None
            if "heatmap" in raw:  # a peak-decoding detector: near ties may be excused
                heat_reference = _sigmoid(reference["heatmap"][0])
                heat_got = _sigmoid(got["heatmap"][0])
                margin = 2 * float(np.abs(heat_reference - heat_got).max()) + 1e-7
                ties = (PeakTies(heat_reference, margin), PeakTies(heat_got, margin))
            counts, problems = compare_decoded(model, reference, got, tolerance, ties)
            for key in ("boxes", "scores", "probabilities"):
                result.max_abs_error[f"{model}/{key}"] = counts.get(f"max_abs_error/{key}", 0.0)
            result.paired[model] = int(counts.get("paired", 0))
            result.reordered[model] = int(counts.get("reordered", 0))
            result.unpaired_at_cut[model] = int(counts.get("unpaired_at_cut", 0))
            result.unpaired_at_peak[model] = int(counts.get("unpaired_at_peak", 0))
            result.problems.extend(problems)
        results.append(result)
    return ParityReport(tolerance, results)


def _sigmoid(logits: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(logits, dtype=np.float64)))
