"""The command lines of the studies' jobs: the one place in detbench that names a tool of tools/ to run.

A study's stage (the ability study, a training, an evaluation, the combined report) and the trade
sweep's trainings each run a tool of the checkout in its own process, exactly as a user would type
it: the job's log opens with that command, so a failed job is rerun by hand with a copy and paste.
The tools import the detector registry (models/), which detbench never imports, so detbench runs
them by path, from the checkout's root (the executors' working folder). Each builder here returns
the argv (the interpreter first); the layer test (tests/core/test_layers.py) holds that no other
module of detbench names a tool's path.

A training is finished when its run folder holds a train_summary.json not marked "interrupted";
it resumes from its checkpoints when its folder holds a checkpoints/ folder (`train_finished`,
`train_resumes`): the one rule the study and the trade sweep share.
"""
from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from detbench.utils.atomic import read_json

# The tools the studies run, by path from the checkout's root.
ANALYZE_TOOL = "tools/analyze.py"
TRAIN_TOOL = "tools/train.py"
EVAL_TOOL = "tools/eval.py"
TOOLS = (ANALYZE_TOOL, TRAIN_TOOL, EVAL_TOOL)
# The trade sweep's measuring worker (a module of detbench, no tool): `python -m` with one JSON spec.
TRADEOFF_WORKER = "detbench.studies.tradeoff_worker"


def _sets(overrides: Sequence[str]) -> list[str]:
    return [x for o in overrides for x in ("--set", o)]


def _quiet(progress: bool) -> list[str]:
    return [] if progress else ["--no-progress"]


@dataclass(frozen=True)
class TrainSpec:
    """One training run of tools/train.py: the detector `model` at `height` metres on the dataset `data`,
    into the run folder `out`, with the preset's budget and `overrides` (--set KEY=VALUE) on top."""

    model: str
    height: float
    preset: str
    data: str | os.PathLike
    device: str
    out: str | os.PathLike
    overrides: tuple[str, ...] = ()
    progress: bool = False  # progress bars (a job alone on the terminal); else --no-progress


def train_finished(run_dir: str | os.PathLike) -> bool:
    """A training whose run folder holds a train_summary.json not marked "interrupted"."""
    summary = Path(run_dir) / "train_summary.json"
    return summary.is_file() and not read_json(summary).get("interrupted", False)


def train_resumes(run_dir: str | os.PathLike) -> bool:
    """A training that continues from its checkpoints (--resume): its run folder holds checkpoints/."""
    return (Path(run_dir) / "checkpoints").is_dir()


def train_command(spec: TrainSpec) -> list[str] | None:
    """tools/train.py's command for `spec` (--resume when `train_resumes`), or None when `train_finished`.
    The training evaluates nothing itself (--no-eval): its evaluations are jobs of their own."""
    if train_finished(spec.out):
        return None
    return [sys.executable, TRAIN_TOOL, "--model", spec.model, "--height", str(spec.height), "--preset", spec.preset,
            "--data", str(spec.data), "--device", spec.device, "--out", str(spec.out),
            *(["--resume"] if train_resumes(spec.out) else []), *_sets(spec.overrides), "--no-eval",
            *_quiet(spec.progress)]


def eval_command(checkpoint: str | os.PathLike, trained_height: float, test_height: float, out: str | os.PathLike,
                 device: str, *, data: str | os.PathLike | None = None, progress: bool = False) -> list[str]:
    """tools/eval.py's command: the checkpoint trained at `trained_height` on the test split at `test_height`
    (--test-height only when they differ) of the dataset it was trained on, or of `data` when given, report into
    the folder `out`."""
    other = ["--test-height", str(test_height)] if test_height != trained_height else []
    on = ["--data", str(data)] if data is not None else []
    return [sys.executable, EVAL_TOOL, "--ckpt", str(checkpoint), *on, *other, "--split", "test", "--out", str(out),
            "--device", device, *_quiet(progress)]


def combine_command(reports: Sequence[str | os.PathLike], out: str | os.PathLike) -> list[str]:
    """tools/eval.py --combine: the finished report.json files merged into one table with the paper's Fig. 8-10."""
    return [sys.executable, EVAL_TOOL, "--combine", *map(str, reports), "--out", str(out)]


def ability_command(heights: Sequence[float], out: str | os.PathLike, *, data: str | os.PathLike | None = None,
                    simulate: int = 0, seed: int = 0, sim_preset: str = "paper", sim_overrides: Sequence[str] = (),
                    progress: bool = False) -> list[str]:
    """tools/analyze.py's command: the LiDAR detection ability at `heights` on `simulate` frames of the simulator
    (hit counts only), or on every frame of the dataset `data`."""
    if simulate:
        source = ["--simulate", str(simulate), "--seed", str(seed), "--sim-preset", sim_preset,
                  *_sets(sim_overrides)]
    else:
        source = ["--data", str(data), "--split", "all"]
    return [sys.executable, ANALYZE_TOOL, *source, "--heights", *map(str, heights), "--out", str(out),
            *_quiet(progress)]


def worker_command(spec: dict) -> list[str]:
    """The trade sweep's worker on one task: `python -m detbench.studies.tradeoff_worker SPEC_JSON`."""
    return [sys.executable, "-m", TRADEOFF_WORKER, json.dumps(spec)]


__all__ = ["ANALYZE_TOOL", "EVAL_TOOL", "TOOLS", "TRADEOFF_WORKER", "TRAIN_TOOL", "TrainSpec", "ability_command",
           "combine_command", "eval_command", "train_command", "train_finished", "train_resumes", "worker_command"]
