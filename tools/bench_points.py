"""Benchmark the PointNet++ / PointRCNN point operations of detbench.ops on 1.8 m LiDAR scans.

Each scan is sampled to --points points (16384, PointRCNN's input), in scan order. Timed, in
milliseconds (median and best of --repeats runs after one warm-up call, so numba compilation
or cache loading is excluded), per call on the whole batch of --frames scans:
  - farthest point sampling --points -> --samples (4096), numba kernel (CPU) and torch path;
  - PointRCNN's four MSG set-abstraction levels (4096, 1024, 256, 64 centres; radii 0.1/0.5,
    0.5/1.0, 1.0/2.0, 2.0/4.0 m; 16/32 samples): FPS + ball query + grouping of xyz;
  - the four feature-propagation levels back to --points (three_nn_interpolate, C channels);
  - RoI point pooling of --rois car-sized RoIs per scan (512 points, 1.0 m extra, C features);
  - rotated BEV NMS of --nms-boxes proposals crowded round 40 vehicles to --nms-keep (the two-stage
    detectors' training budget), numba kernel and torch path (the GPU's), and their ratio.
The load average of the machine is recorded before and after (the machine may be shared);
The thread runtimes are detbench's (detbench/runtime.py): GOMP_SPINCOUNT=3000 (a waiting OpenMP thread spins
briefly, then sleeps), OMP_NUM_THREADS = cores - 1, NUMBA_THREADING_LAYER=omp; a variable set in the
environment wins (e.g. OMP_WAIT_POLICY=PASSIVE to measure with threads that sleep at once).
Writes bench_points.json and bench_points.md to --out.

Usage: python tools/bench_points.py [--out DIR] [--frames N] [--points N] [--samples N] ...  (see --help)
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)
import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)

import numba
import torch

from detbench.benchmarks.points import (FPS_TARGET_MS, PointsBenchSettings, points_bench_markdown,
                                        run_points_bench)
from detbench.sim.scans import load_scans
from detbench.utils.cli import check_out_dir, require, run_main, torch_device
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    D = PointsBenchSettings()  # the defaults
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/bench_points",
                    help="output folder for bench_points.json and bench_points.md (default: %(default)s)")
    ap.add_argument("--frames", type=int, default=1, help="scans per batch (default %(default)s)")
    ap.add_argument("--points", type=int, default=D.points, help="points per scan (default %(default)s, PointRCNN)")
    ap.add_argument("--samples", type=int, default=D.samples, help="FPS samples per scan (default %(default)s)")
    ap.add_argument("--channels", type=int, default=D.channels,
                    help="feature channels C for propagation and pooling (default %(default)s)")
    ap.add_argument("--rois", type=int, default=D.rois, help="RoIs per scan for RoI pooling (default %(default)s)")
    ap.add_argument("--source", choices=["synthetic", "sim", "auto"], default="synthetic",
                    help="scans: the built-in synthetic 1.8 m scan (default, quick), detbench.sim (slower to "
                         "start), or sim when importable")
    ap.add_argument("--nms-boxes", type=int, default=D.nms_boxes,
                    help="proposals entering NMS (default %(default)s; 0 leaves NMS out)")
    ap.add_argument("--nms-keep", type=int, default=D.nms_keep, help="proposals NMS keeps (default %(default)s)")
    ap.add_argument("--seed", type=int, default=D.seed, help="random seed of the scans and the sampling")
    ap.add_argument("--repeats", type=int, default=D.repeats,
                    help="timed runs per case after one warm-up (default %(default)s)")
    ap.add_argument("--threads", type=int, default=D.threads, help="numba and torch CPU threads (default %(default)s)")
    ap.add_argument("--device", default="cpu", help="torch device for the torch-path rows (default %(default)s)")
    ap.add_argument("--skip-torch", action="store_true", help="leave out the torch-path rows (slow on CPU)")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    for flag in ("frames", "points", "samples", "channels", "repeats", "threads"):
        v = getattr(args, flag)
        require(v >= 1, f"--{flag} {v}: must be an integer >= 1")
    require(args.rois >= 0, f"--rois {args.rois}: must be an integer >= 0")
    require(args.nms_boxes >= 0 and args.nms_keep >= 1, f"--nms-boxes {args.nms_boxes} / --nms-keep {args.nms_keep}: "
                                                        f"need --nms-boxes >= 0 and --nms-keep >= 1")
    require(args.samples <= args.points, f"--samples {args.samples}: more than the {args.points} points per scan "
                                         f"(--points); sample at most as many")
    check_out_dir(args.out)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    torch.set_num_threads(args.threads)
    device = torch_device(args.device)
    scans, source = load_scans(args.frames, args.seed, args.source)
    settings = PointsBenchSettings(points=args.points, samples=args.samples, channels=args.channels, rois=args.rois,
                                   nms_boxes=args.nms_boxes, nms_keep=args.nms_keep, seed=args.seed,
                                   repeats=args.repeats, threads=args.threads,
                                   skip_torch=args.skip_torch)
    results = run_points_bench(scans, source, settings, device)
    out_dir = Path(args.out)
    atomic_write_json(out_dir / "bench_points.json", results)
    atomic_write_text(out_dir / "bench_points.md", points_bench_markdown(results))
    print(f"FPS {args.points} -> {args.samples}: {results['fps_ms_per_frame']:.1f} ms per frame "
          f"(target < {FPS_TARGET_MS:.0f} ms); load average before/after {results['load_average_1_5_15min_before'][0]}"
          f"/{results['load_average_1_5_15min_after'][0]}")
    print(f"wrote {out_dir / 'bench_points.json'} and {out_dir / 'bench_points.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
