"""AP@R40 under a scene bootstrap: the report's ranked detections, a weighted AP@R40 vectorised over
replicates, and the paired difference of two sides' AP@R40 on the same scenes.

AP@R40 pools the TP and FP predictions of every frame and ranks them by score, so a scene bootstrap
of AP needs, besides each scene's LiDAR-detected count, where each counted detection falls in the
pooled ranking and which scene it comes from. The evaluator keeps that in its report
(`report["uncertainty"]["ap_ranking"]`, written by `ap_ranking`):

- "scene": for each detection that counts (TP or FP) in at least one range/level, in the order of
  the report's AP ranking (score descending; equal scores in frame order, then input order), the
  index of its scene in `uncertainty["clusters"]`, as decimal numbers separated by spaces;
- "levels": the levels of each outcome character, ["all", "top3", "top6"];
- "outcome": {range: text}, one character per entry of "scene", a base-27 digit (0-9, a-q) whose
  three base-3 digits, most significant first, are the detection's outcome at each of "levels":
  2 a TP, 1 an FP, 0 not counted (ignored). "0" is a detection ignored at every level of the range,
  "q" (26) a TP at all three, "i" (18) a TP at "all" ignored at the others.

The ranking's position replaces the score: AP depends on the order alone, and rounded scores would
merge distinct scores into ties that the pooled order breaks by frame instead. Both fields are text,
so an indented report.json spends no line per detection: a scene number and 3 characters a detection. The
LiDAR-detected count of each scene is `uncertainty["per_cluster"][range][level]["lidar_detected"]`.

A replicate draws scenes with replacement: a scene drawn k times counts its ground truth and its
detections k times, the copies of a detection adjacent in the ranking (`weighted_ap_r40`; the same
figure as AP@R40 of the list with every detection repeated, `ap_r40_ranked`).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import lru_cache

import numpy as np
from numba import njit, prange

from detbench.eval.bootstrap import scene_bootstrap_weights

AP_RECALL_LEVELS = 40
# The digits of an outcome character (module docstring).
_DIGITS = "0123456789abcdefghijklmnopq"
_DIGIT_VALUE = np.full(256, -1, dtype=np.int64)
_DIGIT_VALUE[np.frombuffer(_DIGITS.encode("ascii"), dtype=np.uint8)] = np.arange(len(_DIGITS))


def ap_ranking(flags: np.ndarray, scores: np.ndarray, scene: np.ndarray,
               pairs: Sequence[tuple[str, str]]) -> dict:
    """The report's "ap_ranking" block (module docstring) of the evaluator's kept predictions.

    flags: (M, P) int8, each kept prediction's outcome in each (range, level) of `pairs` (1 TP, 0 FP,
    -1 ignored), predictions in frame order, ranked within each frame; scores (M,); scene (M,) int,
    the scene index of each prediction's frame. `pairs` holds every range with the same three levels."""
    flags = np.asarray(flags, dtype=np.int8).reshape(len(scores), len(pairs))
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")  # the pooled ranking of ap_r40
    order = order[(flags[order] >= 0).any(axis=1)]
    ranges = list(dict.fromkeys(r for r, _ in pairs))
    levels = [lv for r, lv in pairs if r == ranges[0]]
    if len(levels) != 3 or sorted(pairs) != sorted((r, lv) for r in ranges for lv in levels):
        raise ValueError(f"ap_ranking needs every range with the same three levels, got {list(pairs)}")
    digits = np.array(list(_DIGITS))
    out: dict = {"scene": " ".join(map(str, np.asarray(scene, dtype=np.int64)[order].tolist())),
                 "levels": levels, "outcome": {}}
    for r in ranges:
        value = np.zeros(len(order), dtype=np.int64)
        for lv in levels:  # most significant first: 0 ignored, 1 FP, 2 TP
            value = 3 * value + flags[order, list(pairs).index((r, lv))] + 1
        out["outcome"][r] = "".join(digits[value].tolist())
    return out


def has_ap_ranking(report: Mapping) -> bool:
    """Whether `report` keeps the ranked detections a scene bootstrap of AP@R40 needs."""
    unc = report.get("uncertainty")
    return isinstance(unc, Mapping) and isinstance(unc.get("ap_ranking"), Mapping)


