"""Faults in what a user asks of tools/train.py: bad config values and files, a test split with a bad
frame, a refused start or resume. Each is refused before any training, naming the key or file,
and a refused command changes no file."""
import shutil
from pathlib import Path

import pytest

from tests.faults.faultkit import snapshot, train_argv


@pytest.mark.parametrize("override, named", [
    ("train.epochs=2.7", "train.epochs must be an integer"),
    ("train.amp=maybe", "train.amp must be true or false"),
    ("train=5", "train is a section of keys"),
    ("model=foo", "model is a section of keys"),
    ("model.voxel_size=abc", "model.voxel_size must be a list"),
    ("eval.iou_threshold=abc", "eval.iou_threshold must be a number"),
    ("eval.iou_threshold=1.5", "eval.iou_threshold must be a number in (0, 1]"),
    ("eval.split=val", "eval.split must be one of"),
    ("train.epoch=3", "unknown config key 'train.epoch'; did you mean 'epochs'?"),
])
def test_bad_config_value_is_refused_naming_the_key(override, named, tool, fault_data, tmp_path):
    """A value of the wrong kind or range (2.7 epochs, 'maybe' for a switch) is refused before training starts,
    naming the key: never read as something else, never a TypeError traceback."""
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--set", override))
    assert code == 2 and named in err, err
    assert not out.exists()


def test_config_file_values_and_encoding_are_checked(tool, fault_data, tmp_path):
    """A --config file is held to the same checks as --set (a switch is true or false) and must be UTF-8 text;
    either problem is refused naming the file or key before the run folder exists."""
    cfg = tmp_path / "my.yaml"
    cfg.write_text("_base_: second.yaml\ntrain: {drop_last: 'no'}\n")
    code, err = tool("train", *train_argv(fault_data, tmp_path / "run", "--config", cfg))
    assert code == 2 and "train: drop_last must be true or false" in err and "'no'" in err
    cfg.write_bytes(b"_base_: second.yaml\n# caf\xe9\n")
    code, err = tool("train", *train_argv(fault_data, tmp_path / "run", "--config", cfg))
    assert code == 2 and f"{cfg}: not UTF-8 text" in err
    assert not (tmp_path / "run").exists()


def test_bad_test_frame_stops_training_before_it_starts(data_copy, tool, tmp_path):
    """A bad frame of the test split stops training before its first step, named, with no checkpoint written."""
    test_id = (data_copy / "ImageSets" / "test.txt").read_text().split()[-1]
    bad = data_copy / "points" / "1.8" / f"{test_id}.npy"
    bad.write_bytes(bad.read_bytes()[:100])
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(data_copy, out))
    assert code == 2 and str(bad) in err
    assert not (out / "checkpoints").exists()


def test_refused_start_and_resume_change_no_file(trained_run, fault_data, tool):
    """A refused start or resume changes no file of the run (config.yaml included)."""
    before = snapshot(trained_run)
    code, err = tool("train", *train_argv(fault_data, trained_run, "--model", "pillarnet"))
    assert code == 2 and f"{trained_run / 'checkpoints'} already holds checkpoints" in err and "--resume" in err
    code, err = tool("train", *train_argv(fault_data, trained_run, "--resume", "--set", "train.lr=0.01"))
    assert code == 2 and "epoch_002.pt: checkpoint was written with another config (train.lr" in err
    assert snapshot(trained_run) == before


def test_resume_may_change_the_eval_section(trained_run, fault_data, tool, tmp_path):
    """The eval section measures, never trains: a resume with another eval.* is accepted (here: nothing
    left to train, so the checkpoints stay as they are)."""
    run = Path(shutil.copytree(trained_run, tmp_path / "run"))
    before = snapshot(run / "checkpoints")
    code, err = tool("train", *train_argv(fault_data, run, "--resume", "--no-eval", "--set", "eval.max_frames=2"))
    assert code == 0 and "already complete" in err
    assert snapshot(run / "checkpoints") == before
