"""Calibration of the simulator against the paper's Table IV: criteria, scene counts and precision.

The statistics behind tools/check_calibration.py (which only parses arguments and writes the
report). Counts are arrays of the paper's three ranges (RANGE_NAMES) and heights (HEIGHTS):

  a study's summed counts   (3 ranges, 1 + 3)          total, then detected at 0.5 / 1.0 / 1.8 m
  scene counts              (scenes, 3 ranges, 1 + 3)  the same per scene

all vehicles (level "all"), LiDAR-detected by the study's rule. The criteria (`check_counts`):
  1. every (range, height) LDR within +-tolerance of Table IV;
  2. 1.8 m above both lower heights in every range;
  3. 0.5 m and 1.0 m within pair_tolerance of each other in every range.
`precision` turns the scatter of one scene's LDR into the uncertainty of a study of n scenes
and the scenes a cell needs; `block_pass_rate` estimates how often a fresh study meets every
criterion by resampling scenes. LDR = detected / total (a fraction).
"""
from __future__ import annotations

import math
import warnings
from typing import Iterable, Sequence

import numpy as np

from detbench.data.regions import DETECTED_MIN_POINTS, RANGE_NAMES
from detbench.eval.ability import PAPER_TABLE_IV, AbilityStudy

HEIGHTS = ("0.5", "1.0", "1.8")
PAPER_FRAMES = 8000


def paper_arrays() -> tuple[np.ndarray, np.ndarray]:
    """Table IV as arrays: LDR (3 ranges, 3 heights) and vehicles per frame (3 ranges)."""
    ldr = np.array([[PAPER_TABLE_IV[r][1][h][1] for h in HEIGHTS] for r in RANGE_NAMES])
    per_frame = np.array([PAPER_TABLE_IV[r][0] / PAPER_FRAMES for r in RANGE_NAMES])
    return ldr, per_frame


def check_counts(counts: np.ndarray, tolerance: float = 0.05, pair_tolerance: float = 0.03) -> dict:
    """The criteria on summed counts (3 ranges, 1 + 3: total, then detected per height).

    Returns LDR (3, 3), deviation from Table IV, the worst |deviation| and each criterion's
    pass/fail. A range with no vehicle fails (its LDR is undefined).
    """
    counts = np.asarray(counts, dtype=np.float64)
    total = counts[:, :1]
    with np.errstate(invalid="ignore", divide="ignore"):
        ldr = np.where(total > 0, counts[:, 1:] / np.maximum(total, 1), np.nan)
    paper, _ = paper_arrays()
    dev = ldr - paper
    finite = np.isfinite(ldr).all()
    within = bool(finite and (np.abs(dev) <= tolerance + 1e-12).all())
    order = bool(finite and (ldr[:, 2] > np.maximum(ldr[:, 0], ldr[:, 1])).all())
    pair = bool(finite and (np.abs(ldr[:, 0] - ldr[:, 1]) <= pair_tolerance + 1e-12).all())
    return {"ldr": ldr, "deviation": dev, "worst_abs_deviation": float(np.nanmax(np.abs(dev))) if finite else None,
            "within_tolerance": within, "high_above_low": order, "low_pair_close": pair,
            "ok": within and order and pair}


def scene_counts(steps: Iterable[Sequence]) -> np.ndarray:
    """Counts per scene (scenes, 3 ranges, 1 + 3: total, then detected per height), all vehicles.

    `steps`: the simulator's instants in order, each the `SimFrame`s of the HEIGHTS (0.5, 1.0,
    1.8 m) with their `hit_counts` (e.g. `HighwaySimulator.run(..., with_points=False)`).
    Counted by one `AbilityStudy` per scene (the study's own rule, as in tools/analyze.py).
    """
    studies: dict[int, AbilityStudy] = {}
    for step in steps:
        study = studies.setdefault(int(step[0].scene_id),
                                   AbilityStudy(thresholds=(DETECTED_MIN_POINTS,), keep_example=False))
        study.add(step, counts=[f.hit_counts for f in step])
    out = np.zeros((len(studies), len(RANGE_NAMES), 1 + len(HEIGHTS)), np.int64)
    for k, scene in enumerate(sorted(studies)):
        for i, r in enumerate(RANGE_NAMES):
            cells = [studies[scene].cell(h, r, "all") for h in HEIGHTS]
            out[k, i] = [cells[0]["total"]] + [c["detected"] for c in cells]
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


def summarize(block: np.ndarray, frames: int, tolerance: float, pair_tolerance: float) -> dict:
    """`check_counts` on a block of scene counts (scenes, 3, 4), plus its vehicles per frame."""
    res = check_counts(block.sum(0), tolerance, pair_tolerance)
    res["vehicles_per_frame"] = {r: round(float(block[:, i, 0].sum() / frames), 3) for i, r in enumerate(RANGE_NAMES)}
    return res


def scene_ldr_std(scenes: np.ndarray) -> dict:
    """Standard deviation (ddof 0) across scenes of one scene's LDR, {range: {height: value or None}}."""
    with np.errstate(invalid="ignore", divide="ignore"):
        per_scene_ldr = scenes[:, :, 1:] / np.where(scenes[:, :, :1] > 0, scenes[:, :, :1], np.nan)
    return ldr_grid(np.nanstd(per_scene_ldr, axis=0))


