"""The detection evaluator of the Height3 paper (Section V): recall and AP@R40 by range and level.

Every rule is written down, with examples, in docs/evaluation.md. In short, for each range
(small / moderate / large) and level (all / top3 / top6) of `detbench.data.regions`:

- the *evaluated* ground truth of a frame is the set of its vehicles in that range and level
  that the LiDAR detected (`detbench.data.regions`: >= 1 point inside the box with its bottom
  raised 0.05 m); every
  other ground-truth box of the frame is an *ignored* box;
- predictions with score < `score_threshold` are dropped; the rest, highest score first
  (ties: input order), are matched greedily: a prediction takes the still-unmatched evaluated
  box with the highest IoU >= `iou_threshold` (a TP); failing that it is ignored if its IoU
  with an ignored box is >= `iou_threshold`; failing that it is an FP when its centre lies
  in the range and ignored when it does not. A second prediction on an already matched box
  is therefore an FP (that box is evaluated, not ignored);
- recall = TP / LiDAR-detected count (paper eq. 2); AP@R40 (eq. 3) is the mean over the 40
  recall levels r = 1/40 .. 1 of the interpolated precision max_{r' >= r} p(r'), over the
  non-ignored predictions of all frames pooled and ranked by score (ties: frame order, then
  input order within the frame); a recall level never reached counts 0.

Speed: each frame's IoU matrix (kept predictions x all ground truth) is computed once and
reused by the nine range/level pairs; the greedy matching of all frames and pairs runs in one
numba kernel, parallel over frames.

The input type, `EvalFrame`, is in detbench/eval/eval_frame.py; the prediction files on disk
(`<frame_id>.txt`) in detbench/eval/prediction_files.py.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from numba import njit, prange

from detbench.config import ConfigError, section_with_defaults, shipped_default, shipped_defaults
from detbench.data.layout import SPLIT_CHOICES
from detbench.data.regions import (
    DETECTED_MIN_POINTS, LEVELS, RANGE_NAMES, importance_mask, in_range,
)
from detbench.data.detections import Detections
from detbench.eval.ap_bootstrap import AP_RECALL_LEVELS, ap_ranking, weighted_ap_r40
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights
from detbench.eval.eval_frame import EvalFrame, as_eval_frames, eval_frame_from_frame

IOU_KINDS: tuple[str, ...] = ("3d", "bev")
# An IoU counts as reaching the threshold when IoU >= threshold - IOU_EPS. The exact IoU of
# boxes built to overlap by exactly the threshold (a box inside another with half its volume
# has IoU 0.5) is computed with rounding errors of ~1e-15; the tolerance makes such cases
# deterministic without changing any IoU that is meaningfully below the threshold.
IOU_EPS = 1e-9
# Extra variants computed by `evaluate(..., extras=True)`: (iou_kind, iou_threshold).
DEFAULT_EXTRAS: tuple[tuple[str, float], ...] = (("3d", 0.7), ("bev", 0.7), ("3d", 0.5), ("bev", 0.5))

# Per-prediction outcome codes of the matching kernel.
FP, TP, IGNORED = 0, 1, -1

PAIRS: tuple[tuple[str, str], ...] = tuple((r, lv) for r in RANGE_NAMES for lv in LEVELS)


# --------------------------------------------------------------------------------------------
# AP@R40
# --------------------------------------------------------------------------------------------

def ap_r40_ranked(is_tp: Sequence[bool] | np.ndarray, num_gt: int) -> float | None:
    """AP@R40 of a list of predictions already ranked best first.

    is_tp: (K,) bool, True for a TP and False for an FP (ignored predictions must be removed
        before). num_gt: number of evaluated ground-truth boxes (the recall denominator).
    Returns the mean over r in {1/40, ..., 40/40} of max_{k: recall_k >= r} precision_k, where
    precision_k = TP_k / k and recall_k = TP_k / num_gt after the first k predictions; a
    level never reached contributes 0. Returns None when num_gt == 0 (nothing to evaluate).
    The comparison recall_k >= r is done in integers (40 TP_k >= i num_gt), so no rounding.
    """
    num_gt = int(num_gt)
    if num_gt < 0:
        raise ValueError(f"num_gt must be >= 0, got {num_gt}")
    if num_gt == 0:
        return None
    tp = np.asarray(is_tp, dtype=bool).reshape(-1)
    n = tp.size
    if n == 0:
        return 0.0
    tp_cum = np.cumsum(tp, dtype=np.int64)
    if tp_cum[-1] > num_gt:
        raise ValueError(f"{int(tp_cum[-1])} true positives for only {num_gt} ground-truth boxes; "
                         f"each box can be matched once")
    precision = tp_cum / np.arange(1, n + 1, dtype=np.float64)
    best_after = np.maximum.accumulate(precision[::-1])[::-1]  # max precision at rank >= k
    need = np.arange(1, AP_RECALL_LEVELS + 1, dtype=np.int64) * num_gt
    first = np.searchsorted(tp_cum * AP_RECALL_LEVELS, need, side="left")
    reached = first < n
    interp = np.where(reached, best_after[np.minimum(first, n - 1)], 0.0)
    return float(interp.sum() / AP_RECALL_LEVELS)


def ap_r40(scores: Sequence[float] | np.ndarray, is_tp: Sequence[bool] | np.ndarray, num_gt: int) -> float | None:
    """AP@R40 of unranked predictions: ranks by score, highest first, ties in the given order.

    scores: (K,) scores; is_tp: (K,) bool (TP True, FP False); num_gt as in `ap_r40_ranked`.
    """
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    is_tp = np.asarray(is_tp, dtype=bool).reshape(-1)
    if scores.shape != is_tp.shape:
        raise ValueError(f"scores {scores.shape} and is_tp {is_tp.shape} must have the same length")
    order = np.argsort(-scores, kind="stable")
    return ap_r40_ranked(is_tp[order], num_gt)


# --------------------------------------------------------------------------------------------
# Matching kernel
# --------------------------------------------------------------------------------------------

@njit(cache=True, parallel=True)
def _match_kernel(iou_flat, iou_off, pred_off, gt_off, gt_eval, pred_in_range, pair_range, thr):
    """Greedy matching of every frame and every range/level pair.

    iou_flat: concatenation of each frame's (m_f, n_f) IoU matrix (row = prediction in ranked
    order, column = ground truth), starting at iou_off[f]. pred_off, gt_off: (F + 1,) offsets of
    each frame's predictions (ranked, score-filtered) and ground truth. gt_eval: (N, P) bool,
    ground truth evaluated in pair p. pred_in_range: (M, R) bool, prediction centre in range r.
    pair_range: (P,) range index of each pair. thr: IoU threshold (tolerance already applied).
    Returns flags (M, P) int8: 1 TP, 0 FP, -1 ignored.
    """
    num_frames = pred_off.shape[0] - 1
    num_pairs = gt_eval.shape[1]
    flags = np.full((pred_off[num_frames], num_pairs), -1, dtype=np.int8)
    for f in prange(num_frames):
        p0 = pred_off[f]
        m = pred_off[f + 1] - p0
        g0 = gt_off[f]
        n = gt_off[f + 1] - g0
        if m == 0:
            continue
        base = iou_off[f]
        matched = np.zeros(n, dtype=np.bool_)
        for p in range(num_pairs):
            for i in range(n):
                matched[i] = False
            r = pair_range[p]
            for j in range(m):
                best = -1
                best_iou = -1.0
                on_ignored = False
                row = base + j * n
                for i in range(n):
                    v = iou_flat[row + i]
                    if v >= thr:
                        if gt_eval[g0 + i, p]:
                            if not matched[i] and v > best_iou:
                                best = i
                                best_iou = v
                        else:
                            on_ignored = True
                if best >= 0:
                    matched[best] = True
                    flags[p0 + j, p] = 1
                elif on_ignored:
                    flags[p0 + j, p] = -1
                elif pred_in_range[p0 + j, r]:
                    flags[p0 + j, p] = 0
                else:
                    flags[p0 + j, p] = -1
    return flags


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------

def _iou_function(kind: str):
    if kind not in IOU_KINDS:
        raise ValueError(f"unknown iou_kind {kind!r}; use one of {', '.join(IOU_KINDS)}")
    from detbench.ops import boxes_iou3d, boxes_iou_bev  # on first use: detbench.ops loads torch

    return boxes_iou3d if kind == "3d" else boxes_iou_bev


def _check_threshold(value: float, name: str, low_open: bool) -> float:
    v = float(value)
    if not math.isfinite(v) or v > 1.0 or (v <= 0.0 if low_open else v < 0.0):
        rng = "(0, 1]" if low_open else "[0, 1]"
        raise ValueError(f"{name} must be a number in {rng}, got {value!r}")
    return v


EVAL_DEFAULTS: dict[str, Any] = shipped_defaults("eval")  # configs/default.yaml `eval:`, each key documented there


@dataclass(frozen=True)
class EvalConfig:
    """The `eval` section of a run config, checked before any training starts (defaults and units:
    configs/default.yaml)."""

    split: str  # train | test | all
    iou_threshold: float  # in (0, 1]
    score_threshold: float  # in [0, 1]
    max_frames: int  # 0 = all

    @classmethod
    def from_dict(cls, d: Mapping | None, where: str = "eval") -> EvalConfig:
        """Parse the section (missing keys: EVAL_DEFAULTS); ConfigError naming the key on a bad value."""
        v = section_with_defaults(d, EVAL_DEFAULTS, where)
        if v["split"] not in SPLIT_CHOICES:
            raise ConfigError(f"{where}.split must be one of {', '.join(SPLIT_CHOICES)}, got {v['split']!r}")
        if v["max_frames"] < 0:
            raise ConfigError(f"{where}.max_frames must be >= 0 (0 = every frame), got {v['max_frames']!r}")
        try:
            iou = _check_threshold(v["iou_threshold"], f"{where}.iou_threshold", low_open=True)
            score = _check_threshold(v["score_threshold"], f"{where}.score_threshold", low_open=False)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        return cls(split=v["split"], iou_threshold=iou, score_threshold=score, max_frames=int(v["max_frames"]))


class _Prepared(NamedTuple):
    num_frames: int
    gt_off: np.ndarray  # (F+1,)
    pred_off: np.ndarray  # (F+1,)
    gt_level: np.ndarray  # (N, P) bool: in range and level
    gt_eval: np.ndarray  # (N, P) bool: in range, level and LiDAR-detected
    pred_boxes: np.ndarray  # (M, 7) kept predictions, ranked within each frame
    pred_scores: np.ndarray  # (M,)
    pred_in_range: np.ndarray  # (M, R) bool
    gt_boxes: np.ndarray  # (N, 7)


def _prepare(frames: Sequence[EvalFrame], score_threshold: float) -> _Prepared:
    num_frames = len(frames)
    n_gt = np.array([len(f.gt_boxes) for f in frames], dtype=np.int64)
    n_pred = np.array([len(f.pred_boxes) for f in frames], dtype=np.int64)
    gt_off = np.zeros(num_frames + 1, dtype=np.int64)
    np.cumsum(n_gt, out=gt_off[1:])

    def cat(arrays, shape_tail, dtype):
        arrays = [a for a in arrays if len(a)]
        return np.concatenate(arrays) if arrays else np.zeros((0, *shape_tail), dtype=dtype)

    gt_boxes = cat([f.gt_boxes for f in frames], (7,), np.float64)
    gt_points = cat([f.gt_num_points for f in frames], (), np.int64)
    gt_lane = cat([f.gt_lane for f in frames], (), np.int64)
    all_boxes = cat([f.pred_boxes for f in frames], (7,), np.float64)
    all_scores = cat([f.pred_scores for f in frames], (), np.float64)

    # Drop low scores, then rank: frame order, score descending, ties by input order.
    pred_frame = np.repeat(np.arange(num_frames, dtype=np.int64), n_pred)
    kept = np.flatnonzero(all_scores >= score_threshold)
    kept = kept[np.argsort(-all_scores[kept], kind="stable")]
    kept = kept[np.argsort(pred_frame[kept], kind="stable")]
    pred_boxes = np.ascontiguousarray(all_boxes[kept])
    pred_scores = all_scores[kept]
    pred_off = np.zeros(num_frames + 1, dtype=np.int64)
    np.cumsum(np.bincount(pred_frame[kept], minlength=num_frames), out=pred_off[1:])

    # Ranges are per box (one vectorised call over all frames); Top-k is per frame.
    pred_in_range = np.zeros((len(pred_boxes), len(RANGE_NAMES)), dtype=bool)
    gt_level = np.zeros((len(gt_boxes), len(PAIRS)), dtype=bool)
    for ri, r in enumerate(RANGE_NAMES):
        if len(pred_boxes):
            pred_in_range[:, ri] = in_range(pred_boxes, r)
        if not len(gt_boxes):
            continue
        cand = in_range(gt_boxes, r)
        for li, lv in enumerate(LEVELS):
            p = ri * len(LEVELS) + li
            if lv == "all":
                gt_level[:, p] = cand
                continue
            for f in range(num_frames):
                a, b = gt_off[f], gt_off[f + 1]
                if b > a and cand[a:b].any():
                    gt_level[a:b, p] = importance_mask(gt_boxes[a:b], gt_lane[a:b], cand[a:b], lv)
    gt_eval = gt_level & (gt_points >= DETECTED_MIN_POINTS)[:, None]
    return _Prepared(num_frames, gt_off, pred_off, gt_level, gt_eval, pred_boxes, pred_scores,
                     pred_in_range, gt_boxes)


def _iou_blocks(prep: _Prepared, kind: str, progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's (m_f, n_f) IoU matrix, flattened into one buffer, and its offsets."""
    iou_fn = _iou_function(kind)
    m = np.diff(prep.pred_off)
    n = np.diff(prep.gt_off)
    iou_off = np.zeros(prep.num_frames + 1, dtype=np.int64)
    np.cumsum(m * n, out=iou_off[1:])
    flat = np.zeros(int(iou_off[-1]), dtype=np.float64)
    frames_iter: Iterable[int] = np.flatnonzero((m > 0) & (n > 0)).tolist()
    if progress:
        from tqdm import tqdm

        frames_iter = tqdm(frames_iter, desc=f"IoU {kind}", unit="frame", leave=False)
    for f in frames_iter:
        a, b = prep.pred_off[f], prep.pred_off[f + 1]
        c, d = prep.gt_off[f], prep.gt_off[f + 1]
        block = np.asarray(iou_fn(prep.pred_boxes[a:b], prep.gt_boxes[c:d]), dtype=np.float64)
        flat[iou_off[f]:iou_off[f + 1]] = block.reshape(-1)
    return flat, iou_off


