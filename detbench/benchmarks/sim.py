"""The simulator benchmark (tools/bench_sim.py): rays and frames per second of detbench's highway LiDAR
simulator with points and with counts only, idle and beside busy processes, split by stage, and the
on-disk analysis path (detbench.ops.points_in_boxes) on the same point clouds for comparison."""
from __future__ import annotations

import os
import platform
import time

import numba

from detbench import runtime
from detbench.sim import HighwaySimulator
from detbench.sim.lidar import LidarConfig
from detbench.utils.bench import idle_and_loaded, load_line, ratio, runtime_line

__all__ = ["STAGES", "run_sim_bench", "sim_bench_markdown"]

STAGES = [
    ("traffic", "traffic step (IDM, lane changes, window)"),
    ("transform", "road -> ego frame, parts, barriers"),
    ("prepare", "per-object azimuth/slope bounds"),
    ("cull", "azimuth-column culling table"),
    ("cast", "ray casting (ground, boxes, parts)"),
    ("post", "noise, drop-off, intensity, max range"),
    ("count", "points in boxes (0.05 m lift) + compaction"),
]


def _measure(sim_factory, lidars, frames, fps, with_points, progress):
    from tqdm import tqdm

    sim = sim_factory()
    rays = points = 0
    t0 = time.perf_counter()
    for step in tqdm(sim.run(frames, lidars, frames_per_scene=fps, with_points=with_points), total=frames,
                     desc="points" if with_points else "counts", unit="frame", disable=not progress):
        for f in step:
            rays += f.rays_cast
            points += f.points.shape[0]
    wall = time.perf_counter() - t0
    stages = {k: sim.timings.get(k, 0.0) for k, _ in STAGES}
    other = max(wall - sum(stages.values()), 0.0)
    all_rays = frames * sum(lidar.num_rays for lidar in lidars)
    return {
        "with_points": with_points,
        "frames": frames,
        "wall_s": round(wall, 3),
        "frames_per_s": round(frames / wall, 2),
        "lidar_frames_per_s": round(frames * len(lidars) / wall, 2),
        "rays_traced": int(rays),
        "rays_traced_per_s": round(rays / wall, 1),
        "scan_rays_per_s": round(all_rays / wall, 1),
        "points_per_lidar_frame": round(points / max(frames * len(lidars), 1), 1),
        "stages_s": {k: round(v, 4) for k, v in stages.items()} | {"other (python, frames)": round(other, 4)},
        "stages_ms_per_frame": {k: round(1e3 * v / frames, 3) for k, v in stages.items()}
        | {"other (python, frames)": round(1e3 * other / frames, 3)},
    }


def _pib_time(sim_factory, lidars, frames, fps):
    """Seconds that detbench.ops.points_in_boxes takes on the same frames (the on-disk analysis path)."""
    try:
        from detbench.data.regions import DETECTED_BOTTOM_LIFT
        from detbench.ops import points_in_boxes
    except ImportError:
        return None
    total = 0.0
    for step in sim_factory().run(frames, lidars, frames_per_scene=fps, with_points=True):
        for f in step:
            t = time.perf_counter()
            points_in_boxes(f.points, f.boxes, bottom_lift=DETECTED_BOTTOM_LIFT)
            total += time.perf_counter() - t
    return total


