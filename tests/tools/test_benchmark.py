"""tools/benchmark.py --study times the study's models on the frames they were tested on."""
from __future__ import annotations

import json

from tools.benchmark import study_data


def test_a_study_gives_its_own_dataset(tmp_path):
    data = tmp_path / "dataset"
    data.mkdir()
    study = tmp_path / "study"
    study.mkdir()
    (study / "study.json").write_text(json.dumps({"data": str(data), "preset": "quick"}))
    assert study_data(str(study)) == str(data)
    assert study_data(None) is None


def test_an_unfinished_or_moved_study_falls_back_with_a_note(tmp_path, capsys):
    study = tmp_path / "study"
    study.mkdir()
    assert study_data(str(study)) is None  # no study.json yet
    assert "smoke preset's simulated dataset" in capsys.readouterr().out
    (study / "study.json").write_text(json.dumps({"data": str(tmp_path / "gone")}))
    assert study_data(str(study)) is None
    assert "--data ROOT" in capsys.readouterr().out