def _results(prep: _Prepared, flags: np.ndarray) -> dict:
    """The nested results dict {range_name: {level: {...}}} from the kernel's flags."""
    totals = prep.gt_level.sum(axis=0)
    detected = prep.gt_eval.sum(axis=0)
    out: dict[str, dict[str, dict]] = {r: {} for r in RANGE_NAMES}
    for p, (r, lv) in enumerate(PAIRS):
        col = flags[:, p] if len(flags) else np.zeros(0, dtype=np.int8)
        keep = col >= 0
        is_tp = col[keep] == TP
        tp = int(is_tp.sum())
        fp = int(keep.sum()) - tp
        total, det = int(totals[p]), int(detected[p])
        # The kept predictions are already in frame order, ranked within each frame; a stable
        # sort by score therefore breaks ties by frame order, then by input order.
        ap = ap_r40(prep.pred_scores[keep], is_tp, det) if det else None
        out[r][lv] = {
            "total": total,
            "lidar_detected": det,
            "ldr": det / total if total else None,
            "tp": tp,
            "fp": fp,
            "recall": tp / det if det else None,
            "ap_r40": ap,
        }
    return out


def _bootstrap(prep: _Prepared, flags: np.ndarray, clusters: Sequence, replicates: int, seed: int,
               confidence: float = 0.95) -> dict:
    """Percentile bootstrap over clusters (scenes) of recall and AP@R40 for each range/level.

    A replicate draws as many clusters as there are, with replacement; a frame drawn k times
    counts its ground truth and its predictions k times. Also returns the per-cluster TP and
    LiDAR-detected counts and the ranked detections of AP@R40 (detbench.eval.ap_bootstrap), so that
    two reports on the same frames can be compared in pairs.
    """
    labels = [str(c) for c in clusters]
    names = sorted(set(labels))
    index = {c: i for i, c in enumerate(names)}
    frame_cluster = np.array([index[c] for c in labels], dtype=np.int64)
    n = len(names)
    gt_frame = np.repeat(np.arange(prep.num_frames), np.diff(prep.gt_off))
    pred_frame = np.repeat(np.arange(prep.num_frames), np.diff(prep.pred_off))
    det_cluster = np.zeros((n, len(PAIRS)), dtype=np.int64)  # LiDAR-detected boxes per cluster
    tp_cluster = np.zeros((n, len(PAIRS)), dtype=np.int64)
    if len(gt_frame):
        np.add.at(det_cluster, frame_cluster[gt_frame], prep.gt_eval.astype(np.int64))
    if len(flags):
        np.add.at(tp_cluster, frame_cluster[pred_frame], (flags == TP).astype(np.int64))
    out: dict = {"method": "percentile bootstrap over scenes (scenes resampled with replacement)",
                 "num_clusters": n, "replicates": int(replicates), "seed": int(seed), "confidence": confidence,
                 "clusters": names,
                 "per_cluster": {r: {lv: {"tp": tp_cluster[:, p].tolist(), "lidar_detected": det_cluster[:, p].tolist()}
                                     for lv in LEVELS for p in [PAIRS.index((r, lv))]} for r in RANGE_NAMES},
                 "ap_ranking": ap_ranking(flags, prep.pred_scores, frame_cluster[pred_frame], PAIRS),
                 "results": {r: {} for r in RANGE_NAMES}}
    ok = n >= 2 and replicates > 0
    if not ok:
        out["note"] = "needs at least 2 scenes and replicates > 0"
    draws = (scene_bootstrap_weights(n, replicates, seed).astype(np.int64) if ok
             else np.zeros((0, n), np.int64))

    def interval(samples: np.ndarray) -> list | None:
        return percentile_interval(samples, confidence) if ok else None

    for p, (r, lv) in enumerate(PAIRS):
        col = flags[:, p] if len(flags) else np.zeros(0, dtype=np.int8)
        keep = np.flatnonzero(col >= 0)
        order = keep[np.argsort(-prep.pred_scores[keep], kind="stable")]
        tp_ranked = col[order] == TP
        cl_ranked = frame_cluster[pred_frame[order]]
        recalls = bootstrap_ratios(draws, tp_cluster[:, p], det_cluster[:, p])
        aps = weighted_ap_r40(tp_ranked, cl_ranked, det_cluster[:, p], draws)
        out["results"][r][lv] = {"recall_ci95": interval(recalls), "ap_r40_ci95": interval(aps)}
    return out


