"""Measure the road model (detbench/data/road.py) against the simulator's truth, the road plane z = 0.

Per mounting height, on --frames evenly spaced frames of the dataset's --split (the preset's simulated
default dataset unless --data is given), on the model input (points cropped to SECOND's point-cloud
range): the fitted surface's height error at x = 10, 40, 80, 120 m (median and max, metres), the share of
true road points labelled road, of vehicle points labelled road (lost) and of other points labelled
road, the LiDAR-detected vehicles that lose every point, points and active voxels per frame before and
after the road removal (voxels of SECOND's voxel size in the preset), and the fit's time per frame (one
thread, ms). The road settings are configs/default.yaml `road:` with --set road.KEY=VALUE overrides.
The load average is recorded: on a shared machine the times are upper bounds.
Writes bench_road.json and bench_road.md to --out.

Usage: python tools/bench_road.py --preset quick --frames 20 [--out DIR] [--heights 0.5 1.0 1.8]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)
import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)

import numba
import numpy as np
import torch

from detbench.benchmarks.road import road_truth_markdown, road_truth_report
from detbench.config import ConfigError
from detbench.data import Height3Dataset
from detbench.data.road import RoadConfig
from detbench.train.run_config import load_run_config, preset_names
from detbench.utils.cli import UserError, check_out_dir, require, run_main
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/bench_road",
                    help="output folder for bench_road.json and bench_road.md (default: %(default)s)")
    ap.add_argument("--preset", default="quick", choices=preset_names(),
                    help="preset whose simulated dataset and SECOND voxel size are used (default %(default)s)")
    ap.add_argument("--data", default=None, metavar="ROOT", help="a dataset folder instead of the preset's")
    ap.add_argument("--heights", type=float, nargs="+", default=None,
                    help="mounting heights in metres (default: every height of the dataset)")
    ap.add_argument("--frames", type=int, default=20, help="frames per height, evenly spaced (default %(default)s)")
    ap.add_argument("--split", default="test", choices=["train", "test", "all"], help="split (default %(default)s)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="run-config override, e.g. --set road.margin=0.1 (repeatable)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    require(args.frames >= 1, f"--frames {args.frames}: must be an integer >= 1")
    check_out_dir(args.out)
    from detbench.sim.dataset import default_dataset

    try:
        cfg = load_run_config("second", args.preset, overrides=args.overrides)
        road = RoadConfig.from_dict(cfg["road"])
    except ConfigError as e:
        raise UserError(str(e)) from None
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    try:
        root = default_dataset({**cfg["data"], "root": args.data} if args.data else cfg["data"])
    except FileNotFoundError as e:
        raise UserError(f"--data {e}") from None
    heights = args.heights
    if heights is None:
        from detbench.data import read_info

        heights = sorted(read_info(root).heights)
    frames_by_height = {}
    for h in heights:
        try:
            ds = Height3Dataset(root, float(h), args.split)
        except (FileNotFoundError, KeyError, ValueError) as e:
            raise UserError(f"{root}: no frames at {h:g} m ({e}); pick one of the dataset's heights") from None
        idx = np.unique(np.linspace(0, len(ds) - 1, num=min(args.frames, len(ds))).astype(int)) if len(ds) else []
        frames_by_height[float(h)] = [ds[int(i)] for i in idx]
    load_before = os.getloadavg()[0]
    report = road_truth_report(frames_by_height, road, cfg["model"]["point_cloud_range"], cfg["model"]["voxel_size"])
    report["meta"] = {"data": str(root), "split": args.split, "frames": args.frames, "preset": args.preset,
                      "road": {k: v for k, v in cfg["road"].items()}, "voxel_size": cfg["model"]["voxel_size"],
                      "point_cloud_range": cfg["model"]["point_cloud_range"], "threads": 1,
                      "cpus": os.cpu_count(), "load_before": round(load_before, 2),
                      "load_after": round(os.getloadavg()[0], 2)}
    out = Path(args.out)
    atomic_write_json(out / "bench_road.json", report)
    atomic_write_text(out / "bench_road.md", road_truth_markdown(report))
    print(road_truth_markdown(report))
    print(f"wrote {out / 'bench_road.json'} and {out / 'bench_road.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
