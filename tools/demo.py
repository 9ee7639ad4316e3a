#!/usr/bin/env python3
"""Draw a checkpoint's predictions on one frame: bird's-eye view of the points, the ground truth and the boxes.

Runs the detector of a checkpoint (or of a training run's newest checkpoint) on one frame of a
dataset split, with the evaluation's input preparation and post-processing, and draws the frame as
the training preview does: the points the model sees (grey), the ground truth (green) and the
predictions at or above the score threshold (red, with their scores). The computation is
`detbench.train.demo.run_demo`.

Examples:
  python tools/demo.py --ckpt runs/second_h1.8_cpu                       # the run's newest checkpoint, frame 0
  python tools/demo.py --ckpt runs/second_h1.8_cpu/checkpoints/epoch_011.pt --frame 0003_017
  python tools/demo.py --ckpt runs/second_h1.8_cpu --frame -1 --split train --out runs/demo

Writes OUT/<frame_id>.png (the drawing) and OUT/<frame_id>.json (the frame, the checkpoint, the ground
truth and the predictions drawn, machine-readable); default OUT: the run folder's demo_h<height>_<split>.
Units: boxes x y z dx dy dz heading in metres and radians (ego ground frame), scores in [0, 1].
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
from detbench.data.frame import height_or_rig_arg, key_label
from detbench.utils.cli import UserError, check_out_dir, require, run_main, torch_device


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="tools/demo.py", description=__doc__.split("\n\n")[0],
                                 epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", type=Path, required=True,
                    help="detector checkpoint (tools/train.py OUT/checkpoints/*.pt), or a training run's folder "
                         "(OUT) for its newest checkpoint")
    ap.add_argument("--frame", default="0",
                    help="the frame to draw: a frame id of the split (e.g. 0003_017) or an index into its frames "
                         "(0 = the first, -1 = the last; default 0)")
    ap.add_argument("--split", default="test", choices=("train", "test", "all"),
                    help="split the frame is taken from (default test)")
    ap.add_argument("--data", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    ap.add_argument("--height", type=height_or_rig_arg, default=None,
                    help="LiDAR height of the frame, metres, or a rig's name (default: what the checkpoint was "
                         "trained on)")
    ap.add_argument("--score-threshold", type=float, default=shipped_default("eval.score_threshold"),
                    help="predictions below this score are not drawn (default %(default)s, the evaluator's)")
    ap.add_argument("--stage", default="refined", choices=("refined", "proposals"),
                    help="with a two-stage model (pointrcnn, ct3d): 'proposals' draws the first stage's boxes alone")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--out", type=Path, default=None,
                    help="output folder for <frame_id>.png and <frame_id>.json (default: the run folder's "
                         "demo_h<height>_<split>)")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import models
    from detbench.train.checkpoint import CheckpointError
    from detbench.train.demo import DemoOptions, run_demo
    from detbench.train.run_layout import checkpoint_in

    require(math.isfinite(args.score_threshold) and 0 <= args.score_threshold <= 1,
            f"--score-threshold {args.score_threshold:g}: must be a score in [0, 1]; predictions below it are "
            f"not drawn")
    require(args.height is None or isinstance(args.height, str)
            or (math.isfinite(args.height) and args.height > 0),
            f"--height {args.height}: must be a positive number of metres")
    if args.out is not None:
        check_out_dir(args.out)
    device = torch_device(args.device)
    try:
        ckpt = checkpoint_in(args.ckpt)
        model, ck = models.load_from_checkpoint(ckpt, device)
    except CheckpointError as e:
        raise UserError(str(e)) from None
    d, png, js = run_demo(model, ck, DemoOptions(checkpoint=ckpt, frame=args.frame, split=args.split, data=args.data,
                                                 height=args.height, out=args.out, stage=args.stage,
                                                 score_threshold=args.score_threshold, device=str(device)))
    drawn = int(d.drawn.sum())
    print(f"{d.model} ({ckpt}) on frame {d.frame_id} of the {d.split} split at {key_label(d.height)}: "
          f"{len(d.gt_boxes)} ground-truth boxes, {drawn} predictions with score >= {d.score_threshold:g} drawn "
          f"({len(d.scores) - drawn} below), {len(d.points)} points")
    print(f"wrote {png}, {js}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
