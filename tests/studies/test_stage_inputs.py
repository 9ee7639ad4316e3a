"""What a study compares before it reuses a stage: a config key a newer detbench added is no change at its default."""
from __future__ import annotations

import copy

from detbench.studies.stage_inputs import changes, write_record


def _inputs(**data) -> dict:
    return {"config": {"data": {"frames": 1000, "seed": 0, **data}, "model": {"voxel_size": [0.1, 0.1, 0.15]}},
            "data_fingerprint": "abc"}


def test_a_key_added_at_its_default_changes_nothing(tmp_path):
    write_record(tmp_path, "train_second_h1.8", _inputs())  # recorded before data.drop_frames_without existed
    assert changes(tmp_path, "train_second_h1.8", _inputs(drop_frames_without=None)) == []
    # the same key set to another value is a change, named with both values
    lines = changes(tmp_path, "train_second_h1.8", _inputs(drop_frames_without="large"))
    assert len(lines) == 1 and "data.drop_frames_without" in lines[0] and "large" in lines[0]


def test_keys_outside_the_shipped_defaults_and_real_changes_are_reported(tmp_path):
    write_record(tmp_path, "s", _inputs())
    now = _inputs()
    now["config"]["model"]["new_width"] = 8  # not a configs/default.yaml key: no default to assume
    assert any("model.new_width" in ln for ln in changes(tmp_path, "s", now))
    moved = copy.deepcopy(_inputs())
    moved["config"]["data"]["seed"] = 1
    assert any("data.seed" in ln for ln in changes(tmp_path, "s", moved))
    other_data = changes(tmp_path, "s", {**_inputs(), "data_fingerprint": "def"})
    assert other_data == ['data_fingerprint: then "abc", now "def"']


def test_a_checkpoint_from_before_a_new_key_compares_equal():
    from detbench.train.checkpoint import config_diff

    saved = _inputs()["config"]
    assert config_diff(saved, _inputs(drop_frames_without=None)["config"]) == []
    assert config_diff(saved, _inputs(drop_frames_without="small")["config"]) == [
        "data.drop_frames_without: '<absent>' (checkpoint) vs 'small' (now)"]
