"""The paper's ranges (Section III-B) and importance levels (Section III-C), defined once.

Ranges are decided by the box centre in the ego ground frame (x forward, y left):
  small     0 <= x <= 50,  |y| <= 5
  moderate  0 <= x <= 100, |y| <= 10
  large     0 <= x <= 150, |y| <= 15
Borders are inclusive.

Importance levels within a range:
  all   every vehicle in the range
  top3  the nearest vehicle (bird's-eye Euclidean distance of the centre to the origin) in
        each of the ego lane (0), the left lane (+1) and the right lane (-1), among the
        vehicles in that range; a lane with no vehicle contributes nothing
  top6  the two nearest in each of those lanes
Ties in distance are broken by the order of the boxes (the earlier box wins), so the
choice is deterministic.
"""
from __future__ import annotations

import numpy as np

from detbench.data.frame import LANE_OPPOSITE, LANE_UNKNOWN

RANGES: dict[str, tuple[float, float, float]] = {
    # name: (x_min, x_max, |y| max), metres
    "small": (0.0, 50.0, 5.0),
    "moderate": (0.0, 100.0, 10.0),
    "large": (0.0, 150.0, 15.0),
}
RANGE_NAMES: tuple[str, ...] = tuple(RANGES)
LEVELS: tuple[str, ...] = ("all", "top3", "top6")
LEVEL_K: dict[str, int] = {"top3": 1, "top6": 2}  # vehicles kept per lane
TOPK_LANES: tuple[int, ...] = (0, 1, -1)

DEFAULT_LANE_WIDTH = 3.5  # metres


def check_range_name(range_name: str) -> str:
    if range_name not in RANGES:
        raise ValueError(f"unknown range_name {range_name!r}; use one of {', '.join(RANGE_NAMES)}")
    return range_name


def check_level(level: str) -> str:
    if level not in LEVELS:
        raise ValueError(f"unknown level {level!r}; use one of {', '.join(LEVELS)}")
    return level


def in_range(xy: np.ndarray, range_name: str) -> np.ndarray:
    """Boolean (M,) mask of centres inside the range; `xy` is (M, >=2) (boxes are fine)."""
    x0, x1, ymax = RANGES[check_range_name(range_name)]
    xy = np.asarray(xy)
    x, y = xy[:, 0], xy[:, 1]
    return (x >= x0) & (x <= x1) & (np.abs(y) <= ymax)


def importance_mask(xy: np.ndarray, lanes: np.ndarray, candidates: np.ndarray, level: str) -> np.ndarray:
    """Boolean (M,) mask of the boxes at `level` among `candidates` (a boolean (M,) mask).

    `level == "all"` returns `candidates` itself. For top3/top6 the k nearest candidates
    of lanes 0, +1 and -1 are kept; other lanes (further lanes, the opposite carriageway,
    unknown) never take part.
    """
    check_level(level)
    candidates = np.asarray(candidates, dtype=bool)
    if level == "all":
        return candidates.copy()
    k = LEVEL_K[level]
    xy = np.asarray(xy, dtype=np.float64)
    lanes = np.asarray(lanes)
    dist = np.hypot(xy[:, 0], xy[:, 1]) if len(xy) else np.zeros(0)
    out = np.zeros(len(candidates), dtype=bool)
    for lane in TOPK_LANES:
        idx = np.flatnonzero(candidates & (lanes == lane))
        if idx.size:
            order = np.argsort(dist[idx], kind="stable")[:k]
            out[idx[order]] = True
    return out


def region_masks(xy: np.ndarray, lanes: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """All nine (range_name, level) masks for one frame's boxes."""
    out = {}
    for r in RANGE_NAMES:
        cand = in_range(xy, r) if len(xy) else np.zeros(0, dtype=bool)
        for lv in LEVELS:
            out[(r, lv)] = importance_mask(xy, lanes, cand, lv)
    return out


def lanes_from_lateral(y: np.ndarray, lane_width: float = DEFAULT_LANE_WIDTH, ego_offset: float = 0.0) -> np.ndarray:
    """Relative lane index from the lateral offset, for datasets without lane ids.

    The ego is taken to drive in the middle of its lane (`ego_offset` shifts that centre,
    metres, positive to the left); lane i covers y in [(i - 1/2) w, (i + 1/2) w) about it.
    This is exact on straight roads and an approximation on curves.
    """
    if lane_width <= 0:
        raise ValueError(f"lane_width must be positive, got {lane_width}")
    y = np.asarray(y, dtype=np.float64) - ego_offset
    return np.floor(y / lane_width + 0.5).astype(np.int64)


__all__ = [
    "RANGES", "RANGE_NAMES", "LEVELS", "LEVEL_K", "TOPK_LANES", "DEFAULT_LANE_WIDTH",
    "LANE_OPPOSITE", "LANE_UNKNOWN",
    "in_range", "importance_mask", "region_masks", "lanes_from_lateral", "check_range_name", "check_level",
]
