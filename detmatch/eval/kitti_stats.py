"""Numba kernels of the KITTI object evaluation: per-frame matching and score thresholds.

Ports of the official devkit's `computeStatistics` and `getThresholds` (evaluate_object.cpp),
which kitti-object-eval-python copies as `compute_statistics_jit` and `get_thresholds`. All
frames of one (class, difficulty, metric) are processed in one call on flat arrays:

- ground truth, detections and DontCare boxes of every frame are concatenated; frame f owns
  rows `gt_offsets[f]:gt_offsets[f + 1]` (likewise `dt_offsets`, `dc_offsets`);
- `overlaps` holds every frame's (num_dt, num_gt) overlap block, row-major, starting at
  `overlap_offsets[f]`;
- `ignored_gt` / `ignored_dt` use the devkit's codes: 0 = evaluated, 1 = ignored (neighbour
  class, too hard, too small: may absorb a match but is neither TP nor FP nor FN),
  -1 = another class (skipped).

The matching rules, exactly as the devkit's:
- pass 1 (no false positives): each evaluated or ignored ground-truth box, in file order, takes
  the unassigned detection with the highest score among those overlapping it by more than
  `min_overlap` (strictly); a pairing of two evaluated boxes is a TP whose score is a threshold
  candidate;
- pass 2 (per score threshold): detections scoring below the threshold are dropped; each ground
  truth box takes the evaluated detection of greatest overlap (> min_overlap), or failing that
  the first ignored detection that overlaps it; unassigned evaluated detections are FPs unless,
  for the 2D box metric only, their box lies inside a DontCare region: intersection / area of
  the detection > min_overlap.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

NUM_SAMPLE_POINTS = 41


@njit(cache=True)
def true_positive_scores(
    overlaps: np.ndarray,
    overlap_offsets: np.ndarray,
    gt_offsets: np.ndarray,
    dt_offsets: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_dt: np.ndarray,
    dt_scores: np.ndarray,
    min_overlap: float,
) -> np.ndarray:
    """Pass 1: the scores of the true positives of all frames, (T,), in frame order."""
    scores = np.empty(ignored_gt.shape[0], dtype=np.float64)
    count = 0
    num_frames = gt_offsets.shape[0] - 1
    max_dt = 0
    for f in range(num_frames):
        max_dt = max(max_dt, dt_offsets[f + 1] - dt_offsets[f])
    assigned = np.zeros(max_dt, dtype=np.bool_)
    for f in range(num_frames):
        g0, d0, o0 = gt_offsets[f], dt_offsets[f], overlap_offsets[f]
        num_gt = gt_offsets[f + 1] - g0
        num_dt = dt_offsets[f + 1] - d0
        assigned[:num_dt] = False
        for i in range(num_gt):
            if ignored_gt[g0 + i] == -1:
                continue
            det = -1
            best_score = -np.inf
            for j in range(num_dt):
                if ignored_dt[d0 + j] == -1 or assigned[j]:
                    continue
                overlap = overlaps[o0 + j * num_gt + i]
                if overlap > min_overlap and dt_scores[d0 + j] > best_score:
                    det = j
                    best_score = dt_scores[d0 + j]
            if det == -1:
                continue
            assigned[det] = True
            if ignored_gt[g0 + i] == 0 and ignored_dt[d0 + det] == 0:
                scores[count] = dt_scores[d0 + det]
                count += 1
    return scores[:count]


@njit(cache=True)
def score_thresholds(scores: np.ndarray, num_gt: int) -> np.ndarray:
    """The devkit's getThresholds: TP scores sampling recall at 0, 1/40, ..., 1; (<= 41,).

    Walking the scores in descending order, a score is kept when its recall (rank / num_gt) is
    the closest to the next recall step. With fewer than 40 evaluated ground-truth boxes the
    steps cannot all be reached: this is the official sample-count effect.
    """
    ordered = np.sort(scores)[::-1]
    thresholds = np.empty(NUM_SAMPLE_POINTS, dtype=np.float64)
    count = 0
    current_recall = 0.0
    n = ordered.shape[0]
    for i in range(n):
        left_recall = (i + 1) / num_gt
        right_recall = (i + 2) / num_gt if i < n - 1 else left_recall
        if (right_recall - current_recall) < (current_recall - left_recall) and i < n - 1:
            continue
        if count == NUM_SAMPLE_POINTS:  # cannot happen for recall <= 1; guards the buffer
            break
        thresholds[count] = ordered[i]
        count += 1
        current_recall += 1.0 / (NUM_SAMPLE_POINTS - 1.0)
    return thresholds[:count]


@njit(cache=True)
def _dontcare_covers(dt_box: np.ndarray, dc_box: np.ndarray, min_overlap: float) -> bool:
    """Intersection / area of the detection's 2D box > min_overlap (devkit criterion 0)."""
    iw = min(dt_box[2], dc_box[2]) - max(dt_box[0], dc_box[0])
    if iw <= 0:
        return False
    ih = min(dt_box[3], dc_box[3]) - max(dt_box[1], dc_box[1])
    if ih <= 0:
        return False
    area = (dt_box[2] - dt_box[0]) * (dt_box[3] - dt_box[1])
    return iw * ih / area > min_overlap