def _parse_extras(extras, iou_kind: str, iou_threshold: float) -> list[tuple[str, float]]:
    if extras is False or extras is None:
        return []
    pairs = DEFAULT_EXTRAS if extras is True else extras
    out = []
    for item in pairs:
        try:
            kind, thr = item
        except (TypeError, ValueError):
            raise ValueError(f"extras entries must be (iou_kind, iou_threshold) pairs, got {item!r}") from None
        if kind not in IOU_KINDS:
            raise ValueError(f"extras: unknown iou_kind {kind!r}; use one of {', '.join(IOU_KINDS)}")
        thr = _check_threshold(thr, "extras iou_threshold", low_open=True)
        if (kind, thr) != (iou_kind, iou_threshold) and (kind, thr) not in out:
            out.append((kind, thr))
    return out


def extra_key(iou_kind: str, iou_threshold: float) -> str:
    """Name of an extra variant in `report["extras"]`, e.g. "bev_0.7" or "3d_0.5"."""
    return f"{iou_kind}_{iou_threshold:g}"


def evaluate(
    frames: Iterable[EvalFrame],
    iou_threshold: float | None = None,
    score_threshold: float | None = None,
    iou_kind: str = "3d",
    extras: bool | Sequence[tuple[str, float]] = False,
    progress: bool = False,
    timings: dict | None = None,
    bootstrap: int = 0,
    bootstrap_seed: int = 0,
) -> dict:
    """Recall and AP@R40 per range and level, as in the paper's Section V.

    frames: EvalFrame objects (or dicts of their fields), one per frame.
    iou_threshold: IoU (fraction) a prediction needs with a box to match it (>=, see IOU_EPS);
        None: configs/default.yaml `eval.iou_threshold` (the paper's 0.7).
    score_threshold: predictions with score < this are dropped before matching; None:
        `eval.score_threshold` (the paper's 0.1).
    iou_kind: "3d" (rotated 3D IoU) or "bev" (rotated bird's-eye-view IoU).
    extras: True adds report["extras"] with the variants of DEFAULT_EXTRAS other than the
        main one (3D/BEV at IoU 0.7 and 0.5); or a list of (iou_kind, iou_threshold) pairs.
        Each extra is {"iou_kind", "iou_threshold", "results"} with the main results layout.
    progress: show tqdm progress bars over frames.
    timings: if a dict is given, it receives the wall seconds of each stage
        ("prepare", "iou", "match", "ap").
    bootstrap: replicates of a percentile bootstrap over scenes (`EvalFrame.scene_id`; a frame
        without one is its own cluster) of the main variant's recall and AP@R40; 0 = none.
        The report then has "uncertainty" = {"method", "num_clusters", "replicates", "seed",
        "confidence", "clusters", "per_cluster": {range: {level: {"tp", "lidar_detected"}}},
        "ap_ranking": {"scene", "outcome": {range: {level: text}}} (the counted detections in AP
        order with their scenes and outcomes, detbench.eval.ap_bootstrap), "results": {range:
        {level: {"recall_ci95", "ap_r40_ci95"}}}} (intervals [lo, hi] or null when fewer than 2 scenes).

    Returns {"iou_threshold", "iou_kind", "score_threshold", "num_frames",
    "results": {range_name: {level: {"total", "lidar_detected", "ldr", "tp", "fp", "recall",
    "ap_r40"}}}} (+ "extras"). Counts are numbers of vehicles (tp, fp: predictions); ldr,
    recall and ap_r40 are fractions in [0, 1], None where their denominator is 0.
    """
    iou_threshold = _check_threshold(shipped_default("eval.iou_threshold", iou_threshold), "iou_threshold",
                                     low_open=True)
    score_threshold = float(shipped_default("eval.score_threshold", score_threshold))
    if not math.isfinite(score_threshold):
        raise ValueError(f"score_threshold must be a finite number, got {score_threshold!r}")
    if iou_kind not in IOU_KINDS:
        raise ValueError(f"unknown iou_kind {iou_kind!r}; use one of {', '.join(IOU_KINDS)}")
    extra_list = _parse_extras(extras, iou_kind, iou_threshold)
    t = {"prepare": 0.0, "iou": 0.0, "match": 0.0, "ap": 0.0}

    t0 = time.perf_counter()
    frame_list = as_eval_frames(frames)
    prep = _prepare(frame_list, score_threshold)
    t["prepare"] += time.perf_counter() - t0

    pair_range = np.array([RANGE_NAMES.index(r) for r, _ in PAIRS], dtype=np.int64)
    iou_cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def run(kind: str, thr: float) -> dict:
        t1 = time.perf_counter()
        if kind not in iou_cache:
            iou_cache[kind] = _iou_blocks(prep, kind, progress)
        flat, iou_off = iou_cache[kind]
        t2 = time.perf_counter()
        flags = _match_kernel(flat, iou_off, prep.pred_off, prep.gt_off, prep.gt_eval,
                              prep.pred_in_range, pair_range, thr - IOU_EPS)
        t3 = time.perf_counter()
        res = _results(prep, flags)
        t4 = time.perf_counter()
        t["iou"] += t2 - t1
        t["match"] += t3 - t2
        t["ap"] += t4 - t3
        return res

    report = {
        "iou_threshold": iou_threshold,
        "iou_kind": iou_kind,
        "score_threshold": score_threshold,
        "num_frames": prep.num_frames,
        "results": run(iou_kind, iou_threshold),
    }
    if int(bootstrap) < 0:
        raise ValueError(f"bootstrap must be >= 0 replicates, got {bootstrap}")
    if bootstrap:
        flags = _match_kernel(*iou_cache[iou_kind], prep.pred_off, prep.gt_off, prep.gt_eval,
                              prep.pred_in_range, pair_range, iou_threshold - IOU_EPS)
        clusters = [f.scene_id if f.scene_id is not None else f"frame:{i}" for i, f in enumerate(frame_list)]
        report["uncertainty"] = _bootstrap(prep, flags, clusters, int(bootstrap), int(bootstrap_seed))
    if extra_list:
        report["extras"] = {
            extra_key(kind, thr): {"iou_kind": kind, "iou_threshold": thr, "results": run(kind, thr)}
            for kind, thr in extra_list
        }
    if timings is not None:
        timings.update(t)
    return report


