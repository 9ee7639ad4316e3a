"""The height sweep: LiDAR detection ability and training-free placement scores for many heights of one sensor.

`HeightSweep` is a streaming accumulator like `AbilityStudy` (which it uses for the counts, the
Tables IV-VI layout, LDR against distance and the scene bootstrap): feed it the frames of one
instant at every height (`add(frames, counts)`, the same traffic at every height, e.g. one
`HighwaySimulator.run(n, lidars)` step) and ask for `report(coverage=...)`. It adds, per height:

- the evidence scores of detbench.studies.placement (per range, importance-weighted), with 95 %
  intervals from the same scene bootstrap as the LDRs (the same resampled scenes for every
  height, score and cell);
- LDR against distance with intervals;
- S-MIG (Hu et al. 2022) from the probabilistic occupancy grid of the same frames and the
  ray coverage of each height's sensor (`placement.ray_coverage`, computed by the caller, who
  knows the sensor);
- the best height per range and level (largest LDR) and the share of bootstrap replicates in
  which it is the best.

`sweep_markdown(report)` lays it out with heights as rows (20 heights do not fit as columns).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from detbench.data.frame import Frame, height_key
from detbench.data.regions import DETECTED_MIN_POINTS, LEVELS, RANGE_NAMES
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights
from detbench.studies.ability import (
    CELLS, LDR_DISTANCE_HALF_WIDTH_M, LDR_DISTANCE_MAX_M, AbilityStudy, frame_lanes, stacked_masks,
)
from detbench.studies.placement import (
    EVIDENCE_SCALE_POINTS, PRIMARY_SCORE, SCORE_NAMES, SCORE_UNITS, SUM_FIELDS, OccupancyGrid, VoxelGrid,
    evidence_sums, importance_weights, scores_from_sums, smig,
)

_EVIDENCE_SCORES = tuple(s for s in SCORE_NAMES if s != "smig")


class HeightSweep:
    """Accumulate one sensor at many heights on the same traffic (see the module doc).

    Args:
        distance_bin: metres per bin of LDR against distance.
        evidence_scale: n0 of the evidence q(n) = 1 - exp(-n / n0), in points.
        bootstrap: replicates of the scene bootstrap (0 = no intervals); bootstrap_seed seeds it.
        grid: the voxel grid of S-MIG's occupancy grid (default: the large range, 0.5 m voxels).
    """

    def __init__(self, distance_bin: float = 10.0, evidence_scale: float = EVIDENCE_SCALE_POINTS,
                 bootstrap: int = 1000, bootstrap_seed: int = 0, grid: VoxelGrid | None = None):
        if not evidence_scale > 0:
            raise ValueError(f"evidence_scale must be a positive number of points, got {evidence_scale}")
        self.study = AbilityStudy(thresholds=(DETECTED_MIN_POINTS,), distance_bin=distance_bin, keep_example=False,
                                  bootstrap=bootstrap, bootstrap_seed=bootstrap_seed, difference_pairs="adjacent")
        self.evidence_scale = float(evidence_scale)
        self.pog = OccupancyGrid(grid)
        self.num_bins = self.study.num_bins
        self.distance_bin = self.study.distance_bin
        # per cluster: {height: (4, 3) evidence sums}, {height: (2, B) distance total / detected}
        self._sums: dict[str, dict[str, np.ndarray]] = {}
        self._dist: dict[str, dict[str, np.ndarray]] = {}
        self._boxes_per_instant: list[int] = []

    def add(self, frames: Sequence[Frame], counts: Sequence[np.ndarray] | None = None) -> None:
        """Count the frames of one instant, one per height; they must share the traffic (the same
        frame id and boxes) and have distinct heights. counts: optional (M,) points per box (0.05 m lift)
        for each frame, e.g. the simulator's hit counts; by default counted from the points."""
        frames = list(frames)
        if not frames:
            raise ValueError("HeightSweep.add needs the frames of one instant, one per height")
        f0 = frames[0]
        keys = [height_key(f.sensor.height) for f in frames]
        if len(set(keys)) != len(keys):
            raise ValueError(f"frame {f0.frame_id}: heights must differ, got {keys} m")
        for f in frames[1:]:
            if f.frame_id != f0.frame_id or f.boxes.shape != f0.boxes.shape or not np.array_equal(f.boxes, f0.boxes):
                raise ValueError(f"frame {f.frame_id} at {height_key(f.sensor.height)} m does not share the traffic of "
                                 f"frame {f0.frame_id} at {keys[0]} m: a sweep compares heights on the same vehicles")
        self.study.add(frames, counts)
        if counts is None:
            from detbench.data.regions import detected_point_counts

            counts = [detected_point_counts(f.points, f.boxes) for f in frames]
        boxes = np.asarray(f0.boxes)
        masks = stacked_masks(boxes, frame_lanes(f0, self.study.lane_width))
        weights = importance_weights(masks)
        x, y = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
        inside = (x >= 0) & (x <= LDR_DISTANCE_MAX_M) & (np.abs(y) <= LDR_DISTANCE_HALF_WIDTH_M)
        bins = np.minimum((np.maximum(x[inside], 0) / self.distance_bin).astype(np.int64), self.num_bins - 1)
        cluster = str(f0.scene_id or "") or f"frame:{f0.frame_id}"
        sums = self._sums.setdefault(cluster, {})
        dist = self._dist.setdefault(cluster, {})
        for hk, c in zip(keys, counts):
            c = np.asarray(c, dtype=np.int64)
            s = evidence_sums(weights, c, self.evidence_scale)
            sums[hk] = sums[hk] + s if hk in sums else s
            d = np.zeros((2, self.num_bins), np.int64)
            if bins.size:
                d[0] = np.bincount(bins, minlength=self.num_bins)
                d[1] = np.bincount(bins, weights=(c[inside] >= DETECTED_MIN_POINTS), minlength=self.num_bins)
            dist[hk] = dist[hk] + d if hk in dist else d
        self.pog.add(boxes)
        self._boxes_per_instant.append(int(len(boxes)))

    @property
    def heights(self) -> list[str]:
        return self.study.heights

    def _per_cluster(self, store: dict, shape: tuple) -> tuple[list[str], np.ndarray]:
        ids, heights, _ = self.study.cluster_counts()
        arr = np.zeros((len(ids), len(heights)) + shape, np.float64)
        for i, c in enumerate(ids):
            for j, hk in enumerate(heights):
                if hk in store.get(c, {}):
                    arr[i, j] = store[c][hk]
        return ids, arr

    def report(self, coverage: dict[str, np.ndarray] | None = None, source: dict | None = None,
               confidence: float = 0.95) -> dict:
        """JSON-ready results (layout in docs/evaluation.md, "Height sweep").

        coverage: {height key: (nx, ny, nz) bool voxels observed by that height's sensor in the empty
        scene} (`placement.ray_coverage` on the sensor's rays); without it S-MIG is left out.
        """
        ability = self.study.report(source=source)
        heights = self.heights
        unc = ability["extras"]["uncertainty"]
        n_clusters = unc["num_clusters"]
        ok = n_clusters >= 2 and self.study.bootstrap > 0
        counts = self.study.cluster_counts()[2]  # (C, H, 2, 9)
        _, sums = self._per_cluster(self._sums, (len(SUM_FIELDS), len(RANGE_NAMES)))  # (C, H, 4, 3)
        _, dist = self._per_cluster(self._dist, (2, self.num_bins))  # (C, H, 2, B)
        weights = scene_bootstrap_weights(n_clusters, self.study.bootstrap, self.study.bootstrap_seed) if ok else None

        # evidence scores: point values and intervals (same resampled scenes as the LDRs)
        point = scores_from_sums(sums.sum(axis=0).transpose(1, 0, 2))  # {name: (H, 3)}
        boot = None
        if ok:
            bsum = np.tensordot(weights, sums, axes=(1, 0))  # (B, H, 4, 3)
            boot = scores_from_sums(np.moveaxis(bsum, 2, 0))  # {name: (B, H, 3)}
        scores: dict = {}
        smig_vals: dict = {}
        if coverage is not None:
            missing = [hk for hk in heights if hk not in coverage]
            if missing:
                raise ValueError(f"coverage lacks heights {missing} m")
            p = self.pog.probabilities()
            for hk in heights:
                smig_vals[hk] = {r: smig(p, coverage[hk], self.pog.grid.range_mask(r)) for r in RANGE_NAMES}
        for j, hk in enumerate(heights):
            scores[hk] = {}
            for ri, r in enumerate(RANGE_NAMES):
                cell = {}
                for name in _EVIDENCE_SCORES:
                    v = float(point[name][j, ri])
                    cell[name] = {"value": None if math.isnan(v) else round(v, 6),
                                  "ci95": percentile_interval(boot[name][:, j, ri], confidence) if ok else None}
                if smig_vals:
                    s = smig_vals[hk][r]
                    cell["smig"] = {"value": round(s["bits"], 3), "ci95": None,
                                    "fraction": None if math.isnan(s["fraction"]) else round(s["fraction"], 6),
                                    "covered_voxels": s["covered_voxels"], "region_voxels": s["region_voxels"]}
                scores[hk][r] = cell

        # LDR against distance with intervals
        edges = [round(i * self.distance_bin, 6) for i in range(self.num_bins)] + [LDR_DISTANCE_MAX_M]
        dist_out = {}
        bdist = bootstrap_ratios(weights, dist[:, :, 1, :], dist[:, :, 0, :]) if ok else None  # (B, H, B)
        tot_d, det_d = dist.sum(axis=0)[:, 0, :], dist.sum(axis=0)[:, 1, :]
        for j, hk in enumerate(heights):
            dist_out[hk] = {"total": [int(v) for v in tot_d[j]], "detected": [int(v) for v in det_d[j]],
                            "ldr": [None if t == 0 else round(float(d) / float(t), 6)
                                    for d, t in zip(det_d[j], tot_d[j])],
                            "ci95": [percentile_interval(bdist[:, j, b], confidence) if ok else None
                                     for b in range(self.num_bins)]}

        # best height per (range, level) by LDR, and how often the bootstrap agrees
        best = {}
        tot, det = counts[:, :, 0, :].astype(np.float64), counts[:, :, 1, :].astype(np.float64)
        bl = bootstrap_ratios(weights, det, tot) if ok else None  # (B, H, 9)
        for r in RANGE_NAMES:
            best[r] = {}
            for lv in LEVELS:
                k = CELLS.index((r, lv))
                vals = np.array([ability["heights"][hk][r][lv]["ldr"] for hk in heights], dtype=np.float64)
                if not np.isfinite(vals).any():
                    best[r][lv] = None
                    continue
                jb = int(np.nanargmax(vals))
                share = None
                if ok:
                    b = bl[:, :, k]
                    good = np.isfinite(b).all(axis=1)
                    if good.any():
                        share = round(float((np.argmax(b[good], axis=1) == jb).mean()), 4)
                best[r][lv] = {"height": heights[jb], "ldr": round(float(vals[jb]), 6), "bootstrap_share": share}

        totals_equal = all(len({ability["heights"][hk][r][lv]["total"] for hk in heights}) <= 1
                           for r in RANGE_NAMES for lv in LEVELS)
        return {
            "kind": "height_sweep",
            "num_frames": ability["num_frames"],
            "num_scenes": n_clusters,
            "heights": heights,
            "same_traffic": totals_equal,
            "ability": ability,
            "ldr_vs_distance": {"bin_m": self.distance_bin, "edges_m": edges,
                                "region": ability["extras"]["ldr_vs_distance"]["region"], "heights": dist_out},
            "best_height": best,
            "scores": {"definitions": score_definitions(self.evidence_scale, self.pog.grid),
                       "primary": PRIMARY_SCORE, "units": dict(SCORE_UNITS),
                       "occupancy": {"frames": self.pog.frames, "grid": self.pog.grid.to_dict(),
                                     "total_bits": {r: round(float(next(iter(smig_vals.values()))[r]["total_bits"]), 3)
                                                    for r in RANGE_NAMES} if smig_vals else None},
                       "heights": scores},
            "confidence": confidence,
        }


