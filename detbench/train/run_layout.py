"""Where runs live on disk: the names of training-run, evaluation and study folders.

A training run of model M at mounting height H is a folder named `M_hH` inside a study
(`runs/study_<preset>/second_h1.8`), or `runs/M_hH_<preset>` when tools/train.py is given no
--out. A study trained with several seeds (`tools/study.py --seeds`) keeps the run of the config's
own train.seed under that name and suffixes the others' with their seed: `second_h1.8_s1`.
Its checkpoints are in `<run>/checkpoints/`, and the tools that start from a checkpoint write
next to them: `<run>/eval_hH_<split>[_<stage>]/` (tools/eval.py; H is the height tested at),
`<run>/precision_hH_<split>/` (tools/precision.py) and `<run>/demo_hH_<split>/` (tools/demo.py).
Heights are written by `detbench.data.frame.height_key` (1.8, 1.0, 0.25).

`RUN_FOLDER` and `STUDY_FOLDER` say what such folders hold, for `detbench.utils.folder_locks.claim_folder`
(a run or a study writes only into a folder that is new, empty or its own, and locks it while it
runs) and `check_replaceable` (`tools/study.py --fresh` deletes only a study).
"""
from __future__ import annotations

import os
from pathlib import Path

from detbench.data.frame import data_key
from detbench.train.checkpoint import CheckpointError, CheckpointManager
from detbench.utils.atomic import read_json
from detbench.utils.folder_ownership import FolderKind

RUNS_DIR = Path("runs")  # default parent of runs and studies, relative to the working directory

# a training run's folder: what tools/train.py writes, and the evaluations, comparisons and the trade-off
# sweep's cost record written next to its checkpoints; one written before owner files existed is known by
# its checkpoints or its summary
RUN_FOLDER = FolderKind(
    name="a training run", marker="train_summary.json",
    entries=("checkpoints", "tensorboard", "history.json", "config.yaml", "train_summary.json", "train_summary.md",
             "tradeoff_train.json"),
    foreign="part of a training run", unfinished="an unfinished training run", key="run",
    patterns=(r"eval_h[0-9.]+_[a-z]+(_[a-z]+)?", r"precision_h[0-9.]+_[a-z]+", r"demo_h[0-9.]+_[a-z]+"),
    evidence=("checkpoints/epoch_*.pt",))

# a study's folder (tools/study.py): its reports, the ability study, the combined report and one training
# run per model and height (`model_run_name`), each of which must itself be a run
STUDY_FOLDER = FolderKind(
    name="a study", marker="study.json", entries=("study.json", "study.md", "ability", "combined", "cross_height",
             "splits", "stage_inputs", "logs"),
    foreign="written by a study", unfinished="an unfinished study", key="study",
    members=((r"[a-z0-9]+(?:[_-][a-z0-9]+)*_h[0-9]+(?:\.[0-9]+)?(?:_s[0-9]+)?", RUN_FOLDER),),
    evidence=("ability/ability.json",))


def model_run_name(model: str, height: float, seed: int | None = None) -> str:
    """The folder of model `model` trained at `height` inside a study: "second_h1.8"; with `seed` (a
    training seed other than the config's own) "second_h1.8_s1"."""
    return f"{model}_h{data_key(height)}" + ("" if seed is None else f"_s{int(seed)}")


def default_train_dir(model: str, height: float, preset: str) -> Path:
    """tools/train.py's run folder when --out is not given: runs/second_h1.8_cpu."""
    return RUNS_DIR / f"{model_run_name(model, height)}_{preset}"


def default_study_dir(preset: str) -> Path:
    """tools/study.py's output folder when --out is not given: runs/study_cpu."""
    return RUNS_DIR / f"study_{preset}"


def study_run_dir(study: str | os.PathLike, model: str, height: float, seed: int | None = None) -> Path:
    """The training run of `model` at `height` inside a study folder (`seed`: see `model_run_name`)."""
    return Path(study) / model_run_name(model, height, seed)


def eval_dir_name(height: float, split: str = "test", stage: str = "refined") -> str:
    """The folder of an evaluation at test height `height` on `split`: "eval_h1.8_test"; a stage
    other than the final ("refined") one is appended: "eval_h1.8_test_proposals"."""
    return f"eval_h{data_key(height)}_{split}" + ("" if stage == "refined" else f"_{stage}")


def eval_report_path(run_dir: str | os.PathLike, height: float, split: str = "test") -> Path:
    """The report.json of a run's evaluation at `height` on `split`."""
    return Path(run_dir) / eval_dir_name(height, split) / "report.json"


def precision_dir_name(height: float, split: str) -> str:
    """The folder of tools/precision.py's comparison at `height` on `split`: "precision_h1.8_test"."""
    return f"precision_h{data_key(height)}_{split}"


def demo_dir_name(height: float, split: str) -> str:
    """The folder of tools/demo.py's drawings at `height` on `split`: "demo_h1.8_test"."""
    return f"demo_h{data_key(height)}_{split}"


def run_dir_of_checkpoint(ckpt: str | os.PathLike) -> Path:
    """The run folder holding a checkpoint (`<run>/checkpoints/epoch_020.pt` -> `<run>`), absolute."""
    return Path(ckpt).resolve().parent.parent


def checkpoint_in(path: str | os.PathLike) -> Path:
    """The checkpoint `path` names: a file names itself; a training run's folder, or its checkpoints/ folder,
    names the newest checkpoint in it (`CheckpointManager.latest`: the highest epoch, then step).
    CheckpointError naming the folder when it holds none."""
    path = Path(path)
    if not path.is_dir():
        return path
    folder = path if path.name == "checkpoints" and not (path / "checkpoints").is_dir() else path / "checkpoints"
    latest = CheckpointManager(folder).latest()
    if latest is None:
        raise CheckpointError(f"{path}: holds no checkpoint ({folder}/epoch_*.pt); pass a training run's folder "
                              f"(tools/train.py --out OUT) after its first epoch, or a checkpoint file")
    return latest


def training_seconds(run_dir: str | os.PathLike) -> float:
    """How long a run trained, in seconds: the sum of its history.json epochs' `seconds` (each epoch's
    training, evaluation excluded), so a run stopped and resumed counts the epochs of every invocation,
    where train_summary.json's `train_seconds` holds the last invocation only. An epoch resumed from a
    mid-epoch checkpoint counts from its resumption (the part before the stop is not recorded), so a
    stopped run reads short by at most one partial epoch per stop. Without a history, that
    `train_seconds`; 0.0 when the run has neither."""
    run_dir = Path(run_dir)
    if (run_dir / "history.json").is_file():
        epochs = read_json(run_dir / "history.json").get("epochs", [])
        if epochs:
            return float(sum(float(e.get("seconds") or 0.0) for e in epochs))
    if (run_dir / "train_summary.json").is_file():
        return float(read_json(run_dir / "train_summary.json").get("train_seconds") or 0.0)
    return 0.0


__all__ = ["RUNS_DIR", "RUN_FOLDER", "STUDY_FOLDER", "model_run_name", "default_train_dir", "default_study_dir",
           "study_run_dir", "eval_dir_name", "eval_report_path", "precision_dir_name", "run_dir_of_checkpoint",
           "checkpoint_in", "demo_dir_name", "training_seconds"]
