#!/usr/bin/env python3
"""Benchmark the highway LiDAR simulator: rays per second, frames per second, per-stage split.

Runs the simulator twice over the same frames: with points (what tools/simulate.py does)
and without points (what the streaming detection-ability study does: only the hit counts,
only rays in azimuth columns holding a vehicle). The numba compile (or cache load) is
timed separately on a warm-up frame.

Examples:
  python tools/bench_sim.py                      # 300 frames x 3 heights
  python tools/bench_sim.py --frames 1000 --out runs/bench_sim
  python tools/bench_sim.py --heights 0.5 1.8 --set traffic.density_per_km_lane=20
  python tools/bench_sim.py --frames 300 --load 1   # idle, then beside one busy process

Writes OUT/bench_sim.json and OUT/bench_sim.md. Times are wall-clock seconds on this
machine; the split is the sum over the run of each stage's time.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

from detbench import runtime  # noqa: E402  (first detbench import: thread-runtime defaults before numba starts)
from detbench.config import ConfigError  # noqa: E402
from detbench.utils.bench import idle_and_loaded, load_line, ratio, runtime_line  # noqa: E402
from detbench.utils.cli import UserError, check_out_dir, require, run_main  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text  # noqa: E402

STAGES = [
    ("traffic", "traffic step (IDM, lane changes, window)"),
    ("transform", "road -> ego frame, parts, barriers"),
    ("prepare", "per-object azimuth/slope bounds"),
    ("cull", "azimuth-column culling table"),
    ("cast", "ray casting (ground, boxes, parts)"),
    ("post", "noise, drop-off, intensity, max range"),
    ("count", "points in boxes (0.05 m lift) + compaction"),
]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description="Benchmark detbench's highway LiDAR simulator (rays/s, frames/s, "
                                             "per-stage split).",
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300, help="frames (instants) per measured run (default 300)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per scene (default: the preset's, 200); scene set-up time is included")
    ap.add_argument("--heights", type=float, nargs="+", default=[0.5, 1.0, 1.8], metavar="H",
                    help="LiDAR mounting heights in metres (default 0.5 1.0 1.8, the paper's Table II sensors)")
    ap.add_argument("--preset", default="paper", help="simulator preset from configs/sim.yaml (default paper)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator config override, repeatable")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    ap.add_argument("--mode", choices=("both", "points", "counts"), default="both",
                    help="measure with points, counts only (no points), or both (default)")
    ap.add_argument("--load", type=int, default=0, metavar="N",
                    help="measure again beside N busy-loop processes started for it (stopped after); the report has "
                         "idle and loaded figures side by side (default 0: idle only)")
    ap.add_argument("--out", default="runs/bench_sim", help="output folder for the JSON and Markdown")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


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
    all_rays = frames * sum(l.num_rays for l in lidars)
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


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    require(args.frames >= 1, f"--frames {args.frames}: must be an integer >= 1")
    require(args.load >= 0, f"--load {args.load}: must be an integer >= 0 (busy processes beside the second run)")
    require(args.frames_per_scene is None or args.frames_per_scene >= 1,
            f"--frames-per-scene {args.frames_per_scene}: must be an integer >= 1")
    check_out_dir(args.out)
    t_import = time.perf_counter()
    from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config
    import numba

    try:
        cfg = load_sim_config(args.preset, overrides=tuple(args.overrides))
        lidars = [lidar_preset(h) for h in args.heights]
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    fps = args.frames_per_scene or int(cfg["scene"]["frames_per_scene"])

    def factory():
        return HighwaySimulator(cfg, seed=args.seed)

    # warm-up: numba compile (first run on a machine) or cache load, one frame of each mode
    t0 = time.perf_counter()
    for wp in (True, False):
        for _ in factory().run(1, lidars, frames_per_scene=1, with_points=wp):
            pass
    warmup = time.perf_counter() - t0

    def measure() -> list[dict]:
        modes = [wp for wp, m in ((True, "points"), (False, "counts")) if args.mode in ("both", m)]
        return [_measure(factory, lidars, args.frames, fps, wp, not args.no_progress) for wp in modes]

    runs, loaded, load_info = idle_and_loaded(measure, args.load)
    for r, lr in zip(runs, loaded or []):
        r["loaded"] = {k: lr[k] for k in ("wall_s", "frames_per_s", "rays_traced_per_s")}
        r["loaded"]["wall_ratio"] = ratio(lr["wall_s"], r["wall_s"])
    pib = _pib_time(factory, lidars, min(args.frames, 100), fps) if args.mode != "counts" else None
    report = {
        "frames": args.frames, "frames_per_scene": fps, "heights": args.heights, "preset": args.preset,
        "overrides": list(args.overrides), "seed": args.seed,
        "lidars": [l.to_dict() for l in lidars],
        "warmup_s (import + numba compile or cache load + 2 frames)": round(warmup + (t0 - t_import), 3),
        "machine": {"cpus": os.cpu_count(), "numba_threads": numba.get_num_threads(),
                    "threading_layer": numba.threading_layer(), "python": platform.python_version(),
                    "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None},
        "runtime": runtime.describe(),
        "load": load_info,
        "runs": runs,
        "ops_points_in_boxes_ms_per_lidar_frame": None if pib is None else round(
            1e3 * pib / (min(args.frames, 100) * len(lidars)), 3),
    }
    out = Path(args.out)
    atomic_write_json(out / "bench_sim.json", report)
    md = ["# Simulator benchmark", "",
          f"{args.frames} frames x {len(lidars)} LiDARs ({', '.join(l.name for l in lidars)}), preset "
          f"`{args.preset}`, {fps} frames per scene, seed {args.seed}; numba threads "
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
    if load_info:
        md += ["", f"Loaded: the same runs beside {load_line(load_info)}.", "",
               "| mode | idle wall (s) | loaded wall (s) | x idle | idle frames/s | loaded frames/s |", "|---|---|---|---|---|---|"]
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
    atomic_write_text(out / "bench_sim.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
