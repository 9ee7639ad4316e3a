"""Fixtures of the fault suite (tests/faults): what a careless or unlucky user does, and what must follow.

One tiny simulated dataset and one finished two-epoch training run per session (tests that
damage them work on copies); `tool` runs a tool's `main` in-process through `run_main` (exit
status and stderr, as on the command line). Helpers: faultkit.py.
"""
from __future__ import annotations

import importlib
import shutil
from pathlib import Path

import pytest

from tests.faults.faultkit import stalling_trainer, train_argv


@pytest.fixture(scope="session")
def fault_data(tmp_path_factory) -> Path:
    """12 frames (3 scenes of 4: 8 train, 4 test) at 0.5 and 1.8 m. Read-only: damage a `data_copy`."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("faults") / "data"
    return simulate_dataset(root, frames=12, heights=[0.5, 1.8], seed=3, frames_per_scene=4, progress=False)


@pytest.fixture
def data_copy(fault_data, tmp_path) -> Path:
    """A copy of the dataset that the test may damage."""
    return Path(shutil.copytree(fault_data, tmp_path / "data"))


@pytest.fixture(scope="session")
def trained_run(fault_data, tmp_path_factory) -> Path:
    """A complete 2-epoch run (checkpoints/epoch_001.pt, epoch_002.pt) trained in its own process, the same
    way as the runs the kill -9 tests interrupt; read-only."""
    work = tmp_path_factory.mktemp("trained")
    proc, _ = stalling_trainer(work, "none", train_argv(fault_data, work / "run"))
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, out[-2000:] + err[-3000:]
    return work / "run"


@pytest.fixture
def tool(capsys):
    """`tool("train", *argv) -> (exit status, output)`: a tool's main in-process, ended as on the command
    line; the output is stdout and stderr together."""
    from detbench.utils.cli import run_main

    def call(name: str, *argv) -> tuple[int, str]:
        capsys.readouterr()
        code = run_main(importlib.import_module(f"tools.{name}").main, [str(a) for a in argv])
        captured = capsys.readouterr()
        return code, captured.out + captured.err

    return call