def _scenes(text: str) -> np.ndarray:
    try:
        return np.array(text.split(), dtype=np.int64)
    except (AttributeError, ValueError):
        raise ValueError("report uncertainty.ap_ranking.scene must be scene numbers separated by spaces; evaluate "
                         "again (tools/eval.py) to rewrite it") from None


def _outcomes(block: Mapping, r: str, lv: str) -> np.ndarray:
    """(K,) int: each ranked detection's outcome in (r, lv): 2 TP, 1 FP, 0 ignored."""
    levels = list(block.get("levels") or [])
    text = (block.get("outcome") or {}).get(r)
    if lv not in levels or not isinstance(text, str):
        raise ValueError(f"report uncertainty.ap_ranking holds no outcomes of {r}/{lv}; evaluate again "
                         f"(tools/eval.py) to rewrite it")
    value = _DIGIT_VALUE[np.frombuffer(text.encode("latin-1", "replace"), dtype=np.uint8)]
    if (value < 0).any():
        raise ValueError(f"report uncertainty.ap_ranking.outcome[{r!r}] holds characters other than 0-9 and "
                         f"a-q; evaluate again (tools/eval.py) to rewrite it")
    return value // 3 ** (len(levels) - 1 - levels.index(lv)) % 3


def ranked_detections(report: Mapping, r: str, lv: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tp (K,) bool, scene (K,) int, lidar_detected (C,) int): the detections counted in (r, lv), best
    first, with their scenes, and each scene's LiDAR-detected count. ValueError when the block is malformed."""
    unc = report["uncertainty"]
    block = unc["ap_ranking"]
    scene = _scenes(block["scene"])
    codes = _outcomes(block, r, lv)
    det = np.asarray(unc["per_cluster"][r][lv]["lidar_detected"], dtype=np.int64)
    if len(codes) != len(scene) or (len(scene) and (scene.min() < 0 or scene.max() >= len(det))):
        raise ValueError(f"report uncertainty.ap_ranking: {len(codes)} outcomes of {r} for {len(scene)} "
                         f"detections of {len(det)} scenes; evaluate again (tools/eval.py) to rewrite it")
    counted = codes > 0
    return codes[counted] == 2, scene[counted], det