# --------------------------------------------------------------------------------------------
# A dataset's frames and their predictions
# --------------------------------------------------------------------------------------------

def evaluate_predictions(
    dataset,
    predictions_by_frame_id: Mapping[str, Detections | tuple],
    iou_threshold: float | None = None,
    score_threshold: float | None = None,
    iou_kind: str = "3d",
    extras: bool | Sequence[tuple[str, float]] = True,
    progress: bool = True,
    bootstrap: int = 0,
) -> dict:
    """Evaluate predictions against a dataset's frames (the path shared by --pred and --ckpt).

    dataset: a sequence of `detbench.data.Frame` (e.g. `Height3Dataset(root, height, split)`):
        `len(dataset)` and `dataset[i]`.
    predictions_by_frame_id: frame_id -> numpy `Detections` (or a (boxes (M, 7), scores (M,))
        pair); a frame without an entry has no predictions. An id that is not a frame of `dataset` is an error.
    Other arguments as in `evaluate`. Returns the `evaluate` report.
    """
    n = len(dataset)
    ids = getattr(dataset, "frame_ids", None)
    if ids is not None:
        unknown = sorted(set(predictions_by_frame_id) - set(ids))
        if unknown:
            raise KeyError(f"predictions for {len(unknown)} frame id(s) not in the dataset, e.g. "
                           f"{unknown[:3]}; check the split and the file names")
    indices: Iterable[int] = range(n)
    if progress:
        from tqdm import tqdm

        indices = tqdm(indices, desc="frames", unit="frame", leave=False)
    frames = []
    seen = set()
    for i in indices:
        frame = dataset[i]
        seen.add(frame.frame_id)
        frames.append(eval_frame_from_frame(frame, predictions_by_frame_id.get(frame.frame_id)))
    if ids is None:
        unknown = sorted(set(predictions_by_frame_id) - seen)
        if unknown:
            raise KeyError(f"predictions for {len(unknown)} frame id(s) not in the dataset, e.g. "
                           f"{unknown[:3]}; check the split and the file names")
    return evaluate(frames, iou_threshold=iou_threshold, score_threshold=score_threshold,
                    iou_kind=iou_kind, extras=extras, progress=progress, bootstrap=bootstrap)


__all__ = [
    "EvalConfig", "EVAL_DEFAULTS", "evaluate", "evaluate_predictions", "ap_r40", "ap_r40_ranked", "extra_key",
    "IOU_KINDS", "IOU_EPS", "AP_RECALL_LEVELS", "DEFAULT_EXTRAS", "PAIRS", "TP", "FP", "IGNORED",
]
