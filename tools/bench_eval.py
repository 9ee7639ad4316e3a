"""Time the evaluator on a synthetic load the size of the paper's test set.

    python tools/bench_eval.py --out bench/eval            # 2290 frames, ~8 GT, ~30 predictions
    python tools/bench_eval.py --frames 500 --repeats 3    # quicker

The load: per frame a random number of vehicles (mean --gt-per-frame) on the lanes of a
straight highway (ego carriageway lanes -2..2 and the opposite carriageway), about 80 %
LiDAR-detected (fewer far away); predictions are jittered copies of most detected vehicles
(plus some duplicates) and random false positives, --preds-per-frame in total, scores in
[0, 1] (some under the 0.1 threshold). The timed call is `detbench.eval.evaluate(frames)`
(3D IoU 0.7, nine range/level pairs) after one warm-up call, so numba compilation and
cache loading are excluded. Reports the median wall time in seconds and the per-stage split;
writes bench_eval.json and bench_eval.md to --out.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before numba starts)
from detbench.utils.cli import check_out_dir, require, run_main  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    """The command-line options (see --help)."""
    p = argparse.ArgumentParser(
        prog="tools/bench_eval.py",
        description="Wall time of detbench.eval.evaluate on a synthetic test set (paper size by default).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--frames", type=int, default=2290, help="number of frames (the paper's test set: 2290)")
    p.add_argument("--gt-per-frame", type=float, default=8.0, help="mean ground-truth vehicles per frame")
    p.add_argument("--preds-per-frame", type=int, default=30, help="predictions per frame")
    p.add_argument("--repeats", type=int, default=5, help="timed runs after the warm-up; the median is reported")
    p.add_argument("--threads", type=int, default=2, help="numba threads (the target machine has 2 cores)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the synthetic load")
    p.add_argument("--extras", action="store_true",
                   help="also time evaluate(..., extras=True) (BEV IoU and IoU 0.5 variants)")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for bench_eval.json and bench_eval.md (nothing written when omitted)")
    return p


def synthetic_frames(num_frames: int, gt_per_frame: float, preds_per_frame: int, seed: int):
    """List of EvalFrame: vehicles on lanes, predictions = jittered vehicles + false positives.

    Units: metres and radians. Vehicles: lanes -2..2 of the ego carriageway (3.5 m wide) and
    the opposite carriageway (lane 99), x in [-10, 170] m; 10 % trucks (10 x 2.5 x 3.5 m),
    the rest cars (about 4.6 x 1.9 x 1.6 m).
    """
    import numpy as np

    from detbench.data.frame import LANE_OPPOSITE
    from detbench.eval import EvalFrame

    rng = np.random.default_rng(seed)
    frames = []
    for f in range(num_frames):
        n = int(rng.poisson(gt_per_frame))
        lane_slot = rng.integers(-2, 5, n)  # 3 and 4: opposite carriageway
        y = np.where(lane_slot <= 2, lane_slot * 3.5, -(lane_slot + 1) * 3.5) + rng.normal(0, 0.3, n)
        lane = np.where(lane_slot <= 2, lane_slot, LANE_OPPOSITE).astype(np.int64)
        x = rng.uniform(-10, 170, n)
        truck = rng.random(n) < 0.1
        dims = np.where(truck[:, None], [10.0, 2.5, 3.5], [4.6, 1.9, 1.6]) * rng.uniform(0.9, 1.1, (n, 3))
        heading = np.where(lane == LANE_OPPOSITE, np.pi - 1e-3, 0.0) + rng.normal(0, 0.02, n)
        heading = (heading + np.pi) % (2 * np.pi) - np.pi
        gt = np.column_stack([x, y, dims[:, 2] / 2, dims, heading])
        p_det = np.clip(0.95 - 0.003 * np.abs(x), 0.3, 0.95)
        points = np.where(rng.random(n) < p_det, rng.integers(1, 400, n), 0)

        preds, scores = [], []
        for i in np.flatnonzero(points > 0):
            if rng.random() < 0.85:
                copies = 2 if rng.random() < 0.1 else 1
                for _ in range(copies):
                    b = gt[i].copy()
                    b[:2] += rng.normal(0, 0.15, 2)
                    b[3:6] *= rng.normal(1, 0.03, 3)
                    b[6] += rng.normal(0, 0.03)
                    b[2] = b[5] / 2
                    preds.append(b)
                    scores.append(rng.uniform(0.3, 1.0))
        while len(preds) < preds_per_frame:
            d = np.array([4.6, 1.9, 1.6]) * rng.uniform(0.9, 1.1, 3)
            preds.append(np.array([rng.uniform(-10, 170), rng.uniform(-20, 20), d[2] / 2, *d,
                                   rng.uniform(-np.pi, np.pi)]))
            scores.append(rng.uniform(0.0, 0.5))
        frames.append(EvalFrame(gt, points, lane, np.array(preds[:preds_per_frame]).reshape(-1, 7),
                                np.array(scores[:preds_per_frame]), frame_id=f"{f:06d}"))
    return frames


def main(argv: list[str] | None = None) -> int:
    """Build the load, time `evaluate`, print and (with --out) write JSON and Markdown."""
    args = build_parser().parse_args(argv)
    for flag, v in (("--frames", args.frames), ("--repeats", args.repeats), ("--threads", args.threads)):
        require(v >= 1, f"{flag} {v}: must be an integer >= 1")
    require(args.gt_per_frame >= 0, f"--gt-per-frame {args.gt_per_frame}: must be >= 0 (mean vehicles per frame)")
    require(args.preds_per_frame >= 0, f"--preds-per-frame {args.preds_per_frame}: must be >= 0")
    if args.out is not None:
        check_out_dir(args.out)
    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    import numba

    from detbench.eval import evaluate
    from detbench.utils.io import atomic_write_json, atomic_write_text

    numba.set_num_threads(args.threads)
    t0 = time.perf_counter()
    frames = synthetic_frames(args.frames, args.gt_per_frame, args.preds_per_frame, args.seed)
    gen_s = time.perf_counter() - t0
    n_gt = sum(len(f.gt_boxes) for f in frames)
    n_pred = sum(len(f.pred_boxes) for f in frames)

    def timed(extras: bool):
        t = time.perf_counter()
        evaluate(frames, extras=extras)  # warm-up: numba compilation / cache load
        warm = time.perf_counter() - t
        runs, stages = [], []
        for _ in range(args.repeats):
            st: dict = {}
            t = time.perf_counter()
            report = evaluate(frames, extras=extras, timings=st)
            runs.append(time.perf_counter() - t)
            stages.append(st)
        stage_median = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
        return warm, runs, stage_median, report

    warm, runs, stage_median, report = timed(False)
    result = {
        "what": "wall seconds of detbench.eval.evaluate(frames) (3D IoU 0.7, score 0.1, 9 range/level pairs), "
                "median over repeats after one warm-up call",
        "frames": args.frames,
        "gt_boxes": n_gt,
        "predictions": n_pred,
        "gt_per_frame": n_gt / args.frames,
        "predictions_per_frame": n_pred / args.frames,
        "threads": args.threads,
        "repeats": args.repeats,
        "seed": args.seed,
        "seconds_median": statistics.median(runs),
        "seconds_runs": runs,
        "seconds_warmup_call": warm,
        "seconds_by_stage_median": stage_median,
        "seconds_generate_load": gen_s,
        "large_all": report["results"]["large"]["all"],
        "python": platform.python_version(),
        "numba": numba.__version__,
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
    }
    if args.extras:
        warm_x, runs_x, stage_x, _ = timed(True)
        result["extras_seconds_median"] = statistics.median(runs_x)
        result["extras_seconds_by_stage_median"] = stage_x

    print(f"evaluate: {args.frames} frames, {n_gt} GT ({n_gt / args.frames:.1f}/frame), {n_pred} predictions "
          f"({n_pred / args.frames:.1f}/frame), {args.threads} threads")
    print(f"  median {result['seconds_median']:.3f} s over {args.repeats} runs (warm-up call {warm:.2f} s); "
          + ", ".join(f"{k} {v:.3f} s" for k, v in stage_median.items()))
    if args.extras:
        print(f"  with extras (BEV 0.7, 3D 0.5, BEV 0.5): median {result['extras_seconds_median']:.3f} s")
    if args.out is not None:
        md = [
            "# Evaluator benchmark",
            "",
            f"`detbench.eval.evaluate` on a synthetic load: {args.frames} frames, {n_gt / args.frames:.1f} "
            f"ground-truth vehicles and {n_pred / args.frames:.1f} predictions per frame, 3D IoU 0.7, "
            f"score >= 0.1, 9 range/level pairs; {args.threads} numba threads; median of {args.repeats} runs "
            f"after a warm-up call (numba compilation excluded). Times in seconds (wall clock).",
            "",
            "| Stage | Seconds |",
            "|---|---:|",
            *[f"| {k} | {v:.3f} |" for k, v in stage_median.items()],
            f"| **total** | **{result['seconds_median']:.3f}** |",
        ]
        if args.extras:
            md.append(f"| total with extras (BEV 0.7, 3D 0.5, BEV 0.5) | {result['extras_seconds_median']:.3f} |")
        md += ["", f"Machine: {result['machine']}, {result['cpu_count']} CPUs visible, Python {result['python']}, "
                   f"numba {result['numba']}."]
        atomic_write_json(args.out / "bench_eval.json", result)
        atomic_write_text(args.out / "bench_eval.md", "\n".join(md) + "\n")
        print(f"wrote {args.out / 'bench_eval.json'}, {args.out / 'bench_eval.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
