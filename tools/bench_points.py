"""Benchmark detbench.ops.points (PointNet++ / PointRCNN point operations) on 1.8 m LiDAR scans.

Each scan is sampled to --points points (16384, PointRCNN's input), in scan order. Timed, in
milliseconds (median and best of --repeats runs after one warm-up call, so numba compilation
or cache loading is excluded), per call on the whole batch of --frames scans:
  - farthest point sampling --points -> --samples (4096), numba kernel (CPU) and torch path;
  - PointRCNN's four MSG set-abstraction levels (4096, 1024, 256, 64 centres; radii 0.1/0.5,
    0.5/1.0, 1.0/2.0, 2.0/4.0 m; 16/32 samples): FPS + ball query + grouping of xyz;
  - the four feature-propagation levels back to --points (three_nn_interpolate, C channels);
  - RoI point pooling of --rois car-sized RoIs per scan (512 points, 1.0 m extra, C features).
The load average of the machine is recorded before and after (the machine may be shared);
OMP_WAIT_POLICY defaults to PASSIVE (detbench/runtime.py; set it in the environment to measure otherwise).
Writes bench_points.json and bench_points.md to --out.

Usage: python tools/bench_points.py [--out DIR] [--frames N] [--points N] [--samples N] ...  (see --help)
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401
import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from detbench.ops.points import (ball_query, farthest_point_sample, group_neighbours,  # noqa: E402
                                 roi_point_pool, three_nn_interpolate)
from detbench.sim.scans import load_scans  # noqa: E402
from detbench.utils.bench import timed  # noqa: E402
from detbench.utils.cli import check_out_dir, require, run_main, torch_device  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text  # noqa: E402

# PointRCNN (OpenPCDet pointrcnn.yaml, PointNet2MSG backbone)
SA_NPOINTS = [4096, 1024, 256, 64]
SA_RADII = [[0.1, 0.5], [0.5, 1.0], [1.0, 2.0], [2.0, 4.0]]
SA_NSAMPLE = [[16, 32], [16, 32], [16, 32], [16, 32]]
FPS_TARGET_MS = 200.0  # the bound for 16384 -> 4096 points on 2 CPU cores


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/bench_points",
                    help="output folder for bench_points.json and bench_points.md (default: %(default)s)")
    ap.add_argument("--frames", type=int, default=1, help="scans per batch (default %(default)s)")
    ap.add_argument("--points", type=int, default=16384, help="points per scan (default %(default)s, PointRCNN)")
    ap.add_argument("--samples", type=int, default=4096, help="FPS samples per scan (default %(default)s)")
    ap.add_argument("--channels", type=int, default=128, help="feature channels C for propagation and pooling")
    ap.add_argument("--rois", type=int, default=100, help="RoIs per scan for RoI pooling (default %(default)s)")
    ap.add_argument("--source", choices=["synthetic", "sim", "auto"], default="synthetic",
                    help="scans: the built-in synthetic 1.8 m scan (default, quick), detbench.sim (slower to "
                         "start), or sim when importable")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the scans and the sampling")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case after one warm-up (default %(default)s)")
    ap.add_argument("--threads", type=int, default=2, help="numba and torch CPU threads (default %(default)s)")
    ap.add_argument("--device", default="cpu", help="torch device for the torch-path rows (default %(default)s)")
    ap.add_argument("--skip-torch", action="store_true", help="leave out the torch-path rows (slow on CPU)")
    return ap


def sample_scan(scan: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points of the scan in scan order (with repeats only when the scan has fewer points)."""
    idx = rng.choice(len(scan), n, replace=len(scan) < n)
    return scan[np.sort(idx)]


