"""The simulated dataset on disk: the frame stride that spreads a scene's few frames over its whole course, and
the paper's rule that frames without vehicles join neither split."""
import json

import pytest

from detbench.sim.dataset import DATA_DEFAULTS, dataset_digest, simulate_dataset


def test_a_frame_stride_spreads_the_frames_of_a_scene_over_its_course(tmp_path):
    root = simulate_dataset(tmp_path / "ds", frames=6, heights=[1.8], frames_per_scene=3, frame_stride=40,
                            progress=False)
    info = json.loads((root / "dataset.json").read_text())
    assert info["source"]["frame_stride"] == 40 and "scene.frame_rate_hz=0.05" in info["source"]["overrides"]
    stamps = [json.loads((root / "meta" / f"0000_{k:03d}.json").read_text())["timestamp"] for k in range(3)]
    assert stamps == [0.0, 20.0, 40.0]  # 40 frames of the 2 Hz stream apart: 20 s
    assert info["split"]["num_train"] + info["split"]["num_test"] == 6


def test_the_digest_names_a_stride_only_when_it_is_set():
    base = {k: DATA_DEFAULTS[k] for k in DATA_DEFAULTS}
    assert dataset_digest(base) == dataset_digest({**base, "frame_stride": 1})
    assert dataset_digest(base) != dataset_digest({**base, "frame_stride": 40})


def test_the_digest_names_the_drop_rule_only_when_it_is_set(tmp_path):
    base = {k: DATA_DEFAULTS[k] for k in DATA_DEFAULTS}
    assert DATA_DEFAULTS["drop_frames_without"] is None  # cached datasets keep their names
    assert dataset_digest(base) == dataset_digest({**base, "drop_frames_without": None})
    assert dataset_digest(base) != dataset_digest({**base, "drop_frames_without": "large"})
    # the simulator writes the rule through: frames without a vehicle in the small range are in no split
    root = simulate_dataset(tmp_path / "ds", frames=8, heights=[1.0], frames_per_scene=4, progress=False,
                            drop_frames_without="small")
    split = json.loads((root / "dataset.json").read_text())["split"]
    listed = split["num_train"] + split["num_test"]
    assert split["dropped"]["range"] == "small" and listed + split["dropped"]["frames"] == 8


@pytest.mark.parametrize("stride", [0, -1, 2.5])
def test_a_bad_stride_is_refused(tmp_path, stride):
    with pytest.raises(ValueError, match="frame_stride"):
        simulate_dataset(tmp_path / "ds", frames=2, heights=[1.8], frame_stride=stride, progress=False)
