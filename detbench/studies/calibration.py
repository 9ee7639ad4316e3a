"""Calibration of the simulator against the paper's Tables IV, V and VI: criteria, scene counts,
the per-lane decomposition, intervals and precision.

The statistics behind tools/check_calibration.py (which only parses arguments and writes the
report). Counts are arrays over the paper's three ranges (RANGE_NAMES), three importance
levels (LEVELS: all, top3, top6) and heights (HEIGHTS):

  a study's summed counts   (3 ranges, 3 levels, 1 + 3)          total, then detected at 0.5 / 1.0 / 1.8 m
  scene counts              (scenes, 3 ranges, 3 levels, 1 + 3)  the same per scene

LiDAR-detected by the study's rule (at least one point inside the box lifted by 0.05 m).

The decomposition the tables imply (`decompose`), per range:
  second-in-lane  Top6 minus Top3: the second-nearest vehicle of each of the ego, left and
                  right lanes (as many as Top6 holds beyond Top3);
  beyond-Top6     All minus Top6: every other vehicle of the range (third and further in
                  those lanes, and the lanes further out).
Their totals and detected counts are differences of the tables' counts, so their LDRs follow
from Tables IV-VI exactly (e.g. second-in-lane, small range, 0.5 m: (11923 - 9725) /
(13661 - 9949) = 0.59).

The criteria on one study (`check_counts`):
  1. every one of the 27 (range, level, height) LDRs within +-tolerance of the paper;
  2. vehicles per frame of every (range, level) within +-total_tolerance (relative) of the paper's;
  3. the second-in-lane LDR within +-second_tolerance of the paper's at every range and height;
  4. 1.8 m above both lower heights in every (range, level);
  5. 0.5 m and 1.0 m within pair_tolerance of each other in every (range, level).
The beyond-Top6 LDRs and per-frame counts are reported beside the paper's but not judged.
Across seeds (`judge_seeds`), the calibration bar: every cell within +-tolerance for all seeds
but `allowed_misses`, the pooled LDRs within +-pooled_tolerance, and criteria 2-5 on the
pooled counts. `precision` and `block_pass_rate` tell how precise a study of n scenes is.
LDR = detected / total (a fraction).
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence

import numpy as np

from detbench.data.regions import DETECTED_MIN_POINTS, LEVELS, RANGE_NAMES
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights
from detbench.studies.ability import CELLS, PAPER_TABLES, AbilityStudy

HEIGHTS = ("0.5", "1.0", "1.8")
PARTS = ("second", "beyond")  # second-in-lane (Top6 - Top3), beyond-Top6 (All - Top6)
PART_NAMES = {"second": "second-in-lane (Top6 - Top3)", "beyond": "beyond-Top6 (All - Top6)"}
PAPER_FRAMES = 8000
_CELL = {c: i for i, c in enumerate(CELLS)}


# ---------------------------------------------------------------------------- the paper
def paper_counts() -> np.ndarray:
    """Tables IV-VI as counts (3 ranges, 3 levels, 1 + 3): total, then detected per height."""
    return np.array([[[PAPER_TABLES[lv][r][0]] + [PAPER_TABLES[lv][r][1][h][0] for h in HEIGHTS] for lv in LEVELS]
                     for r in RANGE_NAMES], dtype=np.int64)


def paper_arrays() -> tuple[np.ndarray, np.ndarray]:
    """The tables' printed LDRs (3 ranges, 3 levels, 3 heights) and vehicles per frame (3 ranges, 3 levels)."""
    ldr = np.array([[[PAPER_TABLES[lv][r][1][h][1] for h in HEIGHTS] for lv in LEVELS] for r in RANGE_NAMES])
    return ldr, paper_counts()[..., 0] / PAPER_FRAMES