def score_definitions(scale: float, grid: VoxelGrid) -> dict:
    """The score definitions written into every sweep report (the long form is in docs/evaluation.md)."""
    return {
        "weight": "w(v) = 1 + [v in Top6] + [v in Top3] of the range (Top3 vehicles weigh 3, the second nearest "
                  "of each lane 2, others 1)",
        "evidence_q": f"q(n) = 1 - exp(-n / {scale:g}) for n points in the box (bottom raised 0.05 m)",
        "evidence": "sum w q(n) / sum w over the LiDAR-detected vehicles of the range, all frames",
        "evidence_all": "sum w q(n) / sum w over all vehicles of the range (q(0) = 0)",
        "points": "sum w n / sum w over the LiDAR-detected vehicles (mean points per detected vehicle)",
        "ldr_w": "sum w [n >= 1] / sum w over all vehicles (importance-weighted LDR)",
        "smig": f"Hu et al. 2022 S-MIG: sum of the binary entropy (bits) of the occupancy-grid voxels "
                f"({grid.voxel:g} m, centres in the range, z 0-{grid.z_max:g} m) that a ray of the sensor passes "
                f"through in the empty scene (road surface and max range stop rays; vehicles do not: occlusion-free)",
        "intervals": "95 % percentile bootstrap over scenes, the same resampled scenes for every height and score; "
                     "S-MIG has none (deterministic given the occupancy grid)",
    }


