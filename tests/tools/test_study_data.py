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


@pytest.fixture(scope="module")
def other_scenes(tmp_path_factory):
    """Held-out test data: other scenes (seed 1) of the same world at 0.5 and 1.8 m, nearly all in the test split."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("held_out") / "data"
    return simulate_dataset(root, frames=24, heights=[0.5, 1.8], seed=1, frames_per_scene=4, test_fraction=0.8,
                            progress=False)


def test_test_data_is_checked_before_anything_is_created(two_heights, tmp_path):
    from detbench.sim.dataset import simulate_dataset

    one = simulate_dataset(tmp_path / "one", frames=4, heights=[0.5], seed=1, frames_per_scene=2, progress=False)
    out = tmp_path / "study"
    for test_data, words in ((tmp_path / "none", "no dataset.json there"), (one, "lacks 1.8 m (it holds 0.5)")):
        with pytest.raises(UserError) as e:
            run_study(StudyOptions(preset="smoke", data=str(two_heights), test_data=str(test_data), out=str(out)),
                      registry=models, repo=ROOT)
        assert str(e.value).startswith(f"--test-data {test_data}: {words}"), str(e.value)
        assert not out.exists()


def test_test_data_that_repeat_the_training_scenes_are_refused(two_heights, tmp_path):
    """A simulation with the training data's seed draws its scenes again: testing on it would test on train scenes."""
    from detbench.sim.dataset import simulate_dataset

    same = simulate_dataset(tmp_path / "same", frames=16, heights=[0.5, 1.8], seed=0, frames_per_scene=8,
                            progress=False)
    out = tmp_path / "study"
    with pytest.raises(UserError) as e:
        run_study(StudyOptions(preset="smoke", data=str(two_heights), test_data=str(same), out=str(out),
                               no_progress=True), registry=models, repo=ROOT)
    msg = str(e.value)
    assert "repeat the training scenes" in msg and "--seed 1" in msg, msg


def test_the_evaluations_read_the_test_data_and_the_trainings_do_not(two_heights, other_scenes, tmp_path):
    """With test data the evaluation command reads its test split and its stage input is that data's content;
    the training's inputs stay those of the training data, so trained runs are tested on it without training
    again."""
    from detbench.studies.stage_inputs import FileHashes
    from detbench.studies.study_jobs import EvalStage, TrainStage
    from detbench.studies.study_plan import build_plan
    from detbench.train.run_config import load_run_config

    def plan(test_root):
        return build_plan(preset="smoke", models=["second"], left_out=[], heights=[0.5, 1.8], seeds=None,
                          base_cfg=load_run_config("second", "smoke"), out=tmp_path / "study",
                          data_root=two_heights, data_info={}, hashes=FileHashes(tmp_path / "hashes.json"),
                          simulated=False, test_root=test_root)

    own, held_out = plan(None), plan(other_scenes)
    assert own.train_inputs == held_out.train_inputs
    run_dir = held_out.run_dir("second", 1.8, held_out.primary)
    run_dir.mkdir(parents=True)
    (run_dir / "model.pth").write_bytes(b"weights")
    (run_dir / "train_summary.json").write_text(json.dumps({"checkpoint": str(run_dir / "model.pth")}))
    hashes = FileHashes(tmp_path / "hashes.json")
    stages = [EvalStage(p, hashes, "second", 1.8, 1.8, p.primary) for p in (own, held_out)]
    cmds = [s.command() for s in stages]
    assert "--data" not in cmds[0]
    assert cmds[1][cmds[1].index("--data") + 1] == str(other_scenes)
    assert cmds[1][cmds[1].index("--split") + 1] == "test"
    assert stages[0].recorded["data_fingerprint"] == own.data_fingerprints[1.8]
    assert stages[1].recorded["data_fingerprint"] == held_out.test_fingerprints[1.8] != own.data_fingerprints[1.8]
    train = TrainStage(held_out, "second", 1.8, held_out.primary)
    assert train.inputs["data_fingerprint"] == own.data_fingerprints[1.8]


@pytest.mark.slow  # a smoke study of one model at two heights: about half a minute on 2 cores
def test_a_study_tests_on_held_out_data(two_heights, other_scenes, tmp_path):
    """--test-data: trained on the train split of --data, every evaluation on the test split of the held-out data,
    and study.md says which data each step read."""
    out = tmp_path / "study"
    run_study(StudyOptions(preset="smoke", data=str(two_heights), test_data=str(other_scenes), out=str(out),
                           no_progress=True, overrides=["train.epochs=1", "train.tensorboard=false",
                                                        "study.models=[second]"]),
              registry=models, repo=ROOT)
    study = json.loads((out / "study.json").read_text())
    assert study["test_data"] == str(other_scenes) and study["test_data_info"]["num_frames"] == 24
    report = json.loads((out / "second_h1.8" / "eval_h1.8_test" / "report.json").read_text())
    assert report["data"] == str(other_scenes)
    assert study["test_frames"] == report["num_frames"] == study["splits"]["test"]["num_frames"]
    md = (out / "study.md").read_text()
    assert f"trained on the train split of `{two_heights}` (48 frames" in md
    assert f"tested on the test split of `{other_scenes}` (24 frames" in md
