#!/usr/bin/env python3
"""Learning curves: a metric of the evaluations made during training against training CPU-minutes,
averaged over training seeds, for one or more detectors.

Give the run folders of trainings evaluated during training (tools/train.py with
--set train.eval_every=1; their history.json holds each epoch's metrics and its CPU seconds), or of
trainings that kept every epoch's checkpoint (--set train.keep_checkpoints=0, e.g. a study's runs) with
--evaluate N: each epoch checkpoint is then evaluated on N evenly spaced test frames (kept in the run's
curve_eval.json, so a rerun evaluates only new checkpoints). Runs
are grouped by model and preset (or by --label-from folder: the run folder's name without its _s<N>
seed suffix); each group's curve is the mean over its runs at the epochs every run evaluated, with
the [min, max] over runs as a band.

Examples:
  python tools/train.py --model second --height 1.8 --preset cpu --set train.eval_every=1 --set train.seed=1 \\
      --out runs/curves/second_s1
  python tools/curves.py runs/curves/second_s* runs/curves/pillarnet_s* --out runs/curves/report
  python tools/curves.py runs/study_cpu/*_h1.8* --evaluate 150 --out runs/study_cpu/curves

Writes OUT/curves.json, OUT/curves.md and OUT/curves.png (one panel per --metrics entry).
Units: minutes of the training process's CPU time (its DataLoader workers apart; wall minutes for runs
that record no CPU time); metrics are fractions (AP@R40 and recall at 3D IoU 0.7).
"""
from __future__ import annotations

import argparse
import dataclasses
import re
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.studies.learning_curves import (
    DEFAULT_METRICS, collect_curves, curves_markdown, evaluate_run_checkpoints, plot_curves,
)
from detbench.train.checkpoint import CheckpointError
from detbench.utils.atomic import atomic_write_json, atomic_write_text
from detbench.utils.cli import UserError, claim_output, doc_parser, output_folder, run_main
from detbench.utils.report_folders import CURVES_FOLDER


def build_parser() -> argparse.ArgumentParser:
    ap = doc_parser(__doc__)
    ap.add_argument("runs", nargs="+", metavar="RUN", help="training run folders (tools/train.py --out)")
    ap.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS),
                    help=f"metrics of the runs' evaluations, one panel each (default {' '.join(DEFAULT_METRICS)})")
    ap.add_argument("--label-from", choices=("preset", "folder"), default="preset",
                    help="what groups runs beside their model: the preset (default) or the run folder's name "
                         "without a trailing _s<seed>")
    ap.add_argument("--evaluate", type=int, default=0, metavar="N",
                    help="evaluate each run's epoch checkpoints on N evenly spaced test frames first (runs trained "
                         "with --set train.keep_checkpoints=0); 0 (default): use the evaluations made in training")
    ap.add_argument("--title", default="", help="the figure's title")
    ap.add_argument("--out", required=True, help="output folder")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    output_folder(args.out, CURVES_FOLDER)
    if args.evaluate < 0:
        raise UserError(f"--evaluate {args.evaluate}: a number of test frames >= 1, or 0 for none")
    if args.evaluate:
        import models

        def load(path):
            return models.load_from_checkpoint(path, "cpu")

        try:
            for run in args.runs:
                evaluate_run_checkpoints(run, args.evaluate, load, progress=print)
        except (ValueError, CheckpointError) as e:
            raise UserError(str(e)) from None
    label_of = None
    if args.label_from == "folder":
        def label_of(run: Path, preset: str) -> str:
            return re.sub(r"_s\d+$", "", run.name)
    try:
        curves = collect_curves(args.runs, args.metrics, label_of=label_of)
    except ValueError as e:
        raise UserError(str(e)) from None
    with claim_output(args.out, CURVES_FOLDER) as out:
        atomic_write_json(out / "curves.json", {"metrics": list(args.metrics),
                                                "curves": [dataclasses.asdict(c) for c in curves]})
        atomic_write_text(out / "curves.md", curves_markdown(curves, args.metrics))
        plot_curves(curves, out / "curves.png", args.metrics, title=args.title)
    for c in curves:
        last = c.points[-1] if c.points else None
        print(f"{c.model} ({c.label}): {len(c.runs)} run(s), {len(c.points)} evaluated epochs"
              + (f"; last: {last.minutes:.1f} {c.clock} min, " + ", ".join(f"{k} {last.mean[k]:.3f}"
                                                                          for k in args.metrics) if last else ""))
    print(f"wrote {Path(args.out) / 'curves.json'}, curves.md, curves.png")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
