"""Run-folder names (detbench.train.run_layout): the names tools/train.py, eval.py, study.py and benchmark.py share."""
import json
from pathlib import Path

from detbench.train import run_layout as rl


def test_run_folder_names():
    assert rl.model_run_name("second", 1.8) == "second_h1.8"
    assert rl.default_train_dir("second", 1, "cpu") == Path("runs/second_h1.0_cpu")
    assert rl.default_study_dir("quick") == Path("runs/study_quick")
    assert rl.study_run_dir("s", "ct3d", 0.5) == Path("s/ct3d_h0.5")
    assert rl.eval_dir_name(1.8) == "eval_h1.8_test"
    assert rl.eval_dir_name(0.5, "train", "proposals") == "eval_h0.5_train_proposals"
    assert rl.eval_report_path("s/second_h1.8", 0.5) == Path("s/second_h1.8/eval_h0.5_test/report.json")
    assert rl.precision_dir_name(1.8, "test") == "precision_h1.8_test"
    assert rl.run_dir_of_checkpoint("r/checkpoints/epoch_002.pt") == Path("r").resolve()


def test_a_study_names_the_runs_of_other_seeds_after_their_seed_and_owns_them():
    import re

    assert rl.model_run_name("second", 1.8, 1) == "second_h1.8_s1"
    assert rl.study_run_dir("s", "ct3d", 0.5, 2) == Path("s/ct3d_h0.5_s2")
    pattern = rl.STUDY_FOLDER.members[0][0]
    assert re.fullmatch(pattern, "second_h1.8_s1") and re.fullmatch(pattern, "second_h1.8")
    assert not re.fullmatch(pattern, "second_h1.8_x1")
    assert "logs" in rl.STUDY_FOLDER.entries  # the jobs' logs


def test_training_seconds_count_every_invocation_of_a_resumed_run(tmp_path):
    run = tmp_path / "second_h1.8"
    run.mkdir()
    assert rl.training_seconds(run) == 0.0
    # the summary of the last invocation only: 1 epoch of a run resumed after 2
    (run / "train_summary.json").write_text(json.dumps({"train_seconds": 100.0}))
    assert rl.training_seconds(run) == 100.0
    (run / "history.json").write_text(json.dumps({"epochs": [{"epoch": 1, "seconds": 120.5},
                                                             {"epoch": 2, "seconds": 110.0},
                                                             {"epoch": 3, "seconds": 99.5}]}))
    assert rl.training_seconds(run) == 330.0
