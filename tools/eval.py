"""Evaluate 3D detections the way the Height3 paper does (Section V; rules in docs/evaluation.md).

Evaluate saved predictions of one height and split:

    python tools/eval.py --data ROOT --height 1.8 --split test --pred PRED_DIR --out OUT_DIR [--model NAME]

PRED_DIR holds one `<frame_id>.txt` per frame, one box per line, `x y z dx dy dz heading score
[class]` (metres, radians, ego ground frame). A frame without a file has no predictions.
OpenPCDet's outputs are read too: its result.pkl (`--pred .../result.pkl`) and per-frame text
in its layouts (detbench.eval.external); `--pred-frame sensor` moves predictions made in the
LiDAR's own frame to the ground frame with the dataset's sensor height and pitch. A constant
height offset between predictions and vehicles is reported as a likely frame mismatch.
Writes OUT_DIR/report.json, report.md (Table VII layout), report.csv and prints a summary; with
--misses also misses.json and misses.md (where recall goes: loose boxes or vehicles never seen).

Combine several reports (models x heights) into one table and the paper's Fig. 8-10:

    python tools/eval.py --combine A/report.json B/report.json ... --out DIR
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.config import shipped_default
from detbench.data.frame import data_key, height_or_rig_arg, key_label, key_value
from detbench.eval.prediction_files import remove_prediction_folder, write_prediction_folder
from detbench.eval.report import summary_lines
from detbench.utils.atomic import atomic_write_json, atomic_write_text
from detbench.eval.run import (
    CheckpointRun,
    EvalSettings,
    combine_report_files,
    evaluation_report,
    load_split,
    read_saved_predictions,
    report_title,
    write_report,
)
from detbench.utils.cli import UserError, claim_output, output_folder, require, run_main, torch_device
from detbench.utils.report_folders import COMBINED_FOLDER, EVAL_FOLDER

SPLITS = ("train", "test", "all")


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults after each option; the examples laid out as written."""