# ---------------------------------------------------------------------------- Markdown
def _f(v, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _ci(c, digits: int = 2) -> str:
    return "" if c is None else f" [{c[0]:.{digits}f}, {c[1]:.{digits}f}]"


def sweep_markdown(report: dict, title: str = "Height sweep") -> str:
    """Markdown of a `HeightSweep.report()`: Tables IV-VI with heights as rows, LDR against distance,
    the placement scores, adjacent-height differences, best heights and, when present, the correlation
    with trained detectors (report["correlation"], detbench.studies.rankcorr)."""
    ab = report["ability"]
    heights = report["heights"]
    unc = ab["extras"]["uncertainty"]
    src = ab["extras"].get("source") or {}
    out = [f"# {title}", ""]
    sensor = src.get("sensor") or {}
    if src:
        bits = [f"{k}={v}" for k, v in src.items() if not isinstance(v, (dict, list))]
        out += ["Source: " + ", ".join(bits), ""]
    if sensor:
        same = " Only the height changes between rows." if sensor.get("preset") != "paper" else \
            " These are the sensors detbench's simulated datasets use at each height."
        out += [f"Sensor: `{sensor.get('preset')}` ({sensor.get('description', '')}).{same}", ""]
    out += [f"{report['num_frames']} frames in {report['num_scenes']} scenes; {len(heights)} heights "
            f"({heights[0]}-{heights[-1]} m) on the same traffic" if heights else "no frames", ""]
    if heights and not report.get("same_traffic", True):
        out += ["**Warning: the totals differ between heights: the frames were not the same traffic.**", ""]
    out += ["A vehicle is LiDAR-detected when at least one point lies in its box with the bottom raised 0.05 m; "
            "LDR = detected / total, summed over frames. Ranges by box centre (metres): small 0<=x<=50, |y|<=5; "
            "moderate 0<=x<=100, |y|<=10; large 0<=x<=150, |y|<=15. Brackets: 95 % interval, bootstrap over "
            f"{unc['num_clusters']} scenes (the heights of a scene stay together).", ""]
    if not heights:
        return "\n".join(out)
    names = {"all": ("Table IV", "all vehicles"), "top3": ("Table V", "Top3 vehicles"),
             "top6": ("Table VI", "Top6 vehicles")}
    for lv in LEVELS:
        tab, what = names[lv]
        out += [f"## LiDAR detection of {what} (the paper's {tab}, heights as rows)", ""]
        tot = {r: ab["heights"][heights[0]][r][lv]["total"] for r in RANGE_NAMES}
        out += ["| height (m) | " + " | ".join(f"{r.capitalize()}: Number / LDR [95 %]" for r in RANGE_NAMES) + " |",
                "|---|" + "---|" * len(RANGE_NAMES),
                "| Total | " + " | ".join(str(tot[r]) for r in RANGE_NAMES) + " |"]
        for hk in heights:
            cells = []
            for r in RANGE_NAMES:
                c = ab["heights"][hk][r][lv]
                cells.append(f"{c['detected']} / {_f(c['ldr'])}{_ci(unc['heights'][hk][r][lv]['ci95'])}")
            out.append(f"| {hk} | " + " | ".join(cells) + " |")
        out.append("")
    out += ["## Best height by LDR", "",
            "Share: the fraction of bootstrap replicates (resampled scenes) in which the same height is the best.", "",
            "| range | " + " | ".join(f"{lv}: height (LDR, share)" for lv in LEVELS) + " |",
            "|---|" + "---|" * len(LEVELS)]
    for r in RANGE_NAMES:
        cells = []
        for lv in LEVELS:
            b = report["best_height"][r][lv]
            share = "-" if b is None or b["bootstrap_share"] is None else f"{b['bootstrap_share']:.2f}"
            cells.append("-" if b is None else f"{b['height']} m ({_f(b['ldr'])}, {share})")
        out.append(f"| {r.capitalize()} | " + " | ".join(cells) + " |")
    out.append("")
    diffs = unc.get("differences") or {}
    if diffs:
        out += ["## Adjacent heights: LDR difference (all vehicles) [95 %, paired on the same scenes]", "",
                "| heights (m) | " + " | ".join(r.capitalize() for r in RANGE_NAMES) + " |",
                "|---|" + "---|" * len(RANGE_NAMES)]
        for key, d in diffs.items():
            vals = [("-" if d[r]["all"]["diff"] is None else f"{d[r]['all']['diff']:+.3f}"
                     + _ci(d[r]["all"]["ci95"], 3)) for r in RANGE_NAMES]
            out.append(f"| {key} | " + " | ".join(vals) + " |")
        out.append("")
    dist = report["ldr_vs_distance"]
    edges = dist["edges_m"]
    out += [f"## LDR against distance ({dist['region']}; all vehicles)", "",
            "| height (m) | " + " | ".join(f"{edges[b]:g}-{edges[b + 1]:g} m" for b in range(len(edges) - 1)) + " |",
            "|---|" + "---|" * (len(edges) - 1)]
    for hk in heights:
        out.append(f"| {hk} | " + " | ".join(_f(v) for v in dist["heights"][hk]["ldr"]) + " |")
    out += ["", "Vehicles per bin (every height): " + ", ".join(str(v) for v in dist["heights"][heights[0]]["total"]),
            ""]
    sc = report["scores"]
    out += ["## Training-free placement scores", ""]
    out += [f"- `{k}`: {v}" for k, v in sc["definitions"].items()] + [""]
    has_smig = any("smig" in sc["heights"][hk][r] for hk in heights for r in RANGE_NAMES)
    names_here = [s for s in SCORE_NAMES if s != "smig" or has_smig]
    for r in RANGE_NAMES:
        out += [f"{r.capitalize()} range:", "",
                "| height (m) | " + " | ".join(f"{s} ({sc['units'][s]})" for s in names_here) + " |",
                "|---|" + "---|" * len(names_here)]
        for hk in heights:
            cells = []
            for s in names_here:
                c = sc["heights"][hk][r][s]
                if s == "smig":
                    cells.append(f"{_f(c['value'], 0)} "
                                 f"({_f(c['fraction'], 3)} of {sc['occupancy']['total_bits'][r]:.0f})")
                elif s == "points":
                    cells.append(f"{_f(c['value'], 0)}{_ci(c['ci95'], 0)}")
                else:
                    cells.append(f"{_f(c['value'], 3)}{_ci(c['ci95'], 3)}")
            out.append(f"| {hk} | " + " | ".join(cells) + " |")
        out.append("")
    corr = report.get("correlation")
    if corr:
        from detbench.studies.rankcorr import correlation_markdown

        out += [correlation_markdown(corr, report["scores"].get("primary")), ""]
    run = report.get("run")
    if run:
        out += ["## Run", "", ", ".join(f"{k}: {v}" for k, v in run.items() if not isinstance(v, dict)), ""]
    return "\n".join(out)


__all__ = ["HeightSweep", "sweep_markdown", "score_definitions"]
