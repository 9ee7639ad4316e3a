#!/usr/bin/env python3
"""Inference at reduced precision against float32 on one checkpoint: accuracy, box differences, NaN/inf.

Runs the checkpoint's detector over the frames of a split once in float32 and once per
reduced precision (autocast: bfloat16 on the CPU; float16 and bfloat16 on CUDA), and reports
per precision: AP@R40 and recall per range (3D IoU 0.7, level All) and their difference to
float32, the largest difference between the boxes the two runs give for the same vehicle
(corner displacement, centre, size, heading, score), detections found by only one run, the
NaN / inf values in the raw outputs, and seconds per frame. The computation is
`detbench.train.precision.compare_precision` (docs/results.md, "Numerical stability and
inference at reduced precision").

Examples:
  python tools/precision.py --ckpt runs/second_h1.8_cpu/checkpoints/epoch_004.pt   # the last checkpoint of
      # python tools/train.py --model second --height 1.8 --preset cpu (4 epochs; epoch_EEE.pt after EEE epochs)
  python tools/precision.py --ckpt CKPT --frames 0 --precisions float32 bfloat16 --out runs/precision
  python tools/precision.py --ckpt CKPT --device cuda            # float16 and bfloat16 on the GPU

Writes OUT/precision.json and OUT/precision.md (default OUT: the run folder's precision_h<height>_<split>).
Units: metres, radians, seconds per frame; AP@R40 and recall are fractions in [0, 1].
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
from detbench.config import shipped_default
from detbench.data.frame import height_or_rig, height_or_rig_arg
from detbench.train.precision import (PRECISIONS, checkpoint_precision_markdown,
                                      checkpoint_precision_report, precision_frames, precision_summary_lines)
from detbench.utils.cli import UserError, check_out_dir, require, run_main, torch_device
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="tools/precision.py", description=__doc__.split("\n\n")[0],
                                 epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", type=Path, required=True,
                    help="detector checkpoint (tools/train.py OUT/checkpoints/*.pt)")
    ap.add_argument("--data", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    ap.add_argument("--height", type=height_or_rig_arg, default=None,
                    help="LiDAR height of the frames, metres, or a rig's name (default: what the checkpoint was "
                         "trained on)")
    ap.add_argument("--split", default="test", choices=("train", "test", "all"),
                    help="split whose frames are used (default test)")
    ap.add_argument("--frames", type=int, default=40, help="use the first N frames of the split; 0 = all (default 40)")
    ap.add_argument("--precisions", nargs="+", default=None, choices=list(PRECISIONS),
                    help="precisions to compare (float32 is always the reference; default: bfloat16 on cpu, "
                         "float16 and bfloat16 on cuda)")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--batch-size", type=int, default=4, help="frames per forward pass (default 4)")
    ap.add_argument("--score-threshold", type=float, default=shipped_default("eval.score_threshold"),
                    help="detections below are dropped (default %(default)s)")
    ap.add_argument("--match-iou", type=float, default=0.5,
                    help="BEV IoU that makes two runs' detections the same vehicle (default 0.5)")
    ap.add_argument("--out", type=Path, default=None, help="output folder")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import models
    from detbench.data.errors import DatasetError
    from detbench.config import ConfigError, get
    from detbench.train.checkpoint import CheckpointError
    from detbench.train.run_config import check_score_thresholds
    from detbench.train.run_layout import precision_dir_name, run_dir_of_checkpoint

    if args.frames < 0 or args.batch_size < 1:
        raise UserError("--frames must be >= 0 (0 = all) and --batch-size >= 1")
    if not 0.0 < args.match_iou <= 1.0:
        raise UserError(f"--match-iou must lie in (0, 1], got {args.match_iou}")
    require(math.isfinite(args.score_threshold) and 0 <= args.score_threshold <= 1,
            f"--score-threshold {args.score_threshold:g}: must be a score in [0, 1]; detections below it are dropped")
    require(args.height is None or isinstance(args.height, str)
            or (math.isfinite(args.height) and args.height > 0),
            f"--height {args.height}: must be a positive number of metres")
    if args.out is not None:
        check_out_dir(args.out)
    device = torch_device(args.device)
    try:
        model, ck = models.load_from_checkpoint(args.ckpt, device)
        check_score_thresholds(args.score_threshold, get(ck["config"], "model.post.score_threshold"),
                               eval_key="--score-threshold", where=f"--ckpt {args.ckpt}: ",
                               lower_model="train it with --set model.post.score_threshold={value:g}")
    except (CheckpointError, ConfigError) as e:
        raise UserError(str(e)) from None
    height = height_or_rig(args.height if args.height is not None else ck["data"].get("height", float("nan")))
    root = args.data or Path(ck["data"]["source"])
    try:
        frames = precision_frames(root, height, args.split, args.frames)
    except ValueError as e:
        raise UserError(str(e)) from None
    try:
        report = checkpoint_precision_report(model, ck, args.ckpt, frames, root=root, height=height, split=args.split,
                                             precisions=args.precisions, device=device, batch_size=args.batch_size,
                                             score_threshold=args.score_threshold, match_iou=args.match_iou,
                                             progress=not args.no_progress)
    except DatasetError as e:
        raise UserError(str(e)) from None
    out = args.out or run_dir_of_checkpoint(args.ckpt) / precision_dir_name(height, args.split)
    atomic_write_json(out / "precision.json", report)
    atomic_write_text(out / "precision.md", checkpoint_precision_markdown(report))
    for line in precision_summary_lines(report):
        print(line)
    print(f"wrote {out / 'precision.json'}, {out / 'precision.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