def ratios(counts: np.ndarray) -> np.ndarray:
    """detected / total over the last axis (1 + 3): (..., 3), NaN where the total is 0."""
    counts = np.asarray(counts, dtype=np.float64)
    tot = counts[..., :1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(tot > 0, counts[..., 1:] / np.where(tot > 0, tot, 1.0), np.nan)


def decompose(counts: np.ndarray) -> np.ndarray:
    """(..., 3 ranges, 3 levels, 4) -> (..., 3 ranges, 2 parts, 4): second-in-lane = Top6 - Top3,
    beyond-Top6 = All - Top6 (totals and detected counts alike)."""
    counts = np.asarray(counts)
    a, t3, t6 = (counts[..., LEVELS.index(lv), :] for lv in ("all", "top3", "top6"))
    return np.stack([t6 - t3, a - t6], axis=-2)


def paper_decomposition() -> tuple[np.ndarray, np.ndarray]:
    """The decomposition of the paper's counts: LDR (3 ranges, 2 parts, 3 heights) and vehicles per
    frame (3 ranges, 2 parts). Computed from the counts (the tables print no such rows)."""
    d = decompose(paper_counts())
    return ratios(d), d[..., 0] / PAPER_FRAMES


# ---------------------------------------------------------------------------- criteria
def check_counts(counts: np.ndarray, frames: int, tolerance: float = 0.05, pair_tolerance: float = 0.03,
                 total_tolerance: float = 0.15, second_tolerance: float = 0.07) -> dict:
    """The five criteria (module doc) on a study's summed counts (3 ranges, 3 levels, 4) over `frames` frames.

    Returns arrays: ldr and deviation (3, 3, 3), vehicles_per_frame and total_ratio (here / paper,
    3, 3), decomposition_ldr / decomposition_deviation (3, 2, 3), decomposition_per_frame (3, 2);
    scalars: worst_abs_deviation, worst_total_ratio_error, worst_second_deviation; and each
    criterion's pass/fail (within_tolerance, totals_close, second_close, high_above_low,
    low_pair_close) and ok (all five). A cell without vehicles fails (its LDR is undefined).
    """
    counts = np.asarray(counts, dtype=np.float64)
    if counts.shape != (len(RANGE_NAMES), len(LEVELS), 1 + len(HEIGHTS)):
        raise ValueError(f"counts must be (3 ranges, 3 levels, 4), got {counts.shape}")
    if frames <= 0:
        raise ValueError(f"frames must be positive, got {frames}")
    tol = 1e-12
    ldr = ratios(counts)
    paper, paper_pf = paper_arrays()
    dev = ldr - paper
    finite = bool(np.isfinite(ldr).all())
    per_frame = counts[..., 0] / frames
    ratio = per_frame / paper_pf
    dec = decompose(counts)
    dec_ldr = ratios(dec)
    paper_dec, _ = paper_decomposition()
    dec_dev = dec_ldr - paper_dec
    second_dev = dec_dev[:, PARTS.index("second")]
    second_finite = bool(np.isfinite(second_dev).all())
    within = finite and bool((np.abs(dev) <= tolerance + tol).all())
    totals = bool((np.abs(ratio - 1.0) <= total_tolerance + tol).all())
    second = second_finite and bool((np.abs(second_dev) <= second_tolerance + tol).all())
    order = finite and bool((ldr[..., 2] > np.maximum(ldr[..., 0], ldr[..., 1])).all())
    pair = finite and bool((np.abs(ldr[..., 0] - ldr[..., 1]) <= pair_tolerance + tol).all())
    return {"ldr": ldr, "deviation": dev,
            "worst_abs_deviation": float(np.nanmax(np.abs(dev))) if finite else None,
            "vehicles_per_frame": per_frame, "total_ratio": ratio,
            "worst_total_ratio_error": float(np.max(np.abs(ratio - 1.0))),
            "decomposition_ldr": dec_ldr, "decomposition_deviation": dec_dev,
            "decomposition_per_frame": dec[..., 0] / frames,
            "worst_second_deviation": float(np.max(np.abs(second_dev))) if second_finite else None,
            "within_tolerance": within, "totals_close": totals, "second_close": second,
            "high_above_low": order, "low_pair_close": pair,
            "ok": within and totals and second and order and pair}


CRITERIA = ("within_tolerance", "totals_close", "second_close", "high_above_low", "low_pair_close")


# ---------------------------------------------------------------------------- counting
def scene_counts(steps: Iterable[Sequence]) -> np.ndarray:
    """Counts per scene (scenes, 3 ranges, 3 levels, 1 + 3: total, then detected per height).

    `steps`: the simulator's instants in order, each the `SimFrame`s of the HEIGHTS (0.5, 1.0,
    1.8 m) with their `hit_counts` (e.g. `HighwaySimulator.run(..., with_points=False)`).
    Counted by an `AbilityStudy` (the study's own rule, as in tools/analyze.py), per scene.
    """
    study = AbilityStudy(thresholds=(DETECTED_MIN_POINTS,), keep_example=False, bootstrap=0)
    for step in steps:
        study.add(step, counts=[f.hit_counts for f in step])
    return study_scene_counts(study)


def study_scene_counts(study: AbilityStudy) -> np.ndarray:
    """An `AbilityStudy`'s per-scene counts (scenes, 3 ranges, 3 levels, 4) at the HEIGHTS (each must be in it)."""
    _, heights, arr = study.cluster_counts()  # (C, H, 2, 9)
    missing = [h for h in HEIGHTS if h not in heights]
    if missing:
        raise ValueError(f"the study has no frames at {', '.join(missing)} m (heights: {', '.join(heights)})")
    out = np.zeros((arr.shape[0], len(RANGE_NAMES), len(LEVELS), 1 + len(HEIGHTS)), np.int64)
    for i, r in enumerate(RANGE_NAMES):
        for k, lv in enumerate(LEVELS):
            c = _CELL[(r, lv)]
            out[:, i, k, 0] = arr[:, heights.index(HEIGHTS[0]), 0, c]
            for j, h in enumerate(HEIGHTS):
                out[:, i, k, 1 + j] = arr[:, heights.index(h), 1, c]
    return out


def study_runs(scenes: np.ndarray, frames: int, frames_per_scene: int,
               block_frames: int) -> list[tuple[str, np.ndarray, int]]:
    """(name, scene counts, frames) of the whole run ("all") and of each whole block of
    `block_frames` consecutive frames ("block 0", ...; none when block_frames is 0)."""
    runs = [("all", scenes, frames)]
    if block_frames:
        per = block_frames // frames_per_scene
        runs += [(f"block {b}", scenes[b * per:(b + 1) * per], block_frames) for b in range(scenes.shape[0] // per)]
    return runs


def summarize(block: np.ndarray, frames: int, **tolerances) -> dict:
    """`check_counts` on a block of scene counts (scenes, 3, 3, 4) summed."""
    return check_counts(block.sum(0), frames, **tolerances)


# ---------------------------------------------------------------------------- intervals
def bootstrap_intervals(scenes: np.ndarray, frames_per_scene: float, replicates: int = 1000, seed: int = 0,
                        confidence: float = 0.95) -> dict:
    """95 % percentile intervals (bootstrap over scenes) of the pooled LDRs (3, 3, 3), the
    decomposition's LDRs (3, 2, 3) and the vehicles per frame (3, 3), as nested lists of
    [lo, hi] (None where undefined); `frames_per_scene` turns scene totals into per-frame counts."""
    n = int(scenes.shape[0])
    if n < 2 or replicates < 1:
        return {"ldr": None, "decomposition_ldr": None, "vehicles_per_frame": None, "replicates": 0}
    w = scene_bootstrap_weights(n, replicates, seed)  # (B, n)
    sc = scenes.astype(np.float64)
    ldr = bootstrap_ratios(w, sc[..., 1:], np.repeat(sc[..., :1], len(HEIGHTS), axis=-1))  # (B, 3, 3, 3)
    dec = decompose(sc)
    dec_ldr = bootstrap_ratios(w, dec[..., 1:], np.repeat(dec[..., :1], len(HEIGHTS), axis=-1))
    per_frame = np.tensordot(w, sc[..., 0], axes=(1, 0)) / (n * frames_per_scene)  # (B, 3, 3)

    def grid(samples: np.ndarray):
        def nest(idx: tuple):
            if len(idx) == samples.ndim - 1:
                return percentile_interval(samples[(slice(None),) + idx], confidence)
            return [nest(idx + (k,)) for k in range(samples.shape[1 + len(idx)])]

        return nest(())

    return {"ldr": grid(ldr), "decomposition_ldr": grid(dec_ldr), "vehicles_per_frame": grid(per_frame),
            "replicates": int(replicates), "confidence": confidence,
            "method": "percentile bootstrap over scenes (scenes resampled with replacement)"}


# ---------------------------------------------------------------------------- across seeds
def judge_seeds(seed_results: dict, pooled: dict, tolerance: float = 0.05, pooled_tolerance: float = 0.03,
                allowed_misses: int = 1) -> dict:
    """The calibration bar over several seeds' whole runs (`check_counts` results) and their pooled counts.

    cells: each of the 27 cells within +-tolerance for all but `allowed_misses` seeds
    (`seeds_within`: how many were, per cell) and pooled within +-pooled_tolerance;
    totals / second / order / pair: the pooled counts meet criteria 2-5 of `check_counts`.
    """
    devs = np.stack([np.asarray(r["deviation"], dtype=np.float64) for r in seed_results.values()])  # (S, 3, 3, 3)
    seeds_within = (np.abs(devs) <= tolerance + 1e-12).sum(0)
    need = max(len(seed_results) - int(allowed_misses), 0)
    per_seed_ok = bool((seeds_within >= need).all())
    pooled_dev = np.asarray(pooled["deviation"], dtype=np.float64)
    pooled_ok = bool(np.isfinite(pooled_dev).all() and (np.abs(pooled_dev) <= pooled_tolerance + 1e-12).all())
    verdict = {"cells_per_seed": per_seed_ok, "cells_pooled": pooled_ok,
               "totals_pooled": bool(pooled["totals_close"]), "second_pooled": bool(pooled["second_close"]),
               "high_above_low_pooled": bool(pooled["high_above_low"]),
               "low_pair_close_pooled": bool(pooled["low_pair_close"]),
               "high_above_low_every_seed": all(bool(r["high_above_low"]) for r in seed_results.values()),
               "low_pair_close_every_seed": all(bool(r["low_pair_close"]) for r in seed_results.values())}
    verdict["ok"] = all(verdict[k] for k in ("cells_per_seed", "cells_pooled", "totals_pooled", "second_pooled",
                                             "high_above_low_pooled", "low_pair_close_pooled"))
    return {"seeds_within": seeds_within, "seeds_needed": need, "worst_seed_deviation": np.nanmax(np.abs(devs), axis=0),
            "verdict": verdict}


# ---------------------------------------------------------------------------- JSON
def cell_grid(values: np.ndarray, digits: int = 4) -> dict:
    """A (3 ranges, 3 levels, 3 heights) array as {level: {range: {height: value or None}}}."""
    values = np.asarray(values, dtype=np.float64)
    return {lv: {r: {h: (None if not np.isfinite(values[i, k, j]) else round(float(values[i, k, j]), digits))
                     for j, h in enumerate(HEIGHTS)} for i, r in enumerate(RANGE_NAMES)}
            for k, lv in enumerate(LEVELS)}


def part_grid(values: np.ndarray, digits: int = 4) -> dict:
    """A (3 ranges, 2 parts, 3 heights) array as {part: {range: {height: value or None}}}."""
    values = np.asarray(values, dtype=np.float64)
    return {p: {r: {h: (None if not np.isfinite(values[i, k, j]) else round(float(values[i, k, j]), digits))
                    for j, h in enumerate(HEIGHTS)} for i, r in enumerate(RANGE_NAMES)}
            for k, p in enumerate(PARTS)}


def level_grid(values: np.ndarray, names: Sequence[str] = LEVELS, digits: int = 4) -> dict:
    """A (3 ranges, len(names)) array as {name: {range: value}}."""
    values = np.asarray(values, dtype=np.float64)
    return {n: {r: round(float(values[i, k]), digits) for i, r in enumerate(RANGE_NAMES)} for k, n in enumerate(names)}


def jsonable(res: dict) -> dict:
    """A `check_counts` / `summarize` result with its arrays as nested dicts (for JSON)."""
    out = {}
    for k, v in res.items():
        if not isinstance(v, np.ndarray):
            out[k] = v
        elif k.startswith("decomposition_per_frame"):
            out[k] = level_grid(v, PARTS)
        elif k.startswith("decomposition"):
            out[k] = part_grid(v)
        elif v.ndim == 2:
            out[k] = level_grid(v)
        else:
            out[k] = cell_grid(v)
    return out


# ---------------------------------------------------------------------------- precision
def scene_ldr_std(scenes: np.ndarray) -> np.ndarray:
    """Standard deviation (ddof 1) across scenes of one scene's LDR (3, 3, 3), NaN with fewer than 2 scenes."""
    per = ratios(scenes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        valid = np.isfinite(per).sum(0) >= 2
        return np.where(valid, np.nanstd(per, axis=0, ddof=1), np.nan)


def precision(scenes: np.ndarray, tolerance: float, scenes_per_block: int | None) -> dict:
    """How precise a study of n scenes is, from scene counts (scenes, 3, 3, 4).

    scene_std: std of one scene's LDR across scenes; half_width_95_at_block: 1.96 std /
    sqrt(scenes_per_block); scenes_needed: the n with 1.96 std / sqrt(n) <= tolerance -
    |pooled LDR - paper| (None where the pooled LDR is off by the tolerance or more). Normal
    approximation, per cell.
    """
    paper, _ = paper_arrays()
    std = scene_ldr_std(scenes)
    pooled = ratios(scenes.sum(0))
    margin = tolerance - np.abs(pooled - paper)
    with np.errstate(invalid="ignore", divide="ignore"):
        needed = np.where((margin > 0) & np.isfinite(std), np.ceil((1.96 * std / margin) ** 2), np.nan)
    half = 1.96 * std / math.sqrt(scenes_per_block) if scenes_per_block else None
    finite = std[np.isfinite(std)]
    needed_grid = cell_grid(needed, 0)
    needed_grid = {lv: {r: {h: (None if v is None else max(int(v), 1)) for h, v in row.items()}
                        for r, row in g.items()} for lv, g in needed_grid.items()}
    return {"scenes": int(scenes.shape[0]), "scenes_per_block": scenes_per_block,
            "scene_std": cell_grid(std),
            "scene_std_range": [round(float(finite.min()), 4), round(float(finite.max()), 4)] if finite.size
            else [None, None],
            "pooled_ldr": cell_grid(pooled), "half_width_95_at_block": None if half is None else cell_grid(half),
            "scenes_needed": needed_grid,
            "method": "normal approximation per cell: half-width 1.96 std / sqrt(n); needed n from the margin "
                      "tolerance - |pooled - paper|"}


def block_pass_rate(scenes: np.ndarray, scenes_per_block: int, frames_per_scene: int, replicates: int = 2000,
                    seed: int = 0, **tolerances) -> dict:
    """How often a study of `scenes_per_block` scenes meets every criterion, estimated from scene
    counts (scenes, 3, 3, 4).

    Draws `replicates` studies of that many scenes, each scene drawn independently (with
    replacement) from the pooled scenes, i.e. a fresh study from the population the scenes
    estimate, seeded so the figure is reproducible, and applies `check_counts` to each study's
    summed counts. Returns the share of studies meeting every criterion (`ok`) and the +-tolerance
    criterion on the 27 cells alone (`within`); None when there are fewer scenes than a study needs.
    """
    n = int(scenes.shape[0])
    if scenes_per_block < 1 or n < scenes_per_block:
        return {"scenes_per_block": int(scenes_per_block), "replicates": 0, "ok": None, "within": None}
    rng = np.random.default_rng(seed)
    ok = within = 0
    frames = scenes_per_block * frames_per_scene
    for _ in range(replicates):
        res = check_counts(scenes[rng.integers(0, n, scenes_per_block)].sum(0), frames, **tolerances)
        ok += res["ok"]
        within += res["within_tolerance"]
    return {"scenes_per_block": int(scenes_per_block), "replicates": int(replicates),
            "ok": round(ok / replicates, 4), "within": round(within / replicates, 4),
            "method": "share of simulated studies (scenes drawn with replacement from all seeds' scenes) "
                      "whose summed counts meet the criteria"}


def pass_rates(scenes: np.ndarray, study_frames: list[int], frames_per_scene: int, replicates: int = 2000,
               **tolerances) -> dict:
    """`block_pass_rate` for studies of each length in `study_frames` (frames, a multiple of the
    scene length), keyed by the length as a string."""
    return {str(f): block_pass_rate(scenes, f // frames_per_scene, frames_per_scene, replicates, **tolerances)
            for f in sorted(set(study_frames)) if f % frames_per_scene == 0}


__all__ = ["HEIGHTS", "PARTS", "PART_NAMES", "PAPER_FRAMES", "CRITERIA", "paper_counts", "paper_arrays",
           "paper_decomposition", "ratios", "decompose", "check_counts", "scene_counts", "study_scene_counts",
           "study_runs", "summarize", "bootstrap_intervals", "judge_seeds", "cell_grid", "part_grid", "level_grid",
           "jsonable", "scene_ldr_std", "precision", "block_pass_rate", "pass_rates"]