def run_sim_bench(cfg: dict, lidars: list[LidarConfig], *, frames: int, frames_per_scene: int | None = None,
                  seed: int = 0, mode: str = "both", load: int = 0, progress: bool = True, preset: str = "",
                  overrides=(), heights: list[float] | None = None, started: float | None = None) -> dict:
    """The report of bench_sim.json: `frames` instants seen by `lidars` under the simulator config `cfg`,
    with points and/or counts only (`mode` both | points | counts), idle and, with `load`, beside busy
    processes. `preset` and `overrides` name `cfg` in the report, `heights` the LiDARs (default their
    heights); `started` (a time.perf_counter() value,
    default now) counts the caller's set-up (imports, config) into the warm-up figure."""
    started = time.perf_counter() if started is None else started
    fps = frames_per_scene or int(cfg["scene"]["frames_per_scene"])

    def factory():
        return HighwaySimulator(cfg, seed=seed)

    # warm-up: numba compile (first run on a machine) or cache load, one frame of each mode
    t0 = time.perf_counter()
    for wp in (True, False):
        for _ in factory().run(1, lidars, frames_per_scene=1, with_points=wp):
            pass
    warmup = time.perf_counter() - t0

    def measure() -> list[dict]:
        modes = [wp for wp, m in ((True, "points"), (False, "counts")) if mode in ("both", m)]
        return [_measure(factory, lidars, frames, fps, wp, progress) for wp in modes]

    runs, loaded, load_info = idle_and_loaded(measure, load)
    for r, lr in zip(runs, loaded or []):
        r["loaded"] = {k: lr[k] for k in ("wall_s", "frames_per_s", "rays_traced_per_s")}
        r["loaded"]["wall_ratio"] = ratio(lr["wall_s"], r["wall_s"])
    pib = _pib_time(factory, lidars, min(frames, 100), fps) if mode != "counts" else None
    report = {
        "frames": frames, "frames_per_scene": fps,
        "heights": heights if heights is not None else [lidar.height for lidar in lidars],
        "preset": preset, "overrides": list(overrides), "seed": seed,
        "lidars": [lidar.to_dict() for lidar in lidars],
        "warmup_s (import + numba compile or cache load + 2 frames)": round(warmup + (t0 - started), 3),
        "machine": {"cpus": os.cpu_count(), "numba_threads": numba.get_num_threads(),
                    "threading_layer": numba.threading_layer(), "python": platform.python_version(),
                    "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None},
        "runtime": runtime.describe(),
        "load": load_info,
        "runs": runs,
        "ops_points_in_boxes_ms_per_lidar_frame": None if pib is None else round(
            1e3 * pib / (min(frames, 100) * len(lidars)), 3),
    }
    return report


def sim_bench_markdown(report: dict) -> str:
    """bench_sim.md: the report as tables."""
    runs = report["runs"]
    md = ["# Simulator benchmark", "",
          f"{report['frames']} frames x {len(report['lidars'])} LiDARs "
          f"({', '.join(lidar['name'] for lidar in report['lidars'])}), preset `{report['preset']}`, "
          f"{report['frames_per_scene']} frames per scene, seed {report['seed']}; numba threads "
          f"{report['machine']['numba_threads']} ({report['machine']['threading_layer']}), load average "
          f"{report['machine']['load_average_1min']} at the end.", "",
          f"Warm-up (import, numba compile or cache load, 2 frames): "
          f"{report['warmup_s (import + numba compile or cache load + 2 frames)']} s.", "",
          "| mode | wall (s) | frames/s | LiDAR frames/s | rays traced/s | scan rays/s | points per LiDAR frame |",
          "|---|---|---|---|---|---|---|"]
    for r in runs:
        md.append(f"| {'points' if r['with_points'] else 'counts only'} | {r['wall_s']} | {r['frames_per_s']} | "
                  f"{r['lidar_frames_per_s']} | {r['rays_traced_per_s']:.3g} | {r['scan_rays_per_s']:.3g} | "
                  f"{r['points_per_lidar_frame']} |")
    if report["load"]:
        md += ["", f"Loaded: the same runs beside {load_line(report['load'])}.", "",
               "| mode | idle wall (s) | loaded wall (s) | x idle | idle frames/s | loaded frames/s |",
               "|---|---|---|---|---|---|"]
        md += [f"| {'points' if r['with_points'] else 'counts only'} | {r['wall_s']} | {r['loaded']['wall_s']} | "
               f"{r['loaded']['wall_ratio']} | {r['frames_per_s']} | {r['loaded']['frames_per_s']} |" for r in runs]
    md += ["", f"Thread runtimes: {runtime_line(report['runtime'])}."]
    md += ["", "Per-stage split (milliseconds per frame, all LiDARs; idle run):", "",
           "| stage | what | " + " | ".join('points' if r['with_points'] else 'counts only' for r in runs) + " |",
           "|---|---|" + "---|" * len(runs)]
    for k, what in STAGES + [("other (python, frames)", "frame objects, generator, progress")]:
        md.append(f"| {k} | {what} | " + " | ".join(f"{r['stages_ms_per_frame'][k]:.3f}" for r in runs) + " |")
    if report["ops_points_in_boxes_ms_per_lidar_frame"] is not None:
        md += ["", f"For comparison, `detbench.ops.points_in_boxes` on the same point clouds: "
                   f"{report['ops_points_in_boxes_ms_per_lidar_frame']} ms per LiDAR frame."]
    md += ["", "Scan rays/s counts every ray of every scan (channels x samples); rays traced/s only those the "
               "caster followed (counts-only mode skips azimuth columns without a vehicle)."]
    return "\n".join(md) + "\n"
