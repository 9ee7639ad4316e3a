"""LiDAR detection ability (the paper's Section IV): how many vehicles a LiDAR at each height hits.

Definitions (exactly the paper's; each lives in detbench.data.regions):
- a vehicle is *LiDAR-detected* at a height when at least one point of that height's sweep
  lies inside its box with the box bottom raised by 0.05 m (so road points under the car
  do not count): `detected_point_counts(points, boxes) >= DETECTED_MIN_POINTS`;
- ranges by the box centre: small 0<=x<=50, |y|<=5; moderate 0<=x<=100, |y|<=10;
  large 0<=x<=150, |y|<=15 (metres, borders inclusive);
- levels within a range: all; top3 = nearest vehicle in each of the ego, left and right
  lanes; top6 = two nearest in each (a missing lane contributes nothing);
- LDR = detected / total, summed over frames.

Extras: the same counts for other minimum numbers of points (5 and 10 by default), LDR
against the centre's distance along x (10 m bins, vehicles with |y| <= 15 m), the mean
number of points on a detected vehicle, vehicles per frame, and the sampling uncertainty
(`scene_uncertainty`): 95 % intervals of every LDR and of the paired differences between
heights from a bootstrap over scenes. Frames of one scene are 0.5 s apart and strongly
correlated, so scenes (not frames) are resampled; the per-scene scatter of LDR tells how
many scenes a study needs for a given precision.

`AbilityStudy` is a streaming accumulator: feed it frames from disk or from the simulator
(`.add(frame)` or `.add([frame per height])`) and ask for `.report()` (a JSON-ready dict);
detbench.studies.ability_tables lays a report out as Markdown like the paper's Tables IV-VI.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Iterable, Sequence

import numpy as np

from detbench.data.frame import DEFAULT_LANE_WIDTH, LANE_UNKNOWN, Frame, height_key, lanes_from_lateral
from detbench.data.regions import (
    DETECTED_BOTTOM_LIFT, DETECTED_MIN_POINTS, LEVELS, RANGE_NAMES, RANGES, detected_point_counts, region_masks,
)
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights

DEFAULT_THRESHOLDS = (DETECTED_MIN_POINTS, 5, 10)  # minimum points inside a box to call it detected
DEFAULT_BIN_M = 10.0
LDR_DISTANCE_MAX_M = 150.0  # x extent of the large range
LDR_DISTANCE_HALF_WIDTH_M = 15.0  # |y| bound of the large range
PAPER_TABLE_IV = {  # Height3 paper, Table IV (8000 frames): total, then (detected, LDR) per height
    "small": (17268, {"0.5": (12638, 0.73), "1.0": (12572, 0.73), "1.8": (14739, 0.85)}),
    "moderate": (39455, {"0.5": (26407, 0.67), "1.0": (26216, 0.66), "1.8": (32074, 0.81)}),
    "large": (54097, {"0.5": (34296, 0.63), "1.0": (34339, 0.63), "1.8": (42185, 0.78)}),
}
PAPER_TABLE_V = {  # Table V, "Top3" vehicles (nearest in the ego, left and right lanes), same layout
    "small": (9949, {"0.5": (9725, 0.98), "1.0": (9730, 0.98), "1.8": (9862, 0.99)}),
    "moderate": (13364, {"0.5": (12900, 0.97), "1.0": (12899, 0.97), "1.8": (13135, 0.98)}),
    "large": (14522, {"0.5": (13927, 0.96), "1.0": (13925, 0.96), "1.8": (14212, 0.98)}),
}
PAPER_TABLE_VI = {  # Table VI, "Top6" vehicles (two nearest in each of those lanes), same layout
    "small": (13661, {"0.5": (11923, 0.87), "1.0": (11732, 0.86), "1.8": (12838, 0.94)}),
    "moderate": (20407, {"0.5": (17444, 0.85), "1.0": (17147, 0.84), "1.8": (18824, 0.92)}),
    "large": (23303, {"0.5": (19543, 0.84), "1.0": (19267, 0.83), "1.8": (21135, 0.91)}),
}
PAPER_TABLES = {"all": PAPER_TABLE_IV, "top3": PAPER_TABLE_V, "top6": PAPER_TABLE_VI}  # by level
DEFAULT_BOOTSTRAP = 1000  # bootstrap replicates of the scene resampling
CELLS: tuple[tuple[str, str], ...] = tuple((r, lv) for r in RANGE_NAMES for lv in LEVELS)  # 9 (range, level)
_LARGE_ALL = CELLS.index(("large", "all"))


def ldr(detected: int, total: int) -> float:
    """detected / total, NaN when total is 0 (written as null in JSON)."""
    return float(detected) / float(total) if total else float("nan")


def stacked_masks(boxes: np.ndarray, lanes: np.ndarray) -> np.ndarray:
    """The nine (range, level) membership masks of one frame's boxes as a (9, M) bool array.

    Rows follow `CELLS` (small/all, small/top3, small/top6, moderate/all, ...). boxes (M, >=2)
    x, y in metres; lanes (M,) int64 relative lane ids.
    """
    m = len(boxes)
    if m == 0:
        return np.zeros((len(CELLS), 0), dtype=bool)
    masks = region_masks(np.asarray(boxes)[:, :2], np.asarray(lanes))
    return np.stack([masks[c] for c in CELLS])


def frame_lanes(frame: Frame, lane_width: float = DEFAULT_LANE_WIDTH) -> np.ndarray:
    """The frame's lanes with LANE_UNKNOWN entries replaced by lanes from the lateral offset."""
    lanes = np.asarray(frame.lanes, dtype=np.int64)
    unknown = lanes == LANE_UNKNOWN
    if unknown.any():
        lanes = lanes.copy()
        lanes[unknown] = lanes_from_lateral(np.asarray(frame.boxes)[unknown, 1], lane_width)
    return lanes