def car_rois(rng: np.random.Generator, n: int) -> np.ndarray:
    """n car-sized boxes (x, y, z, dx, dy, dz, heading) on the lanes ahead, metres and radians."""
    return np.c_[rng.uniform(5.0, 80.0, n), rng.choice([-7.0, -3.5, 0.0, 3.5, 7.0], n) + rng.normal(0, 0.3, n),
                 np.full(n, 0.8), rng.uniform(4.0, 5.0, n), rng.uniform(1.7, 2.0, n), rng.uniform(1.4, 1.8, n),
                 rng.normal(0.0, 0.1, n)].astype(np.float32)


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    for flag in ("frames", "points", "samples", "channels", "repeats", "threads"):
        v = getattr(args, flag)
        require(v >= 1, f"--{flag} {v}: must be an integer >= 1")
    require(args.rois >= 0, f"--rois {args.rois}: must be an integer >= 0")
    require(args.samples <= args.points, f"--samples {args.samples}: more than the {args.points} points per scan "
                                         f"(--points); sample at most as many")
    check_out_dir(args.out)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    torch.set_num_threads(args.threads)
    device = torch_device(args.device)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    rng = np.random.default_rng(args.seed)
    scans, source = load_scans(args.frames, args.seed, args.source)
    pts = np.concatenate([sample_scan(s, args.points, rng) for s in scans])
    counts = [args.points] * args.frames
    xyz = torch.from_numpy(np.ascontiguousarray(pts[:, :3]))
    load_before = os.getloadavg()
    results: dict = {
        "source": source, "frames": args.frames, "points_per_frame": args.points, "samples": args.samples,
        "channels": args.channels, "rois_per_frame": args.rois, "threads": args.threads,
        "numba_threads": numba.get_num_threads(), "device": str(device), "torch": torch.__version__,
        "numba": numba.__version__, "cpu": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "repeats": args.repeats, "units": "milliseconds per call on the whole batch (median and best)",
        "load_average_1_5_15min_before": [round(v, 2) for v in load_before], "cases": [],
    }

    def add(name, timing, **extra):
        row = {"case": name, "ms": round(timing["ms"], 3), "ms_best": round(timing["ms_best"], 3), **extra}
        results["cases"].append(row)
        print(f"{name:62s} {timing['ms']:9.2f} ms (best {timing['ms_best']:.2f})", flush=True)
        return row

    # Farthest point sampling: the figure.
    fps = lambda: farthest_point_sample(xyz, args.samples, counts)  # noqa: E731
    row = add(f"farthest_point_sample {args.points} -> {args.samples} (numba, CPU)", timed(fps, args.repeats, lambda: None))
    results["fps_ms"] = row["ms"]
    results["fps_ms_per_frame"] = round(row["ms"] / args.frames, 3)
    results["fps_target_ms_per_frame"] = FPS_TARGET_MS
    if not args.skip_torch:
        xd = xyz.to(device)
        same = bool(torch.equal(farthest_point_sample(xd, args.samples, counts, backend="torch").cpu(), fps()))
        add(f"farthest_point_sample {args.points} -> {args.samples} (torch path, {device})",
            timed(lambda: farthest_point_sample(xd, args.samples, counts, backend="torch"), args.repeats, sync),
            equal_to_numba=same)

    # PointRCNN set abstraction: FPS + ball query + grouping per level.
    level_xyz, level_counts = [xyz], [counts]
    cur, cur_counts = xyz, counts
    for level, (npoint, radii, nsamples) in enumerate(zip(SA_NPOINTS, SA_RADII, SA_NSAMPLE)):
        npoint = args.samples if level == 0 else npoint
        idx = farthest_point_sample(cur, npoint, cur_counts)
        centres = cur[idx]
        add(f"  SA level: FPS {cur_counts[0]} -> {npoint}", timed(lambda: farthest_point_sample(cur, npoint, cur_counts),
                                                               args.repeats, lambda: None))
        for r, ns in zip(radii, nsamples):
            cc = [npoint] * args.frames

            def step(r=r, ns=ns, cc=cc):
                bq = ball_query(cur, centres, r, ns, cur_counts, cc)
                return group_neighbours(cur, centres, bq.index), bq

            _, bq = step()
            add(f"  SA level: ball query r={r} m, {ns} samples + grouping ({npoint} centres)",
                timed(step, args.repeats, lambda: None), empty_balls=int(bq.empty.sum()),
                mean_points=round(float(bq.count.float().mean()), 2))
        cur, cur_counts = centres, [npoint] * args.frames
        level_xyz.append(cur)
        level_counts.append(cur_counts)

    # Feature propagation back up the levels.
    for lvl in range(len(level_xyz) - 1, 0, -1):
        src, tgt = level_xyz[lvl], level_xyz[lvl - 1]
        feats = torch.randn(src.shape[0], args.channels)
        add(f"  FP level: three_nn_interpolate {level_counts[lvl][0]} -> {level_counts[lvl - 1][0]}, C={args.channels}",
            timed(lambda: three_nn_interpolate(tgt, src, feats, level_counts[lvl - 1], level_counts[lvl]),
                  args.repeats, lambda: None))

    # RoI point pooling.
    if args.rois:
        rois = torch.from_numpy(np.concatenate([car_rois(rng, args.rois) for _ in range(args.frames)]))
        feats = torch.randn(xyz.shape[0], args.channels)
        pool = lambda: roi_point_pool(xyz, rois, 512, 1.0, feats, counts, [args.rois] * args.frames)  # noqa: E731
        out = pool()
        add(f"roi_point_pool {args.rois} RoIs x 512 points, C={args.channels} (numba, CPU)",
            timed(pool, args.repeats, lambda: None), empty_rois=int(out.empty.sum()),
            mean_points_inside=round(float(out.count.float().mean()), 1))

    results["load_average_1_5_15min_after"] = [round(v, 2) for v in os.getloadavg()]
    out_dir = Path(args.out)
    atomic_write_json(out_dir / "bench_points.json", results)
    atomic_write_text(out_dir / "bench_points.md", markdown(results))
    print(f"FPS {args.points} -> {args.samples}: {results['fps_ms_per_frame']:.1f} ms per frame "
          f"(target < {FPS_TARGET_MS:.0f} ms); load average before/after {results['load_average_1_5_15min_before'][0]}"
          f"/{results['load_average_1_5_15min_after'][0]}")
    print(f"wrote {out_dir / 'bench_points.json'} and {out_dir / 'bench_points.md'}")
    return 0