@njit(cache=True)
def precision_recall_counts(
    overlaps: np.ndarray,
    overlap_offsets: np.ndarray,
    gt_offsets: np.ndarray,
    dt_offsets: np.ndarray,
    dc_offsets: np.ndarray,
    ignored_gt: np.ndarray,
    ignored_dt: np.ndarray,
    dt_scores: np.ndarray,
    gt_alpha: np.ndarray,
    dt_alpha: np.ndarray,
    dt_bbox: np.ndarray,
    dc_bbox: np.ndarray,
    min_overlap: float,
    thresholds: np.ndarray,
    use_dontcare: bool,
) -> np.ndarray:
    """Pass 2: (T, 4) summed over frames, per threshold: TP, FP, FN, orientation similarity.

    The similarity of a TP is (1 + cos(alpha_gt - alpha_dt)) / 2 (FPs add 0); it is only
    meaningful for the 2D box metric, where the devkit computes AOS.
    """
    num_thresholds = thresholds.shape[0]
    counts = np.zeros((num_thresholds, 4), dtype=np.float64)
    num_frames = gt_offsets.shape[0] - 1
    max_dt = 0
    for f in range(num_frames):
        max_dt = max(max_dt, dt_offsets[f + 1] - dt_offsets[f])
    assigned = np.zeros(max_dt, dtype=np.bool_)
    for f in range(num_frames):
        g0, d0, c0, o0 = gt_offsets[f], dt_offsets[f], dc_offsets[f], overlap_offsets[f]
        num_gt = gt_offsets[f + 1] - g0
        num_dt = dt_offsets[f + 1] - d0
        num_dc = dc_offsets[f + 1] - c0
        for t in range(num_thresholds):
            threshold = thresholds[t]
            assigned[:num_dt] = False
            tp = 0
            fn = 0
            similarity = 0.0
            for i in range(num_gt):
                if ignored_gt[g0 + i] == -1:
                    continue
                det = -1
                max_overlap = 0.0
                assigned_ignored = False
                for j in range(num_dt):
                    code = ignored_dt[d0 + j]
                    if code == -1 or assigned[j] or dt_scores[d0 + j] < threshold:
                        continue
                    overlap = overlaps[o0 + j * num_gt + i]
                    if overlap <= min_overlap:
                        continue
                    if code == 0 and (overlap > max_overlap or assigned_ignored):
                        max_overlap = overlap
                        det = j
                        assigned_ignored = False
                    elif code == 1 and det == -1:
                        det = j
                        assigned_ignored = True
                if det == -1:
                    if ignored_gt[g0 + i] == 0:
                        fn += 1
                    continue
                assigned[det] = True
                if ignored_gt[g0 + i] == 0 and ignored_dt[d0 + det] == 0:
                    tp += 1
                    delta = gt_alpha[g0 + i] - dt_alpha[d0 + det]
                    similarity += (1.0 + math.cos(delta)) / 2.0
            fp = 0
            for j in range(num_dt):
                if assigned[j] or ignored_dt[d0 + j] != 0 or dt_scores[d0 + j] < threshold:
                    continue
                covered = False
                if use_dontcare:
                    for k in range(num_dc):
                        if _dontcare_covers(dt_bbox[d0 + j], dc_bbox[c0 + k], min_overlap):
                            covered = True
                            break
                if not covered:
                    fp += 1
            counts[t, 0] += tp
            counts[t, 1] += fp
            counts[t, 2] += fn
            counts[t, 3] += similarity
    return counts