@njit(cache=True, parallel=True)
def _level_terms(tp, scene, tp_scene, n_scene, det, weights, levels):
    """(B, levels) float64: the interpolated precision of each recall level in each replicate (NaN rows where
    the replicate has no LiDAR-detected vehicle). One backward pass over the ranked detections per replicate,
    parallel over replicates: the running maximum of p_k = T_k / N_k is the best precision at rank k or later,
    and it is the term of the levels i with L_{k-1} < i <= L_k, L_k = min(levels, levels T_k // G) the levels
    reached after detection k (the integer form of 40 T_k >= i G)."""
    num_b = weights.shape[0]
    out = np.zeros((num_b, levels))
    for b in prange(num_b):
        g, t, n = 0, 0, 0
        for s in range(weights.shape[1]):
            g += weights[b, s] * det[s]
            t += weights[b, s] * tp_scene[s]
            n += weights[b, s] * n_scene[s]
        if g == 0:
            out[b, :] = np.nan
            continue
        reached = min(levels, (levels * t) // g)
        best = 0.0
        for k in range(tp.shape[0] - 1, -1, -1):
            if n > 0 and t / n > best:
                best = t / n
            w = weights[b, scene[k]]
            if tp[k]:
                t -= w
            n -= w
            before = min(levels, (levels * t) // g)
            for i in range(before, reached):
                out[b, i] = best
            reached = before
    return out


def weighted_ap_r40(tp: np.ndarray, scene: np.ndarray, lidar_detected: np.ndarray,
                    weights: np.ndarray) -> np.ndarray:
    """AP@R40 of each bootstrap replicate: (B,) float64, NaN where a replicate has no LiDAR-detected vehicle.

    tp (K,) bool and scene (K,) int: the counted detections, best first, and the scene of each;
    lidar_detected (C,): each scene's evaluated ground truth; weights (B, C): how often each scene is
    drawn (non-negative integers, `scene_bootstrap_weights`). Replicate b counts detection k w_bk =
    weights[b, scene[k]] times, its copies adjacent: its AP@R40 is that of `ap_r40_ranked` on the list
    with each detection repeated. Within a run of copies precision only rises (TP) or falls (FP), so the
    interpolated precision is read at the run ends: with T_k, N_k the weighted TP and detection counts
    after detection k, p_k = T_k / N_k, and level i's term is max_{k' >= k_i} p_k' for the first k_i with
    40 T_k >= i G_b (G_b the replicate's LiDAR-detected count), 0 when none is. Counts are integers and
    the 40 terms are summed as `ap_r40_ranked` sums them, so the figure is the repeated list's to the last
    bit. A numba kernel, parallel over replicates, with no array of replicates x detections."""
    tp = np.ascontiguousarray(tp, dtype=np.bool_).reshape(-1)
    scene = np.ascontiguousarray(scene, dtype=np.int64).reshape(-1)
    det = np.ascontiguousarray(lidar_detected, dtype=np.int64).reshape(-1)
    w = np.ascontiguousarray(np.rint(np.asarray(weights, dtype=np.float64)), dtype=np.int64).reshape(-1, len(det))
    if len(scene) and (scene.min() < 0 or scene.max() >= len(det)):
        raise ValueError(f"scene indices must lie in [0, {len(det)}), got {scene.min()}..{scene.max()}")
    tp_scene = np.bincount(scene[tp], minlength=len(det)).astype(np.int64)
    n_scene = np.bincount(scene, minlength=len(det)).astype(np.int64)
    terms = _level_terms(tp, scene, tp_scene, n_scene, det, w, AP_RECALL_LEVELS)
    return terms.sum(axis=1) / AP_RECALL_LEVELS


@lru_cache(maxsize=512)
def _replicates(outcome: str, scene: str, levels: tuple, lv: str, det: tuple, replicates: int,
                seed: int) -> np.ndarray:
    """`weighted_ap_r40` of one report's (range, level) under `scene_bootstrap_weights(len(det), replicates,
    seed)`, read-only; keyed by the report's own data, so a study's leads compute each side once."""
    codes = _outcomes({"levels": list(levels), "outcome": {"r": outcome}}, "r", lv)
    counted = codes > 0
    w = scene_bootstrap_weights(len(det), replicates, seed)
    out = weighted_ap_r40(codes[counted] == 2, _scenes(scene)[counted], np.asarray(det, dtype=np.int64), w)
    out.flags.writeable = False
    return out


def ap_replicates(report: Mapping, r: str, lv: str, replicates: int, seed: int) -> np.ndarray:
    """(replicates,) AP@R40 of `report`'s (r, lv) in each replicate of `scene_bootstrap_weights(scenes,
    replicates, seed)`; NaN where a replicate has no LiDAR-detected vehicle. Read-only."""
    ranked_detections(report, r, lv)  # checks the block
    unc = report["uncertainty"]
    block = unc["ap_ranking"]
    return _replicates(block["outcome"][r], block["scene"], tuple(block["levels"]), lv,
                       tuple(unc["per_cluster"][r][lv]["lidar_detected"]), int(replicates), int(seed))


def paired_ap_difference(reports_a: Sequence[Mapping], reports_b: Sequence[Mapping], r: str, lv: str,
                         replicates: int, seed: int) -> np.ndarray:
    """(replicates,) the paired scene bootstrap of mean_a - mean_b of AP@R40 in (r, lv): each side the mean
    over its reports (training seeds), every report of both sides resampled with the same scene draws
    (`scene_bootstrap_weights`), each re-ranked in its replicate. The reports must share their scenes
    (`uncertainty["clusters"]`, ValueError otherwise) and keep "ap_ranking" (`has_ap_ranking`). NaN where a
    replicate leaves a side without LiDAR-detected vehicles."""
    reports = [*reports_a, *reports_b]
    clusters = list(reports[0]["uncertainty"]["clusters"])
    for rep in reports[1:]:
        if list(rep["uncertainty"]["clusters"]) != clusters:
            raise ValueError("the reports of a paired AP@R40 difference must be on the same test scenes "
                             "(uncertainty.clusters differ); compare reports of one test split")

    def side(reps: Sequence[Mapping]) -> np.ndarray:
        return np.mean([ap_replicates(rep, r, lv, replicates, seed) for rep in reps], axis=0)

    return side(reports_a) - side(reports_b)


__all__ = ["AP_RECALL_LEVELS", "ap_ranking", "ap_replicates", "has_ap_ranking", "paired_ap_difference",
           "ranked_detections", "weighted_ap_r40"]
