"""The road model against the simulator's truth (tools/bench_road.py): how far the fitted surface is from
the road, which points it labels road, what it costs per frame, and how many points and voxels a model
is spared.

The simulator's road is the plane z = 0 of the ego ground frame the points are written in (its origin on
the road under the LiDAR; docs/data-format.md), and a noise-free ground return has z = 0 exactly. Per
frame, on the model's input (the points cropped to `point_cloud_range`):
- a true road point: |z| <= 1 mm and in no vehicle box (boxes with their bottom raised 0.05 m, the
  LiDAR-detected rule's lift, so the road inside a box's footprint is road);
- a vehicle point: inside a box with that lift;
- the surface's height error at x = 10, 40, 80, 120 m on the ego's line (y = 0): |fitted z - 0|;
- a LiDAR-detected vehicle (>= 1 point) of the model's range that loses all its points to the road label
  is counted: a detector cannot find a vehicle with no points;
- active voxels: distinct voxels of `voxel_size` holding a point, before and after the road removal.
Time: fit plus labelling of one frame, one thread, median over the frames (CPU time and wall time).
Units: metres, milliseconds, shares in [0, 1].
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Sequence

import numpy as np

from detbench.data.augment import crop_to_range
from detbench.data.regions import detected_point_counts, detected_point_index
from detbench.data.road import RoadConfig, road_mask

__all__ = ["PROBE_X", "active_voxels", "road_truth_frame", "road_truth_markdown", "road_truth_report"]

PROBE_X = (10.0, 40.0, 80.0, 120.0)  # m ahead, on y = 0, where the surface's height error is read
TRUE_ROAD_Z = 1e-3  # m: a simulated ground return has z = 0 exactly


def active_voxels(points: np.ndarray, voxel_size: Sequence[float], point_cloud_range: Sequence[float]) -> int:
    """Distinct voxels of `voxel_size` (metres) holding at least one of `points` (already in the range)."""
    if len(points) == 0:
        return 0
    lo = np.asarray(point_cloud_range[:3], np.float64)
    ijk = np.floor((points[:, :3].astype(np.float64) - lo) / np.asarray(voxel_size, np.float64)).astype(np.int64)
    return int(len(np.unique(ijk, axis=0)))


def road_truth_frame(points: np.ndarray, boxes: np.ndarray, cfg: RoadConfig, point_cloud_range: Sequence[float],
                     voxel_size: Sequence[float]) -> dict:
    """The figures of one frame (see the module doc); `points` and `boxes` as the frame holds them."""
    pts, in_range, _ = crop_to_range(np.asarray(points, np.float32), np.asarray(boxes, np.float32).reshape(-1, 7),
                                     point_cloud_range)
    t_cpu, t_wall = time.process_time(), time.perf_counter()
    mask, fit = road_mask(pts, cfg)
    cpu_ms, wall_ms = (time.process_time() - t_cpu) * 1000, (time.perf_counter() - t_wall) * 1000
    counts, index = detected_point_index(pts, in_range)
    vehicle = index >= 0
    true_road = (np.abs(pts[:, 2]) <= TRUE_ROAD_Z) & ~vehicle
    other = ~vehicle & ~true_road
    after = detected_point_counts(pts[~mask], in_range)
    detected = counts >= 1
    heights = fit.height(np.asarray(PROBE_X), np.zeros(len(PROBE_X))) if fit.ok else np.full(len(PROBE_X), np.nan)
    return {"points_before": int(len(pts)), "points_after": int((~mask).sum()),
            "true_road": int(true_road.sum()), "true_road_labelled": int((mask & true_road).sum()),
            "vehicle_points": int(vehicle.sum()), "vehicle_points_labelled": int((mask & vehicle).sum()),
            "other_points": int(other.sum()), "other_points_labelled": int((mask & other).sum()),
            "detected_vehicles": int(detected.sum()), "vehicles_emptied": int((detected & (after == 0)).sum()),
            "height_error_m": [float(abs(h)) for h in heights], "fit_ok": fit.ok,
            "voxels_before": active_voxels(pts, voxel_size, point_cloud_range),
            "voxels_after": active_voxels(pts[~mask], voxel_size, point_cloud_range),
            "cpu_ms": cpu_ms, "wall_ms": wall_ms}


def _share(rows: list[dict], part: str, whole: str) -> float | None:
    total = sum(r[whole] for r in rows)
    return None if total == 0 else sum(r[part] for r in rows) / total


def road_truth_report(frames_by_height: dict[float, Sequence], cfg: RoadConfig, point_cloud_range: Sequence[float],
                      voxel_size: Sequence[float]) -> dict:
    """{"heights": {height: summary}} over each height's frames (`Frame`s), after one untimed warm-up fit
    (numba's kernels load from their cache)."""
    out = {}
    for height, frames in frames_by_height.items():
        if len(frames):
            road_mask(np.asarray(frames[0].points, np.float32), cfg)  # warm-up: numba kernels
        rows = [road_truth_frame(f.points, f.boxes, cfg, point_cloud_range, voxel_size) for f in frames]
        if not rows:
            continue
        err = np.array([r["height_error_m"] for r in rows], np.float64)  # (frames, probes), NaN: no surface
        out[f"{float(height):g}"] = {
            "frames": len(rows),
            "frames_without_surface": int(sum(not r["fit_ok"] for r in rows)),
            "height_error_m": {f"{x:g}": {"median": _nan_none(np.nanmedian(err[:, i])),
                                          "max": _nan_none(np.nanmax(err[:, i]))}
                               for i, x in enumerate(PROBE_X)} if np.isfinite(err).any() else {},
            "true_road_labelled_share": _share(rows, "true_road_labelled", "true_road"),
            "vehicle_points_labelled_share": _share(rows, "vehicle_points_labelled", "vehicle_points"),
            "other_points_labelled_share": _share(rows, "other_points_labelled", "other_points"),
            "detected_vehicles": sum(r["detected_vehicles"] for r in rows),
            "vehicles_emptied": sum(r["vehicles_emptied"] for r in rows),
            "points_per_frame_before": statistics.median(r["points_before"] for r in rows),
            "points_per_frame_after": statistics.median(r["points_after"] for r in rows),
            "voxels_per_frame_before": statistics.median(r["voxels_before"] for r in rows),
            "voxels_per_frame_after": statistics.median(r["voxels_after"] for r in rows),
            "cpu_ms_per_frame": round(statistics.median(r["cpu_ms"] for r in rows), 2),
            "wall_ms_per_frame": round(statistics.median(r["wall_ms"] for r in rows), 2),
        }
    return {"heights": out}


def _nan_none(v) -> float | None:
    v = float(v)
    return None if not np.isfinite(v) else round(v, 4)


def road_truth_markdown(report: dict) -> str:
    """bench_road.md of a `road_truth_report` (with the tool's `meta` header fields)."""
    meta = report.get("meta", {})
    lines = [f"# The road model against the simulator's truth ({meta.get('data', '')})", "",
             f"Road config: {meta.get('road')}. Frames per height: {meta.get('frames')} of the {meta.get('split')} "
             f"split. Load average (1 min) before / after: {meta.get('load_before')} / {meta.get('load_after')} "
             f"on {meta.get('cpus')} CPUs. Units: metres, ms, shares.", "",
             "| height (m) | err@10 med/max | err@40 | err@80 | err@120 | road labelled | vehicle pts lost | "
             "other pts labelled | vehicles emptied / detected | points/frame before -> after | "
             "voxels/frame before -> after | CPU ms/frame | wall ms/frame |",
             "|" + "---|" * 13]

    def pct(v):
        return "-" if v is None else f"{100 * v:.2f} %"

    def err(s, x):
        e = s["height_error_m"].get(f"{x:g}")
        if not e or e["median"] is None:
            return "-"
        return f"{e['median']:.3f} / {e['max']:.3f}"

    for h, s in report["heights"].items():
        lines.append(
            f"| {h} | {err(s, 10.0)} | {err(s, 40.0)} | {err(s, 80.0)} | {err(s, 120.0)} | "
            f"{pct(s['true_road_labelled_share'])} | {pct(s['vehicle_points_labelled_share'])} | "
            f"{pct(s['other_points_labelled_share'])} | {s['vehicles_emptied']} / {s['detected_vehicles']} | "
            f"{s['points_per_frame_before']:.0f} -> {s['points_per_frame_after']:.0f} | "
            f"{s['voxels_per_frame_before']:.0f} -> {s['voxels_per_frame_after']:.0f} | "
            f"{s['cpu_ms_per_frame']:.1f} | {s['wall_ms_per_frame']:.1f} |")
    return "\n".join(lines) + "\n"
