#!/usr/bin/env python3
"""Simulate a multi-height LiDAR dataset on a highway and write it in the detbench layout.

Every frame, LiDARs at all requested heights see the same traffic at the same instant
(see detbench/sim and docs/data-format.md for the layout).

Examples:
  python tools/simulate.py --out data/sim --frames 2000 --heights 0.5 1.0 1.8 --seed 0
  python tools/simulate.py --out data/sim_small --scenes 2 --frames-per-scene 50 --set traffic.density_per_km_lane=15
  python tools/simulate.py --out data/table1 --frames 400 --lidars ideal-l8 xpeng-g9 arcfox-as-hi
  python tools/simulate.py --out data/rigs --frames 400 --rigs forehead headlights
  python tools/simulate.py --out data/test200 --frames 2000 --frames-per-scene 10 --frame-stride 20 \
      --heights 0.5 1.8 --seed 1 --test-fraction 0.99   # 198 held-out test scenes of the cpu preset's world

Writes the dataset into OUT plus OUT/simulate_run.json (machine-readable summary) and
OUT/simulate_run.md (the same for humans).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.config import ConfigError, shipped_default
from detbench.utils.cli import UserError, add_sim_preset_argument, run_main
from detbench.utils.atomic import DiskFullError
from detbench.utils.staged_folders import recover_staged


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description="Simulate highway LiDAR frames at several mounting heights (same traffic, same instant) and "
                    "write them as a detbench dataset.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Frame ids are SSSS_III (scene, index); the train/test split is by scene. "
               "Config keys: see configs/sim.yaml.")
    ap.add_argument("--out", required=True, metavar="ROOT", help="output folder of the dataset (created)")
    ap.add_argument("--frames", type=int, default=None, metavar="N",
                    help="total number of frames (instants; each is written at every height). "
                         "Default: --scenes x frames per scene")
    ap.add_argument("--scenes", type=int, default=None, metavar="K",
                    help="number of scenes (default: enough scenes for --frames)")
    ap.add_argument("--frames-per-scene", type=int, default=None, metavar="F",
                    help="frames per scene, saved at the --sim-preset's frame rate (2 Hz, so 0.5 s apart). "
                         "Default: the --sim-preset's (200 as in the paper), or frames/scenes when both are given")
    ap.add_argument("--frame-stride", type=int, default=1, metavar="K",
                    help="keep every K-th frame of the --sim-preset's frame rate, so a scene of F frames spans F x K "
                         "frames of time and a few frames per scene sample the whole course of its traffic (the cpu "
                         "and quick presets' data: --frames-per-scene 10 --frame-stride 20, 10 s apart). Default 1")
    ap.add_argument("--heights", type=float, nargs="+", default=None, metavar="H",
                    help="LiDAR mounting heights in metres (default 0.5 1.0 1.8). 0.5, 1.0 and 1.8 are the "
                         "paper's Table II sensors; other heights take the 1.0 m specification")
    ap.add_argument("--lidars", nargs="+", default=None, metavar="NAME",
                    help="LiDAR presets instead of --heights, e.g. h3-1.8 ideal-l8 xpeng-g9 (Table I); their "
                         "heights must differ")
    ap.add_argument("--rigs", nargs="+", default=None, metavar="NAME",
                    help="LiDAR rigs instead of --heights (configs/rigs.yaml or --rig-file; docs/rigs.md): one points "
                         "folder per rig, its sensors' returns merged in the ego frame, with each point's sensor in "
                         "sensor_index/<rig>/; train on one with --height NAME")
    ap.add_argument("--rig-file", default=None, metavar="PATH",
                    help="(--rigs) a rig file with the keys of configs/rigs.yaml (default configs/rigs.yaml)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (same seed and config: identical files)")
    add_sim_preset_argument(ap)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, repeatable, e.g. --set traffic.density_per_km_lane=15 "
                         "(unknown keys are errors)")
    ap.add_argument("--range-noise", type=float, default=None, metavar="M",
                    help="standard deviation of the range noise in metres for every LiDAR "
                         "(default: the --sim-preset's, 0)")
    ap.add_argument("--dropout", type=float, default=None, metavar="P",
                    help="probability in [0, 1] that a return is dropped, for every LiDAR (default 0)")
    ap.add_argument("--test-fraction", type=float, default=shipped_default("data.test_fraction"),
                    help="share of scenes in the test split (default %(default).4g)")
    ap.add_argument("--drop-frames-without", choices=("small", "moderate", "large"), default=None, metavar="RANGE",
                    help="frames with no vehicle in this range (small, moderate or large) join neither split, as "
                         "the paper drops its 987 frames without vehicles (the paper preset's training data uses "
                         "large); default: keep every frame")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace a dataset already in --out (the new one is built beside it and swapped in when "
                         "complete, so an interrupted run leaves the old one; --out must hold only a dataset's files)")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from detbench.sim import HighwaySimulator, load_sim_config
    from detbench.sim.dataset import (check_space, estimate_dataset_bytes, human_bytes, plan_frames,
                                      strided_overrides, write_simulation)
    from detbench.sim.run import RunSummary, run_lidars, run_rigs, simulation_source

    from detbench.data.frame import height_key

    for h in args.heights or ():
        try:
            height_key(h)
        except ValueError as e:
            raise UserError(f"--heights {h:g}: {e}") from None
    if args.frame_stride < 1:
        raise UserError(f"--frame-stride {args.frame_stride}: keep every K-th frame, K an integer >= 1")
    try:
        args.overrides = strided_overrides(args.sim_preset, args.overrides, args.frame_stride)  # as the presets' data
        cfg = load_sim_config(args.sim_preset, overrides=tuple(args.overrides))
        frames, fps = plan_frames(args.frames, args.scenes, args.frames_per_scene,
                                  int(cfg["scene"]["frames_per_scene"]))
        if sum(bool(v) for v in (args.lidars, args.heights, args.rigs)) > 1:
            raise ValueError("give one of --heights, --lidars and --rigs")
        if args.rig_file and not args.rigs:
            raise ValueError("--rig-file needs --rigs NAME [NAME ...]")
        if args.rigs and (args.range_noise is not None or args.dropout is not None):
            raise ValueError("--range-noise and --dropout: set them per sensor in the rig file (range_noise_m, "
                             "dropout) for --rigs")
        if args.rigs:
            lidars = run_rigs(args.rigs, args.rig_file)
        else:
            lidars = run_lidars(args.lidars or args.heights, range_noise=args.range_noise, dropout=args.dropout)
        sim = HighwaySimulator(cfg, seed=args.seed)
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None

    out = Path(args.out)
    what = "rigs" if args.rigs else "heights"
    source = simulation_source(cfg, lidars, preset=args.sim_preset, seed=args.seed, overrides=args.overrides,
                               frames=frames, frames_per_scene=fps)
    if args.frame_stride > 1:
        source["frame_stride"] = args.frame_stride
    summary = RunSummary(out, lidars, frames=frames, frames_per_scene=fps, seed=args.seed, preset=args.sim_preset,
                         overrides=args.overrides)
    for note in recover_staged(out):
        print(f"note: {note}", file=sys.stderr)
    size = estimate_dataset_bytes(lidars, frames)
    try:
        free = check_space(out, size, what=f"the dataset ({frames} frames x {len(lidars)} {what})",
                           fix="free some space there, give --out on a larger filesystem, or simulate fewer "
                               "--frames or --heights")
    except DiskFullError as e:
        raise UserError(f"--out {e}") from None
    print(f"simulating {frames} frames x {len(lidars)} {what} into {out}: about {human_bytes(size)} on disk "
          f"({human_bytes(free)} free)")
    try:
        write_simulation(out, sim, lidars, frames, source=source, frames_per_scene=fps,
                         test_fraction=args.test_fraction, overwrite=args.overwrite, progress=not args.no_progress,
                         on_step=summary.tally, finish=summary.write, drop_frames_without=args.drop_frames_without)
    except (FileExistsError, ValueError, TypeError) as e:
        raise UserError(str(e)) from None
    except DiskFullError as e:
        raise UserError(f"{e.path}: could not be written: {e.reason}; the new dataset was being built there, "
                        f"beside {out}, and that folder is removed, so {out} is unchanged; free some space in "
                        f"{out.parent} (or raise the limit), then run the same command again") from None
    seconds = time.perf_counter() - summary.t0
    print(f"wrote {frames} frames x {len(lidars)} {what} to {out} in {seconds:.1f} s "
          f"(summary: {out / 'simulate_run.md'})")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
