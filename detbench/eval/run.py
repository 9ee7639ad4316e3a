"""One evaluation as tools/eval.py runs it: the split's frames, the predictions (saved, or produced by the
caller from a checkpoint), the report with where its inputs came from, and its files; and the merge of
finished reports into one table with the paper's Fig. 8-10.

A problem the user can fix (a missing dataset or report, a malformed prediction file) is a `UserError`
naming the file and the fix.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from detbench.data import Height3Dataset, split_ids
from detbench.data.errors import DatasetError
from detbench.data.frame import key_label
from detbench.data.layout import sim_calibration
from detbench.eval.evaluate import evaluate_predictions
from detbench.eval.external import LoadedPredictions, load_predictions, vertical_offset_check
from detbench.eval.report import (combine_reports, combined_csv, combined_markdown, data_labels, label_variants,
                                  plot_by_height, plot_by_level, plot_by_range, report_to_csv, report_to_markdown)
from detbench.utils.cli import UserError, as_user_error
from detbench.utils.atomic import atomic_write_json, atomic_write_text, read_json

__all__ = ["CheckpointRun", "EvalSettings", "combine_report_files", "evaluation_report", "load_split",
           "read_saved_predictions", "report_title", "write_report"]


@dataclass
class EvalSettings:
    """How predictions are matched and what the report holds (the options of tools/eval.py, whose defaults
    are its own)."""

    iou_threshold: float  # IoU (fraction) a prediction needs with a vehicle to count as a TP
    score_threshold: float  # predictions scoring below are dropped before matching
    iou_kind: str  # "3d" (rotated boxes) or "bev"
    extras: bool  # also the BEV IoU and IoU 0.5 variants
    bootstrap: int  # replicates of the bootstrap over scenes behind the 95 % intervals (0: none)
    progress: bool = True


@dataclass
class CheckpointRun:
    """Where a checkpoint's predictions came from, for the report."""

    trained_height: float | str  # metres, or a rig's name
    predictions_dir: Path
    stage: str = "refined"  # or "proposals": a two-stage model's first stage alone
    train_seed: int | None = None  # the training's train.seed (the seed statistics name runs by it)
    train_preset: str | None = None  # the training budget (configs/presets/), for the figures' titles


def load_split(root: Path, height: float | str, split: str) -> tuple[Height3Dataset, list[str]]:
    """(the dataset of `split` at `height` (metres, or a rig's name), frame ids of the other splits)."""
    if not Path(root).is_dir():
        raise UserError(f"{root}: dataset root not found; give --data the folder written by tools/simulate.py "
                        f"or holding the Height3 data")
    try:
        dataset = Height3Dataset(root, height, split)
        other: list[str] = []
        if split != "all":
            wanted = set(dataset.frame_ids)
            other = [f for f in split_ids(root, "all") if f not in wanted]
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UserError(str(e)) from None
    return dataset, other


def read_saved_predictions(path: Path, dataset, other_ids, *, pred_frame: str = "ground",
                           classes=None) -> LoadedPredictions:
    """`load_predictions` with a file problem as a UserError."""
    try:
        return load_predictions(path, dataset, other_ids, pred_frame=pred_frame, classes=classes)
    except (FileNotFoundError, ValueError) as e:
        raise UserError(str(e)) from None


def data_source(source) -> dict:
    """What a report's frames are, from the dataset.json `source`: for the simulator its kind,
    calibration, seed, preset and `--set` overrides (figure titles name the calibration and seed,
    `detbench.eval.report.data_label`); for anything else its kind ("dataset": data on disk)."""
    src = source if isinstance(source, dict) else {}
    if src.get("kind") == "simulator":
        return {"kind": "simulator", "calibration": sim_calibration(src), "seed": src.get("seed"),
                "preset": src.get("preset"), "overrides": list(src.get("overrides") or [])}
    return {"kind": str(src.get("kind") or "dataset")}