def ldr_grid(values: np.ndarray) -> dict:
    """A (3 ranges, 3 heights) array as {range: {height: value or None}}, rounded to 4 places."""
    return {r: {h: (None if not np.isfinite(values[i, j]) else round(float(values[i, j]), 4))
                for j, h in enumerate(HEIGHTS)} for i, r in enumerate(RANGE_NAMES)}


def jsonable(res: dict) -> dict:
    """A `check_counts` / `summarize` result with its arrays as `ldr_grid` dicts (for JSON)."""
    return {k: (ldr_grid(v) if isinstance(v, np.ndarray) else v) for k, v in res.items()}


def precision(scenes: np.ndarray, paper_ldr: np.ndarray, tolerance: float, scenes_per_block: int | None) -> dict:
    """How precise a study of n scenes is, from scene counts (scenes, 3 ranges, 4: total, detected x 3 heights).

    scene_std: std (ddof 1) of one scene's LDR across scenes (scenes with vehicles in the range);
    half_width_95_at_block: 1.96 std / sqrt(scenes_per_block); scenes_needed: the n with
    1.96 std / sqrt(n) <= tolerance - |pooled LDR - paper| (None where the pooled LDR is off by
    the tolerance or more). Normal approximation, per cell.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        per = scenes[:, :, 1:] / np.where(scenes[:, :, :1] > 0, scenes[:, :, :1], np.nan)
        tot = scenes.sum(0)
        pooled = tot[:, 1:] / np.where(tot[:, :1] > 0, tot[:, :1], np.nan)
    std = np.full(per.shape[1:], np.nan)
    valid = np.isfinite(per).sum(0) >= 2
    if valid.any():
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # cells with fewer than 2 scenes stay NaN
            std = np.where(valid, np.nanstd(per, axis=0, ddof=1), np.nan)
    margin = tolerance - np.abs(pooled - paper_ldr)
    with np.errstate(invalid="ignore", divide="ignore"):
        needed = np.where((margin > 0) & np.isfinite(std), np.ceil((1.96 * std / margin) ** 2), np.nan)
    half = 1.96 * std / math.sqrt(scenes_per_block) if scenes_per_block else None
    finite = std[np.isfinite(std)]
    return {"scenes": int(scenes.shape[0]), "scenes_per_block": scenes_per_block,
            "scene_std": ldr_grid(std), "scene_std_range": [round(float(finite.min()), 4), round(float(finite.max()), 4)]
            if finite.size else [None, None],
            "pooled_ldr": ldr_grid(pooled), "half_width_95_at_block": None if half is None else ldr_grid(half),
            "scenes_needed": {r: {h: (None if not np.isfinite(needed[i, j]) else max(int(needed[i, j]), 1))
                                  for j, h in enumerate(HEIGHTS)} for i, r in enumerate(RANGE_NAMES)},
            "method": "normal approximation per cell: half-width 1.96 std / sqrt(n); needed n from the margin "
                      "tolerance - |pooled - paper|"}


def block_pass_rate(scenes: np.ndarray, scenes_per_block: int, tolerance: float, pair_tolerance: float,
                    replicates: int = 2000, seed: int = 0) -> dict:
    """How often a study of `scenes_per_block` scenes meets every criterion, estimated from scene
    counts (scenes, 3 ranges, 4: total, detected x 3 heights).

    Draws `replicates` studies of that many scenes, each scene drawn independently (with
    replacement) from the pooled scenes, i.e. a fresh study from the population the scenes
    estimate (drawing distinct scenes would understate the spread by sqrt((N - n) / (N - 1))),
    seeded so the figure is reproducible, and applies `check_counts` to each study's summed
    counts, as a study of that length would be judged. Returns the share of studies meeting
    every criterion (`ok`), and of those meeting the +-tolerance criterion alone (`within`);
    None when there are fewer scenes than a study needs (too few to stand for the population).
    """
    n = int(scenes.shape[0])
    if scenes_per_block < 1 or n < scenes_per_block:
        return {"scenes_per_block": int(scenes_per_block), "replicates": 0, "ok": None, "within": None}
    rng = np.random.default_rng(seed)
    ok = within = 0
    for _ in range(replicates):
        res = check_counts(scenes[rng.integers(0, n, scenes_per_block)].sum(0), tolerance, pair_tolerance)
        ok += res["ok"]
        within += res["within_tolerance"]
    return {"scenes_per_block": int(scenes_per_block), "replicates": int(replicates),
            "ok": round(ok / replicates, 4), "within": round(within / replicates, 4),
            "method": "share of simulated studies (scenes drawn with replacement from all seeds' scenes) "
                      "whose summed counts meet the criteria"}


def pass_rates(scenes: np.ndarray, study_frames: list[int], frames_per_scene: int, tolerance: float,
               pair_tolerance: float) -> dict:
    """`block_pass_rate` for studies of each length in `study_frames` (frames, a multiple of the
    scene length), keyed by the length as a string."""
    return {str(f): block_pass_rate(scenes, f // frames_per_scene, tolerance, pair_tolerance)
            for f in sorted(set(study_frames)) if f % frames_per_scene == 0}


__all__ = ["HEIGHTS", "PAPER_FRAMES", "paper_arrays", "check_counts", "scene_counts", "study_runs", "summarize",
           "scene_ldr_std", "ldr_grid", "jsonable", "precision", "block_pass_rate", "pass_rates"]
