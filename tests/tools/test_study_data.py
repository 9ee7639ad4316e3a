"""tools/study.py on the user's own dataset (docs/your-data.md): without --heights the study runs at every
height the dataset holds, and a --heights it lacks is refused naming the heights it has."""
from __future__ import annotations

import json

import pytest

import models
from detbench.studies.study import StudyOptions, run_study, study_heights
from detbench.utils.cli import UserError
from tests.helpers import ROOT

PRESET_HEIGHTS = [0.5, 1.0, 1.8]  # configs/default.yaml data.heights: the study's default without --data


@pytest.fixture(scope="module")
def two_heights(tmp_path_factory):
    """A dataset of the simulator at the smoke preset's size (48 frames, 8 per scene) at 0.5 and 1.8 m only."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("mine") / "data"
    return simulate_dataset(root, frames=48, heights=[0.5, 1.8], seed=0, frames_per_scene=8, progress=False)


def test_without_heights_the_study_takes_the_datasets_own(two_heights):
    assert study_heights(str(two_heights), None, PRESET_HEIGHTS) == [0.5, 1.8]
    assert study_heights(str(two_heights), [1.8], PRESET_HEIGHTS) == [1.8]
    assert study_heights(None, None, PRESET_HEIGHTS) == PRESET_HEIGHTS  # the simulated default: the preset's


def test_a_height_the_dataset_lacks_is_refused_before_anything_is_created(two_heights, tmp_path):
    out = tmp_path / "study"
    with pytest.raises(UserError) as e:
        run_study(StudyOptions(preset="smoke", data=str(two_heights), heights=[1.0, 1.8], out=str(out)),
                  registry=models, repo=ROOT)
    msg = str(e.value)
    assert msg.startswith("--heights 1: the dataset ") and "holds 0.5 m, 1.8 m" in msg, msg
    assert "leave --heights out" in msg and "simulate" not in msg and not out.exists()


@pytest.mark.slow  # a smoke study of one model at two heights: about half a minute on 2 cores
def test_the_your_data_command_runs_on_a_two_height_dataset(two_heights, tmp_path):
    """docs/your-data.md's one command (`tools/study.py --preset P --data DATA --out OUT`) on a dataset with two
    of the preset's three heights: it studies those two."""
    out = tmp_path / "study"
    run_study(StudyOptions(preset="smoke", data=str(two_heights), out=str(out), no_progress=True,
                           overrides=["train.epochs=1", "train.tensorboard=false", "study.models=[second]"]),
              registry=models, repo=ROOT)
    study = json.loads((out / "study.json").read_text())
    assert study["heights"] == [0.5, 1.8] and study["models"] == ["second"]
    assert sorted(study["data_fingerprints"]) == ["0.5", "1.8"]
    assert "Heights: 0.5 m, 1.8 m." in (out / "study.md").read_text()