def markdown(r: dict) -> str:
    """Human-readable report of the results dict."""
    lines = [
        "# Point operations benchmark (tools/bench_points.py)", "",
        f"- scans: {r['source']}",
        f"- batch: {r['frames']} scan(s) x {r['points_per_frame']} points; FPS samples {r['samples']}; "
        f"C = {r['channels']}; RoIs per scan {r['rois_per_frame']}",
        f"- numba threads {r['numba_threads']}, torch threads {r['threads']}, device {r['device']}, torch {r['torch']}, "
        f"numba {r['numba']}, {r['cpus']} CPUs, OMP_WAIT_POLICY {r.get('omp_wait_policy')}",
        f"- times in milliseconds per call on the whole batch: median and best of {r['repeats']} runs after a warm-up",
        f"- load average (1 min) before / after: {r['load_average_1_5_15min_before'][0]} / "
        f"{r['load_average_1_5_15min_after'][0]} (a shared machine slows every row)",
        f"- **FPS {r['points_per_frame']} -> {r['samples']}: {r['fps_ms_per_frame']:.1f} ms per frame** "
        f"(target < {r['fps_target_ms_per_frame']:.0f} ms)",
        "", "| case | median ms | best ms | details |", "|---|---:|---:|---|",
    ]
    for row in r["cases"]:
        details = ", ".join(f"{k}={v}" for k, v in row.items() if k not in ("case", "ms", "ms_best"))
        lines.append(f"| {row['case'].strip()} | {row['ms']:.2f} | {row['ms_best']:.2f} | {details} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(run_main(main))
