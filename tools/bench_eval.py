"""Time the evaluator on a synthetic load the size of the paper's test set.

    python tools/bench_eval.py --out bench/eval            # 2290 frames, ~8 GT, ~30 predictions
    python tools/bench_eval.py --frames 500 --repeats 3    # quicker
    python tools/bench_eval.py --frames 600 --bootstrap 1000   # the scene bootstrap and report.json's size

The load: per frame a random number of vehicles (mean --gt-per-frame) on the lanes of a
straight highway (ego carriageway lanes -2..2 and the opposite carriageway), about 80 %
LiDAR-detected (fewer far away); predictions are jittered copies of most detected vehicles
(plus some duplicates) and random false positives, --preds-per-frame in total, scores in
[0, 1] (some under the 0.1 threshold). The timed call is `detbench.eval.evaluate(frames)`
(3D IoU 0.7, nine range/level pairs) after one warm-up call, so numba compilation and
cache loading are excluded. Reports the median wall time in seconds and the per-stage split;
with --bootstrap B also the time of `evaluate(frames, bootstrap=B)` (frames in scenes of 10) and the
size of its report.json; writes bench_eval.json and bench_eval.md to --out.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before numba starts)
from detbench.utils.cli import check_out_dir, require, run_main


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
    p.add_argument("--bootstrap", type=int, default=0, metavar="B",
                   help="also time evaluate(..., bootstrap=B) over scenes of 10 frames and measure its report.json "
                        "(bytes, with and without the AP ranking); 0 = not")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for bench_eval.json and bench_eval.md (nothing written when omitted)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Build the load, time `evaluate`, print and (with --out) write JSON and Markdown."""
    args = build_parser().parse_args(argv)
    for flag, v in (("--frames", args.frames), ("--repeats", args.repeats), ("--threads", args.threads)):
        require(v >= 1, f"{flag} {v}: must be an integer >= 1")
    require(args.gt_per_frame >= 0, f"--gt-per-frame {args.gt_per_frame}: must be >= 0 (mean vehicles per frame)")
    require(args.preds_per_frame >= 0, f"--preds-per-frame {args.preds_per_frame}: must be >= 0")
    require(args.bootstrap >= 0, f"--bootstrap {args.bootstrap}: must be an integer >= 0 (0 = no bootstrap)")
    if args.out is not None:
        check_out_dir(args.out)
    os.environ["NUMBA_NUM_THREADS"] = str(args.threads)
    import numba

    from detbench.benchmarks.eval import eval_bench_markdown, run_eval_bench
    from detbench.utils.atomic import atomic_write_json, atomic_write_text

    numba.set_num_threads(args.threads)
    result = run_eval_bench(args.frames, args.gt_per_frame, args.preds_per_frame, repeats=args.repeats,
                            threads=args.threads, seed=args.seed, extras=args.extras, bootstrap=args.bootstrap)
    n_gt, n_pred, stage_median = result["gt_boxes"], result["predictions"], result["seconds_by_stage_median"]
    print(f"evaluate: {args.frames} frames, {n_gt} GT ({n_gt / args.frames:.1f}/frame), {n_pred} predictions "
          f"({n_pred / args.frames:.1f}/frame), {args.threads} threads")
    print(f"  median {result['seconds_median']:.3f} s over {args.repeats} runs "
          f"(warm-up call {result['seconds_warmup_call']:.2f} s); "
          + ", ".join(f"{k} {v:.3f} s" for k, v in stage_median.items()))
    if args.extras:
        print(f"  with extras (BEV 0.7, 3D 0.5, BEV 0.5): median {result['extras_seconds_median']:.3f} s")
    if args.bootstrap:
        print(f"  with a scene bootstrap ({args.bootstrap} replicates, {result['bootstrap_scenes']} scenes): median "
              f"{result['bootstrap_seconds_median']:.3f} s; report.json {result['report_json_bytes'] / 1024:.0f} KiB "
              f"({result['report_json_bytes_without_ap_ranking'] / 1024:.0f} KiB without the AP ranking of "
              f"{result['ranked_detections']} detections)")
    if args.out is not None:
        atomic_write_json(args.out / "bench_eval.json", result)
        atomic_write_text(args.out / "bench_eval.md", eval_bench_markdown(result))
        print(f"wrote {args.out / 'bench_eval.json'}, {args.out / 'bench_eval.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
