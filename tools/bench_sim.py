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
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench import runtime  # noqa: F401  (first detbench import: thread-runtime defaults before numba starts)
from detbench.config import ConfigError
from detbench.utils.cli import UserError, add_sim_preset_argument, check_out_dir, require, run_main
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description="Benchmark detbench's highway LiDAR simulator (rays/s, frames/s, "
                                             "per-stage split).",
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300, help="frames (instants) per measured run (default 300)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per scene (default: the --sim-preset's, 200); scene set-up time is included")
    ap.add_argument("--heights", type=float, nargs="+", default=[0.5, 1.0, 1.8], metavar="H",
                    help="LiDAR mounting heights in metres (default 0.5 1.0 1.8, the paper's Table II sensors)")
    add_sim_preset_argument(ap)
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


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    require(args.frames >= 1, f"--frames {args.frames}: must be an integer >= 1")
    require(args.load >= 0, f"--load {args.load}: must be an integer >= 0 (busy processes beside the second run)")
    require(args.frames_per_scene is None or args.frames_per_scene >= 1,
            f"--frames-per-scene {args.frames_per_scene}: must be an integer >= 1")
    check_out_dir(args.out)
    t_import = time.perf_counter()
    from detbench.benchmarks.sim import run_sim_bench, sim_bench_markdown
    from detbench.sim import lidar_preset, load_sim_config

    try:
        cfg = load_sim_config(args.sim_preset, overrides=tuple(args.overrides))
        lidars = [lidar_preset(h) for h in args.heights]
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    report = run_sim_bench(cfg, lidars, frames=args.frames, frames_per_scene=args.frames_per_scene, seed=args.seed,
                           mode=args.mode, load=args.load, progress=not args.no_progress, preset=args.sim_preset,
                           overrides=args.overrides, heights=args.heights, started=t_import)
    out = Path(args.out)
    atomic_write_json(out / "bench_sim.json", report)
    md = sim_bench_markdown(report)
    atomic_write_text(out / "bench_sim.md", md)
    print(md, end="")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
