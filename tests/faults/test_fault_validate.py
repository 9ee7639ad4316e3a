"""What validation lets through: a scene in both splits under an edited split.rule, a num_frames that is not
the dataset's, a box without volume, and a drop rule that empties both splits."""
import json

from tests.faults.faultkit import snapshot


def _edit_info(data, **changes):
    info = json.loads((data / "dataset.json").read_text())
    for key, value in changes.items():
        target = info
        *path, last = key.split("__")
        for k in path:
            target = target[k]
        target[last] = value
    (data / "dataset.json").write_text(json.dumps(info))


def test_a_scene_in_both_splits_is_found_whatever_split_rule_says(data_copy, tool):
    """A frame of a training scene moved to test.txt, and split.rule edited to time-block: validate names the
    scene in both splits (a time-block split is by design only for a dataset of one scene)."""
    from detbench.data.validate import validate_dataset

    train = (data_copy / "ImageSets" / "train.txt").read_text().split()
    test = (data_copy / "ImageSets" / "test.txt").read_text().split()
    (data_copy / "ImageSets" / "train.txt").write_text("".join(f + "\n" for f in train[1:]))
    (data_copy / "ImageSets" / "test.txt").write_text("".join(f + "\n" for f in [train[0], *test]))
    _edit_info(data_copy, split__rule="time-block")
    rep = validate_dataset(data_copy)
    scene = train[0].split("_")[0]
    assert any(f"scene(s) ['{scene}'] have frames in both train.txt and test.txt" in e for e in rep.errors), rep.errors


def test_a_wrong_num_frames_is_an_error(data_copy, tool):
    """num_frames 99999 in dataset.json of a 12-frame dataset: validate names it and the count to set, and a
    training refuses the dataset in one line instead of reporting 99999 frames."""
    from detbench.data.validate import validate_dataset

    _edit_info(data_copy, num_frames=99999)
    rep = validate_dataset(data_copy)
    want = "'num_frames' is 99999, but ImageSets list 12 frame(s); set num_frames to 12 in dataset.json"
    assert any(want in e for e in rep.errors), rep.errors
    code, err = tool("train", "--model", "second", "--height", 1.8, "--preset", "smoke", "--data", data_copy,
                     "--out", data_copy.parent / "run", "--no-progress")
    assert code == 2 and want in err and "Traceback" not in err


def test_a_box_without_volume_is_an_error(data_copy):
    """A label with a zero width: validate names the file and line; reading it is refused (it would count as a
    vehicle the LiDAR missed and lower the detection rate without a word)."""
    from detbench.data.validate import validate_dataset

    label = data_copy / "labels" / "0000_000.txt"
    lines = label.read_text().splitlines()
    parts = lines[0].split()
    parts[4] = "0"
    label.write_text("\n".join([" ".join(parts), *lines[1:]]) + "\n")
    rep = validate_dataset(data_copy)
    assert any("0000_000.txt:1: size dy is 0; box sizes must be > 0 metres" in e for e in rep.errors), rep.errors


def test_a_drop_rule_that_empties_both_splits_is_refused(tmp_path, tool):
    """--drop-frames-without small on traffic with no vehicle near: refused in one line, nothing written."""
    out = tmp_path / "sim"
    code, err = tool("simulate", "--out", out, "--frames", 2, "--heights", 1.8, "--drop-frames-without", "small",
                     "--set", "traffic.density_per_km_lane=0", "--set", "traffic.opposite_density_per_km_lane=0",
                     "--no-progress")
    assert code == 2, err[-3000:]
    assert ("error: dropping the frames without a vehicle in the small range (--drop-frames-without small) leaves "
            "both splits empty: none of the 2 frames has one" in err), err
    assert "Traceback" not in err
    assert not out.exists() and snapshot(tmp_path) == {}