def build_parser() -> argparse.ArgumentParser:
    """The command-line options (see --help)."""
    p = argparse.ArgumentParser(
        prog="tools/eval.py",
        description="Recall and AP@R40 of 3D vehicle detections by range (small/moderate/large) and "
                    "importance level (All/Top3/Top6), restricted to LiDAR-detected vehicles, as in the "
                    "Height3 paper. Either evaluate one prediction folder (--data, --height, --pred) or "
                    "combine finished reports (--combine).",
        formatter_class=_HelpFormatter,
        epilog="examples:\n"
               "  python tools/eval.py --ckpt runs/second_h1.8_cpu/checkpoints/epoch_004.pt     # its own height\n"
               "  python tools/eval.py --ckpt runs/second_h1.8_cpu            # the run's newest checkpoint\n"
               "  python tools/eval.py --ckpt runs/second_h1.8_cpu/checkpoints/epoch_004.pt --test-height 0.5\n"
               "  python tools/eval.py --data data/sim --height 1.8 --pred PRED_DIR --out runs/eval_second_1.8\n"
               "  python tools/eval.py --combine runs/study_quick/*_h?.?/eval_*_test/report.json --out runs/combined\n"
               "--ckpt writes OUT/report.json, report.md, report.csv and OUT/pred/ (default OUT: the run folder's\n"
               "eval_h<height>_<split>, with _proposals for --stage proposals). --combine refuses cross-height and\n"
               "first-stage-only reports unless --with-variants. Units: metres, radians; recall, AP@R40 and LDR\n"
               "are fractions in [0, 1].",
    )
    src = p.add_argument_group("evaluate one model at one height")
    src.add_argument("--data", type=Path, help="dataset root in the Height3 layout (docs/data-format.md)")
    src.add_argument("--height", type=height_or_rig_arg,
                     help="LiDAR mounting height to evaluate, metres (e.g. 0.5, 1.0, 1.8), or the name of a rig the "
                          "dataset holds (tools/simulate.py --rigs; docs/rigs.md), e.g. headlights")
    src.add_argument("--split", default="test", choices=SPLITS, help="dataset split whose frames are evaluated")
    src.add_argument("--pred", type=Path,
                     help="folder of predictions: one <frame_id>.txt per frame, lines 'x y z dx dy dz heading "
                          "score [class]' in metres and radians (or OpenPCDet's 'x y z dx dy dz heading class "
                          "score', or its KITTI text layout); a missing file means no predictions for that frame. "
                          "Or OpenPCDet's result.pkl (per-frame dicts with frame_id, boxes_lidar, score, name): "
                          "a pickle can run code when loaded, so it is read with a restricted unpickler (plain "
                          "containers and numpy arrays only); open only result files you or your tools wrote")
    src.add_argument("--pred-frame", choices=("ground", "sensor"), default="ground",
                     help="with --pred: frame of the predictions: 'ground' (detbench's ego ground frame) or "
                          "'sensor' (the LiDAR's own frame, e.g. a model trained on an OpenPCDet export with "
                          "--frame sensor): moved to the ground frame with the dataset's sensor height and pitch")
    src.add_argument("--pred-classes", nargs="+", default=None, metavar="NAME",
                     help="with --pred: prediction classes to evaluate (case-insensitive); default every class "
                          "but Pedestrian, Cyclist, Person_sitting, DontCare. Predictions without a class are "
                          "always kept")
    src.add_argument("--ckpt", type=Path,
                     help="detector checkpoint (tools/train.py OUT/checkpoints/*.pt) to run instead of --pred, or "
                          "a training run's folder (OUT) for its newest checkpoint; --data and --height default "
                          "to what it was trained on; its predictions are written to OUT/pred/ in the --pred "
                          "format")
    src.add_argument("--test-height", type=height_or_rig_arg, default=None,
                     help="with --ckpt: evaluate at this height (or rig) instead of the training one (cross-height)")
    src.add_argument("--device", default="cpu", help="with --ckpt: cpu, cuda or cuda:N")
    src.add_argument("--batch-size", type=int, default=4, help="with --ckpt: frames per forward pass")
    src.add_argument("--stage", default="refined", choices=("refined", "proposals"),
                     help="with --ckpt of a two-stage model (pointrcnn, ct3d): 'proposals' evaluates the first "
                          "stage's boxes alone (same final NMS and score threshold), to see what the second stage "
                          "adds")
    src.add_argument("--model", default=None,
                     help="model name stored in the report (needed later by --combine); default: the "
                          "checkpoint's model when known, else none")
    p.add_argument("--out", type=Path, required=False, help="output folder for JSON, Markdown, CSV (and figures)")
    p.add_argument("--iou-threshold", type=float, default=shipped_default("eval.iou_threshold"),
                   help="IoU (fraction) a prediction needs with a vehicle to count as a TP")
    p.add_argument("--iou-kind", default="3d", choices=("3d", "bev"),
                   help="main IoU: rotated 3D boxes or bird's-eye view")
    p.add_argument("--score-threshold", type=float, default=shipped_default("eval.score_threshold"),
                   help="predictions with a score below this are dropped before matching")
    p.add_argument("--bootstrap", type=int, default=1000, metavar="B",
                   help="replicates of the bootstrap over test scenes behind the 95 %% intervals of recall and "
                        "AP@R40 in the report (default 1000; 0 = none)")
    p.add_argument("--no-extras", action="store_true",
                   help="skip the extra variants (BEV IoU and IoU 0.5) in the report")
    p.add_argument("--misses", action="store_true",
                   help="also write where recall goes (misses.json, misses.md): per range, each LiDAR-detected "
                        "vehicle's best 3D IoU with a kept prediction, the near misses' box errors in metres, "
                        "and recall by vehicle length and by distance (detbench.eval.misses)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    comb = p.add_argument_group("combine reports")
    comb.add_argument("--combine", nargs="+", type=Path, metavar="REPORT",
                      help="report.json files (each with model and height) to merge into one table "
                           "(combined.md/.csv/.json) and figures (fig8_by_height.png, "
                           "fig9_recall_by_range.png, fig10_recall_by_level.png)")
    comb.add_argument("--with-variants", action="store_true",
                      help="with --combine: admit cross-height reports (a checkpoint tested at another height than "
                           "it was trained at) and first-stage-only reports (--stage proposals), each as a "
                           "separately labelled column, e.g. 'second [trained at 0.5 m]'; without it they are "
                           "refused, since the paper's Table VII holds each model at its own height, whole")
    comb.add_argument("--no-figures", action="store_true", help="with --combine: write no PNG figures")
    comb.add_argument("--range", dest="range_name", default="large", choices=("small", "moderate", "large"),
                      help="with --combine: range shown in the by-height and by-level figures")
    return p


# --------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------

def predictions_from_checkpoint(ckpt: Path, dataset, device="cpu", batch_size: int = 4,
                                progress: bool = True, stage: str = "refined"):
    """Run a detector checkpoint over `dataset` -> ({frame_id: (boxes, scores)}, model name, what the checkpoint
    records of its training data)."""
    import models
    from detbench.train.checkpoint import CheckpointError
    from detbench.train.inference import checkpoint_predictions

    try:
        model, ck = models.load_from_checkpoint(ckpt, device)
    except CheckpointError as e:
        raise UserError(str(e)) from None
    preds = checkpoint_predictions(model, ck, dataset, device=device, batch_size=batch_size, progress=progress,
                                   stage=stage, source=ckpt)
    return preds, ck["model_name"], ck["data"]


def checkpoint_defaults(args: argparse.Namespace) -> None:
    """Take a run folder's newest checkpoint for --ckpt RUN_DIR; fill --data and --height from the checkpoint when
    not given; resolve --test-height and --out. UserError when --score-threshold is below the checkpoint's
    model.post.score_threshold."""
    from detbench.config import ConfigError, get
    from detbench.train.checkpoint import CheckpointError, load_checkpoint
    from detbench.train.run_config import check_score_thresholds
    from detbench.train.run_layout import checkpoint_in

    try:
        given, args.ckpt = args.ckpt, checkpoint_in(args.ckpt)
        ck = load_checkpoint(args.ckpt)
        check_score_thresholds(args.score_threshold, get(ck["config"], "model.post.score_threshold"),
                               eval_key="--score-threshold", where=f"--ckpt {args.ckpt}: ",
                               lower_model="train it with --set model.post.score_threshold={value:g}")
    except (CheckpointError, ConfigError) as e:
        raise UserError(str(e)) from None
    if args.ckpt != given:
        print(f"checkpoint: {args.ckpt} (the newest in {given})")
    trained_h = _recorded_key(ck["data"].get("height"))
    if args.model is not None and args.model != ck["model_name"]:
        raise UserError(f"--model {args.model}: --ckpt {args.ckpt} is a {ck['model_name']} checkpoint; leave --model "
                        f"out (the report takes the checkpoint's model) or give --model {ck['model_name']}")
    if trained_h is None and args.height is None:
        raise UserError(f"--ckpt {args.ckpt}: records no training height (data.height); give --height H in metres")
    if args.height is None:
        args.height = trained_h
    elif trained_h is not None and data_key(args.height) != data_key(trained_h):
        trained, given = _arg(trained_h), _arg(args.height)
        raise UserError(f"--ckpt {args.ckpt} was trained at {key_label(trained_h)}, not --height {given}; to test "
                        f"it at another height keep --height {trained} (or leave it out) and add "
                        f"--test-height {given}")
    if args.data is None:
        args.data = Path(ck["data"]["source"])
    args.trained_height = float("nan") if trained_h is None else trained_h
    seed = (ck.get("config") or {}).get("train", {}).get("seed")
    args.train_seed = int(seed) if isinstance(seed, (int, float)) and not isinstance(seed, bool) else None
    preset = (ck.get("config") or {}).get("preset")
    args.train_preset = str(preset) if isinstance(preset, str) and preset else None
    if args.test_height is not None:
        args.height = args.test_height
    if args.out is None:
        from detbench.train.run_layout import eval_dir_name, run_dir_of_checkpoint

        args.out = run_dir_of_checkpoint(args.ckpt) / eval_dir_name(args.height, args.split, args.stage)


def _recorded_key(value) -> float | str | None:
    """A checkpoint's recorded data.height: a height in metres, a rig's name, or None when it records none."""
    if isinstance(value, str):
        try:
            return key_value(value)
        except ValueError:
            return None
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0:
        return float(value)
    return None


def _arg(value: float | str | None) -> str:
    """A height or rig as the command line writes it: 1.8, headlights."""
    return "?" if value is None else value if isinstance(value, str) else f"{value:g}"


def write_misses(dataset, preds, settings: EvalSettings, out: Path, title: str) -> list[Path]:
    """misses.json and misses.md in `out`: per range, where recall goes (detbench.eval.misses)."""
    from detbench.data.regions import RANGE_NAMES
    from detbench.eval.misses import misses, misses_markdown

    frames = [dataset[i] for i in range(len(dataset))]
    found = {r: misses(frames, preds, r, settings.score_threshold, settings.iou_threshold).to_dict()
             for r in RANGE_NAMES}
    atomic_write_json(out / "misses.json", found)
    atomic_write_text(out / "misses.md", "\n".join(misses_markdown(d, title) for d in found.values()))
    return [out / "misses.json", out / "misses.md"]


def check_arguments(args: argparse.Namespace) -> None:
    """UserError for a value that would zero or void the result: no frames per pass, a threshold no score or
    IoU can reach, a negative bootstrap, a height that is not a positive number of metres."""
    require(args.batch_size >= 1, f"--batch-size {args.batch_size}: must be an integer >= 1 (frames per forward pass)")
    require(math.isfinite(args.score_threshold) and 0 <= args.score_threshold <= 1,
            f"--score-threshold {args.score_threshold:g}: must be a score in [0, 1]; predictions below it are dropped")
    require(math.isfinite(args.iou_threshold) and 0 < args.iou_threshold <= 1,
            f"--iou-threshold {args.iou_threshold:g}: must be an IoU in (0, 1], e.g. 0.7")
    require(args.bootstrap >= 0, f"--bootstrap {args.bootstrap}: must be an integer >= 0 (0 = no intervals)")
    for flag, h in (("--height", args.height), ("--test-height", args.test_height)):
        require(h is None or isinstance(h, str) or (math.isfinite(h) and h > 0),
                f"{flag} {h}: must be a positive number of metres or a rig's name")


def run_evaluate(args: argparse.Namespace) -> int:
    """Evaluate one prediction folder (or checkpoint) at one height and split; exit status."""
    check_arguments(args)
    if args.test_height is not None and args.ckpt is None:
        raise UserError("--test-height goes with --ckpt (test a model trained at one height on another)")
    if args.ckpt is not None:
        checkpoint_defaults(args)
    missing = [name for name, v in (("--data", args.data), ("--height", args.height), ("--out", args.out)) if v is None]
    # (with --ckpt these were filled from the checkpoint above)
    if missing:
        raise UserError(f"missing {', '.join(missing)}; evaluating needs --data ROOT --height H (or a rig's name) "
                        f"(--pred DIR | --ckpt FILE) --out DIR")
    if (args.pred is None) == (args.ckpt is None):
        raise UserError("give exactly one of --pred PRED_DIR (saved predictions) or --ckpt FILE (a checkpoint)")
    if args.pred is None and (args.pred_frame != "ground" or args.pred_classes is not None):
        raise UserError("--pred-frame and --pred-classes describe saved predictions; they go with --pred")
    output_folder(args.out, EVAL_FOLDER)
    device = torch_device(args.device) if args.ckpt is not None else None
    t0 = time.perf_counter()
    dataset, other_ids = load_split(args.data, args.height, args.split)
    model = args.model
    saved = checkpoint = None
    if args.pred is not None:
        saved = read_saved_predictions(args.pred, dataset, other_ids, pred_frame=args.pred_frame,
                                       classes=args.pred_classes)
        preds, skipped = saved.predictions, saved.skipped
    else:
        preds, ckpt_model, trained_on = predictions_from_checkpoint(args.ckpt, dataset, device, args.batch_size,
                                                                    not args.no_progress, args.stage)
        skipped = []
        model = model or ckpt_model
        checkpoint = CheckpointRun(args.trained_height, args.out / "pred", args.stage,
                                   train_seed=args.train_seed, train_preset=args.train_preset)
    with claim_output(args.out, EVAL_FOLDER):
        if checkpoint is not None:
            write_prediction_folder(preds, checkpoint.predictions_dir)
        elif (args.out / "pred").is_dir() and not args.pred.resolve().is_relative_to((args.out / "pred").resolve()):
            remove_prediction_folder(args.out / "pred")  # an earlier evaluation's, not these predictions
    settings = EvalSettings(iou_threshold=args.iou_threshold, score_threshold=args.score_threshold,
                            iou_kind=args.iou_kind, extras=not args.no_extras, bootstrap=args.bootstrap,
                            progress=not args.no_progress)
    full = evaluation_report(dataset, preds, settings, model=model, height=args.height, split=args.split,
                             data=args.data, source=args.pred if args.pred is not None else args.ckpt, saved=saved,
                             pred_frame=args.pred_frame, checkpoint=checkpoint)
    if checkpoint is not None:
        from detbench.train.run import training_data_warnings

        full.setdefault("warnings", []).extend(
            training_data_warnings(trained_on, Path(args.data), args.split, list(dataset.frame_ids)))
    title = report_title(model, args.height, args.split, args.stage if args.ckpt is not None else "refined")
    with claim_output(args.out, EVAL_FOLDER):
        paths = write_report(full, args.out, title)
        if args.misses:
            paths += write_misses(dataset, preds, settings, args.out, title)
    for line in summary_lines(full):
        print(line)
    if skipped:
        print(f"  skipped {len(skipped)} prediction file(s) of frames outside the {args.split!r} split")
    if args.pred is not None:
        print(f"  {len(preds)} of {full['num_frames']} frames had predictions")
        for note in saved.notes:
            print(f"  {note}")
    for w in full.get("warnings", []):
        print(f"tools/eval.py: warning: {w}", file=sys.stderr)
    print(f"  {time.perf_counter() - t0:.1f} s")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


# --------------------------------------------------------------------------------------------
# combine
# --------------------------------------------------------------------------------------------

def run_combine(args: argparse.Namespace) -> int:
    """Merge finished report.json files into combined.md/.csv/.json and figures; exit status."""
    if args.out is None:
        raise UserError("--combine needs --out DIR for the combined table")
    if any(v is not None for v in (args.data, args.height, args.pred, args.ckpt)):
        raise UserError("--combine merges finished reports; do not give --data/--height/--pred/--ckpt with it")
    with claim_output(args.out, COMBINED_FOLDER):
        comb, paths = combine_report_files(args.combine, args.out, figures=not args.no_figures,
                                           range_name=args.range_name, with_variants=args.with_variants)
    print(f"combined {len(args.combine)} reports: models {', '.join(comb['models'])}; heights "
          f"{', '.join(key_label(h) for h in comb['heights'])}")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the tool with `argv` (default: sys.argv); 0, or a `UserError` (see detbench.utils.cli)."""
    args = build_parser().parse_args(argv)
    if args.combine:
        return run_combine(args)
    return run_evaluate(args)


if __name__ == "__main__":
    sys.exit(run_main(main))
