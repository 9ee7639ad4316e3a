#!/usr/bin/env python3
"""The speed/accuracy trade of each detector: latency, memory and AP@R40 across the knobs users turn.

For each model, from the preset's point, one knob at a time and a few joint points:
  voxel      voxel / pillar size x0.5 and x2 (trained; the grid is re-fitted to a whole number of cells
             when the preset's range does not divide)
  width      every channel width x0.5 and x2 (trained)
  region     the grid shrunk to x <= 50 m, |y| <= 5 m and to x <= 100 m, |y| <= 10 m plus the config's
             margins (trained), against the full grid evaluated on the same range
  points     input point budget at test time, 16384 and 4096 points by random or farthest-point
             subsampling (preset model); PointRCNN also its sampled points per frame x0.5 / x2 (trained)
  road       the model trained with road points removed before voxelising or sampling, or kept: the
             opposite of its config's road.drop (configs/default.yaml `road:`)
  proposals  two-stage models: proposals refined at test time x0.25 / x0.5 (preset model), training
             RoIs per frame x0.5 / x2 (trained)
  precision  bfloat16 autocast on CPU; float16 and bfloat16 autocast on CUDA (preset model)
  threads    torch and numba threads, powers of two up to the cores (preset model)
  joint      fast (voxel x2 + width x0.5, also run in bfloat16), near field (small region + voxel x0.5),
             bfloat16 + 16384 random points
  curve      the training budget: one run of --curve-scale x the preset's epochs, its checkpoints
             evaluated on the test split (AP@R40 against training CPU-minutes)
Each point: latency per frame (median and 90th percentile after warm-up, split by stage), peak
memory, parameters, AP@R40 and recall at 3D IoU 0.7 per range on the test split, and a Pareto
flag per range (latency against AP@R40, all models on one device).

Examples:
  python tools/tradeoff.py --preset smoke --out runs/tradeoff_smoke
  python tools/tradeoff.py --preset cpu --models second pillarnet --budget 240 --out runs/tradeoff_cpu
  python tools/tradeoff.py --preset cpu --knobs precision threads points --out runs/tradeoff_cpu
  python tools/tradeoff.py --preset cpu --budget 240 --out runs/tradeoff_cpu --dry-run   # the plan only

--budget MINUTES keeps the sweep within that wall time: tasks are planned in priority order
(the preset's points, the inference-only knobs, the trained knobs, the learning curves, the
joint points; cheapest first within a tier) by estimated cost, re-planned after each task with
the costs measured so far; what does not fit is listed as skipped, and a task still running at
the deadline is stopped (a training run keeps its checkpoint). The sweep resumes: a finished
point or training run in OUT is reused, an interrupted run continues; run it again with a
larger budget to add what was skipped.
Writes OUT/tradeoff.json, tradeoff.md, tradeoff.png (latency against AP@R40 per range, one
curve per model), learning_curve.png, and OUT/points/, runs/, curve/, logs/.
Units: milliseconds per frame, MiB = 2^20 bytes, seconds and minutes of wall time; AP and recall
are fractions.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
import models
from detbench.studies.tradeoff_points import KNOBS
from detbench.studies.tradeoff_sweep import TradeoffOptions, plan_lines, prepare_sweep, run_tradeoff
from detbench.train.run_config import preset_names
from detbench.utils.cli import doc_parser, run_main


def build_parser() -> argparse.ArgumentParser:
    ap = doc_parser(__doc__)
    ap.add_argument("--preset", default="smoke", choices=preset_names(),
                    help="the point every knob starts from (models trained at that preset's size and schedule); "
                         "default smoke")
    ap.add_argument("--models", nargs="+", default=None,
                    help=f"detectors (default all: {', '.join(models.REGISTRY)})")
    ap.add_argument("--knobs", nargs="+", default=list(KNOBS), choices=KNOBS, metavar="KNOB",
                    help=f"knobs to sweep (default all: {' '.join(KNOBS)}); the preset's point is always measured")
    ap.add_argument("--out", required=True, help="output folder (resumed when it exists)")
    ap.add_argument("--budget", type=float, default=None, metavar="MINUTES",
                    help="wall-time budget of the sweep in minutes (default: none, every point runs)")
    ap.add_argument("--height", type=float, default=1.8, help="LiDAR mounting height in metres (default 1.8)")
    ap.add_argument("--data", default=None, metavar="ROOT",
                    help="dataset root (docs/data-format.md); default: the preset's simulated dataset")
    ap.add_argument("--device", default="auto",
                    help="cpu, cuda or auto (cuda when present) for training and measuring (default auto)")
    ap.add_argument("--frames", type=int, default=20, help="timed test frames per point (default 20)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed passes first (default 3)")
    ap.add_argument("--eval-frames", type=int, default=0, metavar="N",
                    help="evaluate AP on N evenly spaced test frames (default 0: the whole test split)")
    ap.add_argument("--curve-scale", type=float, default=2.0,
                    help="the learning-curve run trains this many times the preset's epochs (default 2, so the "
                         "curve goes past the preset's budget; 1 reuses the preset's own run)")
    ap.add_argument("--curve-points", type=int, default=8,
                    help="about this many checkpoints of the learning-curve run are evaluated (default 8)")
    ap.add_argument("--dry-run", action="store_true", help="print the plan with estimated costs; run nothing")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    opts = TradeoffOptions(preset=args.preset, models=args.models, knobs=args.knobs, budget=args.budget,
                           height=args.height, data=args.data, device=args.device, frames=args.frames,
                           warmup=args.warmup, eval_frames=args.eval_frames, curve_scale=args.curve_scale,
                           curve_points=args.curve_points)
    sw = prepare_sweep(opts, args.out, registry=models, repo=ROOT, progress=not args.no_progress)
    if args.dry_run:
        print("\n".join(plan_lines(sw)))
        return 0
    names = list(sw.preset_cfgs)
    print(f"tradeoff: {len(sw.points)} points over {', '.join(names)} ({args.preset} preset, {sw.device}); "
          f"data {sw.root}; out {sw.out}", flush=True)
    try:
        result, skipped = run_tradeoff(sw, progress=not args.no_progress)
    except KeyboardInterrupt:
        print(f"interrupted: what finished is in {sw.out / 'tradeoff.json'}; run the same command to continue")
        return 130
    per_model = {n: sum(p["model"] == n for p in result["points"]) for n in names}
    print(f"tradeoff done in {(time.perf_counter() - sw.t0) / 60:.1f} min: points per model "
          + ", ".join(f"{k} {v}" for k, v in per_model.items())
          + (f"; {len(skipped)} task(s) skipped" if skipped else "")
          + (f"; {len(sw.failed)} failed" if sw.failed else ""))
    print(f"wrote {sw.out / 'tradeoff.json'}, {sw.out / 'tradeoff.md'}" + (", tradeoff.png" if result["points"] else "")
          + (", learning_curve.png" if result["curves"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
