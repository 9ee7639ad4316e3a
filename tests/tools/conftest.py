"""Fixtures the command tests share: one small simulated dataset and one smoke training run per session
(tests that change the run work on a copy)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory) -> Path:
    """9 frames (3 scenes of 3) at 0.5 and 1.8 m; seed 7 puts LiDAR-detected vehicles in the test scene."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("smoke") / "sim"
    return simulate_dataset(root, frames=9, heights=[0.5, 1.8], seed=7, frames_per_scene=3, progress=False)


@pytest.fixture(scope="session")
def smoke_run(smoke_data, tmp_path_factory) -> Path:
    """A SECOND run trained one epoch of the smoke preset at 1.8 m by tools/train.py (in this process): the run
    folder, with checkpoints/epoch_001.pt. Read-only."""
    import tools.train
    from detbench.utils.cli import run_main

    out = tmp_path_factory.mktemp("smoke") / "second_h1.8"
    assert run_main(tools.train.main, ["--model", "second", "--height", "1.8", "--preset", "smoke", "--data",
                                       str(smoke_data), "--out", str(out), "--epochs", "1", "--no-progress",
                                       "--set", "train.tensorboard=false", "--set", "train.seed=3"]) == 0
    assert json.loads((out / "train_summary.json").read_text())["epochs_completed"] == 1
    return out
