"""tools/benchmark.py times a --study's models on the frames they were tested on."""
from __future__ import annotations

from tools.benchmark import frames_source


def test_the_frames_come_from_data_else_the_checkpoints_dataset_else_the_smoke_set(tmp_path):
    trained_on = tmp_path / "dataset"
    trained_on.mkdir()
    ck = {"data": {"source": str(trained_on)}}
    assert frames_source("elsewhere", ck) == "elsewhere"  # --data wins
    assert frames_source(None, ck) == str(trained_on)
    assert frames_source(None, {"data": {"source": str(tmp_path / "moved")}}) is None  # not on this machine
    assert frames_source(None, None) is None and frames_source(None, {}) is None