def evaluation_report(dataset, preds: dict, settings: EvalSettings, *, model: str | None, height: float,
                      split: str, data, source, saved: LoadedPredictions | None = None, pred_frame: str = "ground",
                      checkpoint: CheckpointRun | None = None) -> dict:
    """The report of `preds` on `dataset`, headed by what was evaluated: `source` is the prediction file or
    folder (`saved`, read in `pred_frame`) or the checkpoint (`checkpoint`)."""
    try:
        report = evaluate_predictions(
            dataset, preds, iou_threshold=settings.iou_threshold, score_threshold=settings.score_threshold,
            iou_kind=settings.iou_kind, extras=settings.extras, progress=settings.progress,
            bootstrap=settings.bootstrap)
    except (ValueError, KeyError) as e:  # a check of ours is one line; numpy's or a kernel's error is a bug
        raise as_user_error(e, always=(DatasetError,)) from None
    full = {"model": model, "height": height if isinstance(height, str) else float(height), "split": split,
            "data": str(data), "data_source": data_source(dataset.info.source),
            "predictions": str(source), **report}
    if checkpoint is not None:
        full["trained_height"] = checkpoint.trained_height
        full["predictions_dir"] = str(checkpoint.predictions_dir)
        full["stage"] = checkpoint.stage
        if checkpoint.train_seed is not None:
            full["train_seed"] = checkpoint.train_seed
        if checkpoint.train_preset:
            full["train_preset"] = checkpoint.train_preset
    if saved is not None:
        full["prediction_files"] = len(preds)
        full["files_of_other_splits_skipped"] = len(saved.skipped)
        full["prediction_input"] = saved.info
        full["frame_check"] = vertical_offset_check(dataset, preds, pred_frame=pred_frame,
                                                    score_threshold=settings.score_threshold)
        if full["frame_check"]["warning"]:
            full["warnings"] = [full["frame_check"]["warning"]]
    empty = empty_input_warning(full)
    if empty:
        full.setdefault("warnings", []).append(empty)
    return full


def empty_input_warning(report: dict) -> str | None:
    """The warning for a report whose figures mean nothing: no labelled vehicle in any range, or vehicles without
    one point inside any (empty or misread point files); None otherwise."""
    cells = [r["all"] for r in report["results"].values()]
    where = f"the {report['num_frames']} frame(s) of the {report['split']!r} split at {key_label(report['height'])}"
    if not any(c["total"] for c in cells):
        return (f"no vehicle in any range in {where}: every label file is empty or holds no vehicle box, so "
                f"recall and AP are undefined; check the labels")
    if not any(c["lidar_detected"] for c in cells):
        return (f"not one point lies in any vehicle box in {where}, so every LDR is 0 and no vehicle is evaluated; "
                f"the point files are probably empty or misread (run tools/validate.py on the dataset)")
    return None


def report_title(model: str | None, height: float, split: str, stage: str = "refined") -> str:
    """The heading of report.md."""
    title = f"Detection results{' of ' + model if model else ''} at {key_label(height)} ({split} split)"
    if stage != "refined":
        title += f", {stage} of the first stage alone"
    return title


def write_report(report: dict, out: Path, title: str) -> list[Path]:
    """Write report.json, report.md and report.csv into `out`; returns the paths."""
    out = Path(out)
    paths = [out / "report.json", out / "report.md", out / "report.csv"]
    atomic_write_json(paths[0], report)
    atomic_write_text(paths[1], report_to_markdown(report, title=title))
    atomic_write_text(paths[2], report_to_csv(report))
    return paths


def combine_report_files(report_paths, out: Path, *, figures: bool = True, range_name: str = "large",
                         with_variants: bool = False) -> tuple[dict, list[Path]]:
    """Merge finished report.json files into out/combined.json, .md, .csv and (with `figures`) the paper's
    Fig. 8-10, the by-height and by-level ones at `range_name`; (the combined dict, the written paths).
    Cross-height and first-stage-only reports are refused unless `with_variants`, which shows each as a model
    of its own ("second [trained at 0.5 m]", `label_variants`)."""
    out = Path(out)
    reports, sources = [], []
    for path in report_paths:
        try:
            reports.append(read_json(path))
        except (FileNotFoundError, ValueError) as e:
            raise UserError(str(e)) from None
        sources.append(str(path))
    if with_variants:
        reports = label_variants(reports)
    try:
        comb = combine_reports(reports, sources)
        md = combined_markdown(reports, sources=sources)
        csv_text = combined_csv(reports, sources=sources)
    except ValueError as e:
        raise UserError(str(e)) from None
    comb["sources"] = sources
    if len(data_labels(reports)) > 1:  # e.g. reports of two calibrations: the table is not one world's
        print(f"warning: the reports come from different data ({comb['data']}); combined.md and the figures "
              f"name them all, but a model's figures at different heights may not be comparable", file=sys.stderr)
    paths = [out / "combined.json", out / "combined.md", out / "combined.csv"]
    atomic_write_json(paths[0], comb)
    atomic_write_text(paths[1], md)
    atomic_write_text(paths[2], csv_text)
    if figures:
        paths.append(plot_by_height(reports, out / "fig8_by_height.png", range_name=range_name))
        paths.append(plot_by_range(reports, out / "fig9_recall_by_range.png"))
        paths.append(plot_by_level(reports, out / "fig10_recall_by_level.png", range_name=range_name))
    return comb, paths
