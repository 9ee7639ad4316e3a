"""The paper's definitions on a frame's boxes, each in this one place: ranges (Section III-B),
importance levels (Section III-C) and the LiDAR-detected rule (Section IV).

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
choice is deterministic. Lanes follow the Frame's convention (detbench.data.frame).

LiDAR-detected: a vehicle is detected at a height when at least `DETECTED_MIN_POINTS` (1)
point of that height's sweep lies inside its box with the bottom face raised by
`DETECTED_BOTTOM_LIFT` (0.05 m), so road points under the car do not count:
`lidar_detected(points, boxes)`, or `detected_point_counts(points, boxes) >= k` for other
minimum numbers of points; `detected_point_index` also gives the box each point counts for.
The ability study, the evaluator (the ground truth a detector is scored on), the training
set and its ground-truth database all use these functions; the simulator's fast path counts
with its own numba kernel fed by the same constant (detbench.sim.raycast.count_table, proven
equal by tests).
"""
from __future__ import annotations

import numpy as np


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
RANGE_LABELS: dict[str, str] = {"small": "Small", "moderate": "Moderate", "large": "Large"}  # in tables and figures
LEVEL_LABELS: dict[str, str] = {"all": "All", "top3": "Top3", "top6": "Top6"}

DETECTED_BOTTOM_LIFT = 0.05  # metres the box bottom is raised when counting points inside
DETECTED_MIN_POINTS = 1  # points inside the lifted box that make a vehicle LiDAR-detected


def range_extent_label(range_name: str) -> str:
    """The range with its extent, for reports: "small (x <= 50 m, |y| <= 5 m)"."""
    _, x_max, y_max = RANGES[range_name]
    return f"{range_name} (x <= {x_max:g} m, |y| <= {y_max:g} m)"


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


def detected_point_index(points, boxes, bottom_lift: float = DETECTED_BOTTOM_LIFT) -> tuple[np.ndarray, np.ndarray]:
    """`detected_point_counts` with the points that count: ((M,) int64 counts, (N,) int64 index of
    the first (lowest-index) box holding each point, -1 for none), for callers that gather a
    vehicle's points (the ground-truth database) and must not test the points twice.
    """
    from detbench.ops import points_in_boxes  # on first use: detbench.ops loads torch

    boxes = np.asarray(boxes)
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64), np.full(len(points), -1, dtype=np.int64)
    counts, index = points_in_boxes(points, boxes, bottom_lift=bottom_lift)
    return np.asarray(counts, dtype=np.int64), np.asarray(index, dtype=np.int64)


def detected_point_counts(points, boxes, bottom_lift: float = DETECTED_BOTTOM_LIFT) -> np.ndarray:
    """(M,) int64 number of `points` (N, >=3) inside each of `boxes` (M, 7) with the bottom raised
    `bottom_lift` metres (numpy arrays; metres and radians in one frame).

    Compare with `DETECTED_MIN_POINTS` (or another minimum) to decide "detected".
    """
    return detected_point_index(points, boxes, bottom_lift)[0]


def lidar_detected(points, boxes, min_points: int = DETECTED_MIN_POINTS,
                   bottom_lift: float = DETECTED_BOTTOM_LIFT) -> np.ndarray:
    """(M,) bool: the boxes (M, 7) with >= `min_points` of `points` (N, >=3) inside, bottom raised
    `bottom_lift` metres. With the defaults this is the paper's LiDAR-detected rule."""
    return detected_point_counts(points, boxes, bottom_lift) >= min_points


__all__ = [
    "RANGES", "RANGE_NAMES", "LEVELS", "LEVEL_K", "TOPK_LANES", "DETECTED_BOTTOM_LIFT", "DETECTED_MIN_POINTS",
    "in_range", "importance_mask", "region_masks", "check_range_name", "check_level",
    "detected_point_counts", "detected_point_index", "lidar_detected",
]