@dataclass
class ExampleFrames:
    """The frames of one instant kept for the bird's-eye figure: one Frame and its (M,) point counts per height."""

    frame_id: str
    frames: dict[str, Frame] = field(default_factory=dict)
    counts: dict[str, np.ndarray] = field(default_factory=dict)
    in_large: np.ndarray | None = None  # (M,) bool, boxes in the large range
    score: float = -1.0


class AbilityStudy:
    """Accumulate total and LiDAR-detected vehicles per height, range and level.

    Args:
        thresholds: minimum numbers of points inside the (lifted) box for "detected"; the
            first must be DETECTED_MIN_POINTS = 1 (the paper's rule, reported under "heights"),
            the others go to extras["min_points"].
        distance_bin: width in metres of the x bins of LDR against distance.
        bottom_lift: metres the box bottom is raised (DETECTED_BOTTOM_LIFT = 0.05, the paper's value).
        lane_width: metres, used only for boxes whose lane is LANE_UNKNOWN.
        keep_example: keep the instant whose heights differ most in detected vehicles (large
            range) for the bird's-eye figure; `example_frame_id` forces a given id instead.
        bootstrap: replicates of the scene bootstrap behind extras["uncertainty"] (0 = none).
        bootstrap_seed: seed of the bootstrap (the same counts and seed give the same intervals).
        difference_pairs: which paired height differences extras["uncertainty"] holds: "all" pairs
            (the default; three heights give three) or "adjacent" (each height against the next
            lower one; a sweep of 20 heights would otherwise hold 190).

    Per frame the cost is one points_in_boxes call and a few vectorised numpy operations;
    the nine masks are computed once per instant and reused across heights.
    """

    def __init__(self, thresholds: Sequence[int] = DEFAULT_THRESHOLDS, distance_bin: float = DEFAULT_BIN_M,
                 bottom_lift: float = DETECTED_BOTTOM_LIFT, lane_width: float = DEFAULT_LANE_WIDTH,
                 keep_example: bool = True, example_frame_id: str | None = None, bootstrap: int = DEFAULT_BOOTSTRAP,
                 bootstrap_seed: int = 0, difference_pairs: str = "all"):
        th = [int(t) for t in thresholds]
        if not th or th[0] != DETECTED_MIN_POINTS or any(t < 1 for t in th) or len(set(th)) != len(th):
            raise ValueError(f"thresholds must start with 1 (the paper's rule) and hold distinct integers >= 1, "
                             f"got {list(thresholds)}")
        if not distance_bin > 0:
            raise ValueError(f"distance_bin must be positive metres, got {distance_bin}")
        if difference_pairs not in ("all", "adjacent"):
            raise ValueError(f"difference_pairs must be 'all' or 'adjacent', got {difference_pairs!r}")
        self.difference_pairs = difference_pairs
        if int(bootstrap) < 0:
            raise ValueError(f"bootstrap must be >= 0 replicates, got {bootstrap}")
        self.bootstrap = int(bootstrap)
        self.bootstrap_seed = int(bootstrap_seed)
        self.thresholds = np.asarray(th, dtype=np.int64)
        self.distance_bin = float(distance_bin)
        self.bottom_lift = float(bottom_lift)
        self.lane_width = float(lane_width)
        self.num_bins = int(math.ceil(LDR_DISTANCE_MAX_M / self.distance_bin))
        self.keep_example = keep_example
        self.example_frame_id = example_frame_id
        self._total: dict[str, np.ndarray] = {}  # (9,) per height
        self._detected: dict[str, np.ndarray] = {}  # (T, 9)
        self._points_sum: dict[str, np.ndarray] = {}  # (9,) points inside detected boxes
        self._dist_total: dict[str, np.ndarray] = {}  # (B,)
        self._dist_detected: dict[str, np.ndarray] = {}  # (B,)
        self._frames: dict[str, int] = {}
        self._frame_ids: set[str] = set()
        # per cluster (scene id, or the frame id when a frame has none): {height: (2, 9) total, detected}
        self._clusters: dict[str, dict[str, np.ndarray]] = {}
        self._cluster_frames: dict[str, dict[str, int]] = {}  # frames per cluster and height
        self._frames_without_scene = 0
        self._cache_key = None
        self._cache = None
        self._group: ExampleFrames | None = None
        self.example: ExampleFrames | None = None

    # ------------------------------------------------------------------ feeding
    def _geometry(self, frame: Frame):
        """(9, M) masks and (M,) distance bin (-1 outside), cached across the heights of one instant."""
        key = frame.frame_id
        if self._cache_key == key and self._cache is not None:
            boxes, lanes, masks, bins = self._cache
            if boxes.shape == frame.boxes.shape and np.array_equal(boxes, frame.boxes) \
                    and np.array_equal(lanes, frame.lanes):
                return masks, bins
        boxes = np.asarray(frame.boxes)
        lanes = frame_lanes(frame, self.lane_width)
        masks = stacked_masks(boxes, lanes)
        x, y = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
        inside = (x >= 0) & (x <= LDR_DISTANCE_MAX_M) & (np.abs(y) <= LDR_DISTANCE_HALF_WIDTH_M)
        bins = np.where(inside, np.minimum((np.maximum(x, 0) / self.distance_bin).astype(np.int64),
                                           self.num_bins - 1), -1)
        self._cache_key = key
        self._cache = (boxes.copy(), np.asarray(frame.lanes).copy(), masks, bins)
        return masks, bins

    def add(self, frames: Frame | Iterable[Frame], counts: np.ndarray | Sequence[np.ndarray] | None = None,
            keys: Sequence[str] | None = None) -> None:
        """Count one frame, or the frames of one instant (one per height).

        `counts` (optional): precomputed (M,) points-per-box counts (with the 0.05 m lift) for
        each frame, e.g. from a simulator that counts while ray casting; by default they are
        computed with points_in_boxes. `keys` (optional): the name each frame is counted under
        (a rig's name) instead of its sensor's height.
        """
        if isinstance(frames, Frame):
            frames = [frames]
            counts = None if counts is None else [counts]
            keys = None if keys is None else [keys] if isinstance(keys, str) else keys
        frames = list(frames)
        if counts is not None and len(counts) != len(frames):
            raise ValueError(f"{len(counts)} count arrays for {len(frames)} frames")
        if keys is not None and len(keys) != len(frames):
            raise ValueError(f"{len(keys)} keys for {len(frames)} frames")
        for i, f in enumerate(frames):
            self._add_one(f, None if counts is None else np.asarray(counts[i], dtype=np.int64),
                          None if keys is None else str(keys[i]))

    def _add_one(self, frame: Frame, counts: np.ndarray | None, key: str | None = None) -> None:
        if not isinstance(frame, Frame):
            raise TypeError(f"AbilityStudy.add takes Frame objects, got {type(frame).__name__}")
        hk = key if key is not None else height_key(frame.sensor.height)
        if counts is None:
            counts = detected_point_counts(frame.points, frame.boxes, self.bottom_lift)
        elif counts.shape != (frame.num_boxes,):
            raise ValueError(f"frame {frame.frame_id}: counts has shape {counts.shape}, expected ({frame.num_boxes},)")
        masks, bins = self._geometry(frame)
        if hk not in self._total:
            c = len(CELLS)
            self._total[hk] = np.zeros(c, np.int64)
            self._detected[hk] = np.zeros((len(self.thresholds), c), np.int64)
            self._points_sum[hk] = np.zeros(c, np.int64)
            self._dist_total[hk] = np.zeros(self.num_bins, np.int64)
            self._dist_detected[hk] = np.zeros(self.num_bins, np.int64)
            self._frames[hk] = 0
        self._frames[hk] += 1
        if frame.frame_id not in self._frame_ids and not str(frame.scene_id or ""):
            self._frames_without_scene += 1
        self._frame_ids.add(frame.frame_id)
        cluster = str(frame.scene_id or "") or f"frame:{frame.frame_id}"
        per_height = self._clusters.setdefault(cluster, {})
        frames_here = self._cluster_frames.setdefault(cluster, {})
        frames_here[hk] = frames_here.get(hk, 0) + 1
        if hk not in per_height:
            per_height[hk] = np.zeros((2, len(CELLS)), np.int64)
        if frame.num_boxes:
            mi = masks.astype(np.int64)  # (9, M)
            det = (counts[None, :] >= self.thresholds[:, None]).astype(np.int64)  # (T, M)
            self._total[hk] += mi.sum(axis=1)
            self._detected[hk] += det @ mi.T
            per_height[hk][0] += mi.sum(axis=1)
            per_height[hk][1] += mi @ det[0]
            self._points_sum[hk] += mi @ (counts * det[0])
            sel = bins >= 0
            if sel.any():
                self._dist_total[hk] += np.bincount(bins[sel], minlength=self.num_bins)
                self._dist_detected[hk] += np.bincount(bins[sel], weights=det[0][sel],
                                                       minlength=self.num_bins).astype(np.int64)
        if self.keep_example:
            self._track_example(frame, hk, counts, masks)

    # ------------------------------------------------------------------ example for Fig. 5
    def _track_example(self, frame: Frame, hk: str, counts: np.ndarray, masks: np.ndarray) -> None:
        if self._group is None or self._group.frame_id != frame.frame_id:
            self._close_group()
            self._group = ExampleFrames(frame.frame_id, in_large=masks[_LARGE_ALL].copy())
        self._group.frames[hk] = frame
        self._group.counts[hk] = counts

    def _close_group(self) -> None:
        g = self._group
        self._group = None
        if g is None or not g.frames:
            return
        if self.example_frame_id is not None:
            if g.frame_id == self.example_frame_id:
                self.example = g
            return
        in_large = g.in_large
        det = [int(((c >= DETECTED_MIN_POINTS) & in_large).sum()) for c in g.counts.values()]
        # the instant whose heights differ most; ties go to the one with more vehicles in range
        g.score = (max(det) - min(det)) * 1000 + int(in_large.sum()) if len(det) > 1 else int(in_large.sum())
        if self.example is None or g.score > self.example.score:
            self.example = g

    def example_frames(self) -> ExampleFrames | None:
        """The kept instant (frames and counts per height) for the bird's-eye figure, or None."""
        self._close_group()
        return self.example

    # ------------------------------------------------------------------ results
    @property
    def heights(self) -> list[str]:
        """Height keys seen so far, ascending (names given as keys: in the order first seen)."""
        try:
            return sorted(self._total, key=float)
        except ValueError:
            return list(self._total)

    @property
    def num_frames(self) -> int:
        """Distinct frame ids seen (an instant at three heights counts once)."""
        return len(self._frame_ids)

    def cell(self, height: float | str, range_name: str, level: str, threshold: int = DETECTED_MIN_POINTS) -> dict:
        """{"total", "detected", "ldr"} of one (height, range, level) for a minimum point count."""
        hk = height if isinstance(height, str) else height_key(height)
        i = CELLS.index((range_name, level))
        t = int(np.flatnonzero(self.thresholds == threshold)[0])
        tot, det = int(self._total[hk][i]), int(self._detected[hk][t, i])
        return {"total": tot, "detected": det, "ldr": ldr(det, tot)}

    def _table(self, t_index: int) -> dict:
        out = {}
        for hk in self.heights:
            tot, det = self._total[hk], self._detected[hk][t_index]
            out[hk] = {r: {lv: {"total": int(tot[CELLS.index((r, lv))]), "detected": int(det[CELLS.index((r, lv))]),
                                "ldr": ldr(det[CELLS.index((r, lv))], tot[CELLS.index((r, lv))])}
                           for lv in LEVELS} for r in RANGE_NAMES}
        return out

    def report(self, source: dict | None = None) -> dict:
        """JSON-ready results.

        {"num_frames": N, "heights": {"<h>": {"<range_name>": {"<level>": {"total", "detected",
        "ldr"}}}}, "extras": {...}} with heights as decimal strings ("0.5", "1.0", "1.8"),
        ldr NaN (null in JSON) where total is 0. Extras: definitions, min_points (per
        threshold, same layout as "heights"), ldr_vs_distance, mean_points_per_detected,
        vehicles_per_frame, frames_per_height, example_frame, source.
        """
        self._close_group()
        heights = self.heights
        edges = [round(i * self.distance_bin, 6) for i in range(self.num_bins)] + [LDR_DISTANCE_MAX_M]
        per_frame = {}
        if heights:
            h0 = heights[0]
            n0 = max(self._frames[h0], 1)
            per_frame = {r: float(self._total[h0][CELLS.index((r, "all"))]) / n0 for r in RANGE_NAMES}
        mean_pts = {}
        for hk in heights:
            det = self._detected[hk][0]
            mean_pts[hk] = {r: (float(self._points_sum[hk][CELLS.index((r, "all"))]) / det[CELLS.index((r, "all"))]
                                if det[CELLS.index((r, "all"))] else float("nan")) for r in RANGE_NAMES}
        extras = {
            "definitions": {
                "detected": f"at least N points inside the box with its bottom raised by {self.bottom_lift} m "
                            f"(N = 1 in 'heights')",
                "bottom_lift_m": self.bottom_lift,
                "ranges_m": {r: {"x": [x0, x1], "abs_y_max": ym} for r, (x0, x1, ym) in RANGES.items()},
                "levels": {"all": "every vehicle in the range",
                           "top3": "nearest vehicle (BEV centre distance) in each of the ego, left and right lanes",
                           "top6": "two nearest vehicles in each of the ego, left and right lanes"},
                "ldr": "detected / total over all frames (null when total is 0)",
            },
            "min_points": {str(int(t)): self._table(i) for i, t in enumerate(self.thresholds)},
            "ldr_vs_distance": {
                "bin_m": self.distance_bin,
                "edges_m": edges,
                "region": f"box centre 0 <= x <= {LDR_DISTANCE_MAX_M:g} m, |y| <= {LDR_DISTANCE_HALF_WIDTH_M:g} m; "
                          f"binned by x",
                "heights": {hk: {"total": self._dist_total[hk].tolist(), "detected": self._dist_detected[hk].tolist(),
                                 "ldr": [ldr(d, t) for d, t in zip(self._dist_detected[hk], self._dist_total[hk])]}
                            for hk in heights},
            },
            "mean_points_per_detected": mean_pts,
            "vehicles_per_frame": per_frame,
            "frames_per_height": {hk: self._frames[hk] for hk in heights},
            "example_frame": None if self.example is None else self.example.frame_id,
            "paper_table_iv": {r: {"total": tot,
                                   "heights": {h: {"detected": d, "ldr": rate} for h, (d, rate) in hs.items()}}
                               for r, (tot, hs) in PAPER_TABLE_IV.items()},
        }
        extras["decomposition"] = decomposition(self._table(0))
        extras["uncertainty"] = self.uncertainty()
        if source is not None:
            extras["source"] = source
        return {"num_frames": self.num_frames, "heights": self._table(0), "extras": extras}

    def cluster_counts(self) -> tuple[list[str], list[str], np.ndarray]:
        """(cluster ids, heights, counts (C, H, 2, 9)): total and detected (>= 1 point) per
        cluster, height and cell. A cluster is a scene, or a lone frame that has no scene id;
        a height missing from a cluster counts zero there."""
        ids = sorted(self._clusters)
        heights = self.heights
        arr = np.zeros((len(ids), len(heights), 2, len(CELLS)), np.int64)
        for i, c in enumerate(ids):
            for j, hk in enumerate(heights):
                if hk in self._clusters[c]:
                    arr[i, j] = self._clusters[c][hk]
        return ids, heights, arr

    def cluster_frames(self) -> np.ndarray:
        """Frames per cluster and height, (C, H), in the order of `cluster_counts`."""
        ids, heights = sorted(self._clusters), self.heights
        return np.array([[self._cluster_frames.get(c, {}).get(hk, 0) for hk in heights] for c in ids],
                        dtype=np.int64).reshape(len(ids), len(heights))

    def uncertainty(self, confidence: float = 0.95) -> dict:
        """Sampling uncertainty of the LDRs from a percentile bootstrap over scenes.

        Returns {"method", "clusters" ("scene" or "frame" when some frames had no scene id),
        "num_clusters", "replicates", "confidence", "heights": {h: {range: {level: {"ci95":
        [lo, hi], "scene_std": s, "vehicles_per_frame_ci95": [lo, hi]}}}}, "differences": {"<hi>-<lo>":
        {range: {level: {"diff", "ci95"}}}}}. vehicles_per_frame_ci95 is the interval of the cell's vehicles
        per frame (the same scene resampling). scene_std is the standard deviation of one scene's LDR (scenes with
        vehicles in the cell); the standard error of a study of n such scenes is about
        scene_std / sqrt(n). Differences pair the heights within each resampled scene (the
        same traffic), so they are much tighter than the LDRs themselves. Values are null when
        fewer than 2 clusters were seen or bootstrap is 0.
        """
        ids, heights, arr = self.cluster_counts()
        n = len(ids)
        out = {"method": "percentile bootstrap over scenes (scenes resampled with replacement; the heights of a "
                         "scene stay together)",
               "clusters": "frame" if self._frames_without_scene else "scene",
               "num_clusters": n, "replicates": self.bootstrap, "confidence": confidence,
               "heights": {}, "differences": {}}
        ok = n >= 2 and self.bootstrap > 0
        if not ok:
            out["note"] = "needs at least 2 scenes and bootstrap > 0"
        tot, det = arr[:, :, 0, :].astype(np.float64), arr[:, :, 1, :].astype(np.float64)  # (C, H, 9)
        if ok:
            boot = bootstrap_ratios(scene_bootstrap_weights(n, self.bootstrap, self.bootstrap_seed), det, tot)
            with np.errstate(invalid="ignore", divide="ignore"):
                per_scene = np.where(tot > 0, det / np.where(tot > 0, tot, 1.0), np.nan)  # (C, H, 9)

        def interval(samples: np.ndarray) -> list | None:
            return percentile_interval(samples, confidence) if ok else None

        def spread(values: np.ndarray) -> float | None:
            good = values[np.isfinite(values)]
            return round(float(good.std(ddof=1)), 6) if ok and good.size >= 2 else None

        if ok:
            frames = self.cluster_frames().astype(np.float64)  # (C, H)
            w = scene_bootstrap_weights(n, self.bootstrap, self.bootstrap_seed)
            vpf_boot = np.einsum("bc,chk->bhk", w, tot) / np.maximum(w @ frames, 1.0)[:, :, None]  # (B, H, 9)
        for j, hk in enumerate(heights):
            out["heights"][hk] = {r: {lv: {"ci95": interval(boot[:, j, CELLS.index((r, lv))]) if ok else None,
                                           "scene_std": spread(per_scene[:, j, CELLS.index((r, lv))]) if ok else None,
                                           "vehicles_per_frame_ci95":
                                               interval(vpf_boot[:, j, CELLS.index((r, lv))]) if ok else None}
                                      for lv in LEVELS} for r in RANGE_NAMES}
        if self.difference_pairs == "adjacent":
            pairs = [(a, a + 1) for a in range(len(heights) - 1)]
        else:
            pairs = [(a, b) for a in range(len(heights)) for b in range(a + 1, len(heights))]
        for a, b in pairs:
            key = f"{heights[b]}-{heights[a]}" if _numeric(heights) else f"{heights[b]} - {heights[a]}"
            cells = {}
            for r in RANGE_NAMES:
                cells[r] = {}
                for lv in LEVELS:
                    k = CELLS.index((r, lv))
                    ta, tb = tot[:, a, k].sum(), tot[:, b, k].sum()
                    d = (ldr(det[:, b, k].sum(), tb) - ldr(det[:, a, k].sum(), ta))
                    cells[r][lv] = {"diff": None if math.isnan(d) else round(d, 6),
                                    "ci95": interval(boot[:, b, k] - boot[:, a, k]) if ok else None}
            out["differences"][key] = cells
        return out


