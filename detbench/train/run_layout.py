"""Where runs live on disk: the names of training-run, evaluation and study folders.

A training run of model M at mounting height H is a folder named `M_hH` inside a study
(`runs/study_<preset>/second_h1.8`), or `runs/M_hH_<preset>` when tools/train.py is given no
--out. Its checkpoints are in `<run>/checkpoints/`, and the tools that start from a checkpoint
write next to them: `<run>/eval_hH_<split>[_<stage>]/` (tools/eval.py; H is the height tested
at) and `<run>/precision_hH_<split>/` (tools/precision.py). Heights are written by
`detbench.data.frame.height_key` (1.8, 1.0, 0.25).
"""
from __future__ import annotations

import os
from pathlib import Path

from detbench.data.frame import height_key

RUNS_DIR = Path("runs")  # default parent of runs and studies, relative to the working directory


def model_run_name(model: str, height: float) -> str:
    """The folder of model `model` trained at `height` inside a study: "second_h1.8"."""
    return f"{model}_h{height_key(height)}"


def default_train_dir(model: str, height: float, preset: str) -> Path:
    """tools/train.py's run folder when --out is not given: runs/second_h1.8_cpu."""
    return RUNS_DIR / f"{model_run_name(model, height)}_{preset}"


def default_study_dir(preset: str) -> Path:
    """tools/study.py's output folder when --out is not given: runs/study_cpu."""
    return RUNS_DIR / f"study_{preset}"


def study_run_dir(study: str | os.PathLike, model: str, height: float) -> Path:
    """The training run of `model` at `height` inside a study folder."""
    return Path(study) / model_run_name(model, height)


def eval_dir_name(height: float, split: str = "test", stage: str = "refined") -> str:
    """The folder of an evaluation at test height `height` on `split`: "eval_h1.8_test"; a stage
    other than the final ("refined") one is appended: "eval_h1.8_test_proposals"."""
    return f"eval_h{height_key(height)}_{split}" + ("" if stage == "refined" else f"_{stage}")


def eval_report_path(run_dir: str | os.PathLike, height: float, split: str = "test") -> Path:
    """The report.json of a run's evaluation at `height` on `split`."""
    return Path(run_dir) / eval_dir_name(height, split) / "report.json"


def precision_dir_name(height: float, split: str) -> str:
    """The folder of tools/precision.py's comparison at `height` on `split`: "precision_h1.8_test"."""
    return f"precision_h{height_key(height)}_{split}"


def run_dir_of_checkpoint(ckpt: str | os.PathLike) -> Path:
    """The run folder holding a checkpoint (`<run>/checkpoints/epoch_020.pt` -> `<run>`), absolute."""
    return Path(ckpt).resolve().parent.parent


__all__ = ["RUNS_DIR", "model_run_name", "default_train_dir", "default_study_dir", "study_run_dir", "eval_dir_name",
           "eval_report_path", "precision_dir_name", "run_dir_of_checkpoint"]