def _numeric(keys: Sequence[str]) -> bool:
    """True when every key is a height (a number), False when some are names (rigs)."""
    try:
        [float(k) for k in keys]
    except ValueError:
        return False
    return True


# ---------------------------------------------------------------------------- decomposition
DECOMPOSITION_PARTS = {"second": ("top6", "top3"), "beyond": ("all", "top6")}  # part: (level minus level)


def decomposition(table: dict) -> dict:
    """The per-lane split the paper's tables imply, from a `heights` table ({height: {range: {level:
    {"total", "detected", "ldr"}}}}): second-in-lane = Top6 minus Top3 (the second-nearest vehicle of
    the ego, left and right lanes), beyond-Top6 = All minus Top6 (every other vehicle of the range).
    Returns {part: {height: {range: {"total", "detected", "ldr"}}}} (ldr NaN when the total is 0)."""
    out = {}
    for part, (a, b) in DECOMPOSITION_PARTS.items():
        out[part] = {}
        for hk, ranges in table.items():
            out[part][hk] = {}
            for r, cells in ranges.items():
                tot = int(cells[a]["total"]) - int(cells[b]["total"])
                det = int(cells[a]["detected"]) - int(cells[b]["detected"])
                out[part][hk][r] = {"total": tot, "detected": det, "ldr": ldr(det, tot)}
    return out


def paper_decomposition() -> dict:
    """`decomposition` of the paper's Tables IV-VI (8000 frames), same layout."""
    table = {h: {r: {lv: {"total": PAPER_TABLES[lv][r][0], "detected": PAPER_TABLES[lv][r][1][h][0],
                          "ldr": PAPER_TABLES[lv][r][1][h][1]} for lv in LEVELS} for r in RANGE_NAMES}
             for h in ("0.5", "1.0", "1.8")}
    return decomposition(table)


__all__ = ["AbilityStudy", "ExampleFrames", "decomposition", "paper_decomposition", "stacked_masks", "frame_lanes",
           "ldr", "CELLS", "DECOMPOSITION_PARTS", "DEFAULT_BOOTSTRAP", "DEFAULT_THRESHOLDS", "PAPER_TABLE_IV",
           "PAPER_TABLE_V", "PAPER_TABLE_VI", "PAPER_TABLES"]
