"""Faults in a dataset on disk: empty, malformed, NaN and missing files; a stale ground-truth database;
seeds beyond 64 bits. Every problem is named with its file (and line); nothing is changed."""
import json

import numpy as np
import pytest

from tests.faults.faultkit import snapshot
import tools.train


def test_empty_points_file_is_named_by_every_reader(data_copy, tool, tmp_path):
    """A 0-byte points file (an interrupted copy) is named by validate and analyze, and --skip-bad skips it."""
    bad = data_copy / "points" / "1.8" / "0000_001.npy"
    bad.write_bytes(b"")
    before = snapshot(data_copy)
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{bad}: the file is empty (0 bytes)" in err and "1 problem(s)" in err
    code, err = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--no-progress")
    assert code == 2 and f"{bad}: the file is empty (0 bytes)" in err
    code, err = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--no-progress",
                     "--skip-bad")
    assert code == 0
    skipped = json.loads((tmp_path / "a" / "ability.json").read_text())["extras"]["source"]["skipped"]
    assert len(skipped) == 1 and str(bad) in skipped[0]
    assert snapshot(data_copy) == before


def test_validate_lists_every_problem_with_file_and_line(data_copy, capsys):
    """A whole dataset in one pass: every malformed label line, NaN points, an empty and a missing file."""
    from detbench.data.validate import validate_dataset

    label = data_copy / "labels" / "0001_001.txt"
    lines = label.read_text().splitlines()
    lines[0] = lines[0].replace(lines[0].split()[2], "abc", 1)
    lines.append("1 2 3 -4 5 6 0.1 car")
    label.write_text("\n".join(lines) + "\n")
    pts_path = data_copy / "points" / "0.5" / "0002_000.npy"
    pts = np.load(pts_path)
    pts[7, 1] = np.nan
    np.save(pts_path, pts)
    (data_copy / "points" / "1.8" / "0000_002.npy").write_bytes(b"")
    (data_copy / "points" / "1.8" / "0002_003.npy").unlink()
    before = snapshot(data_copy)
    rep = validate_dataset(data_copy)
    text = "\n".join(rep.errors)
    assert not rep.ok and len(rep.errors) == 5, text
    assert f"{label}:1: column 'z' is 'abc'" in text and f"{label}:{len(lines)}: size dx is -4" in text
    assert f"{pts_path}: 1 point(s) have NaN" in text and "0000_002.npy: the file is empty" in text
    assert "0002_003.npy" in text
    assert snapshot(data_copy) == before


def test_malformed_label_stops_analyze_with_file_and_line(data_copy, tool, tmp_path):
    """A label line with too few columns stops analyze naming the file, the line and --skip-bad."""
    label = data_copy / "labels" / "0002_001.txt"
    label.write_text(label.read_text() + "1 2 3 4 5 6\n")
    code, err = tool("analyze", "--data", data_copy, "--out", tmp_path / "a", "--no-figures", "--no-progress")
    n = len(label.read_text().splitlines())
    assert code == 2 and f"{label}:{n}: 6 columns, expected 8" in err and "--skip-bad" in err


def test_missing_points_file_is_named(data_copy, tool, tmp_path):
    """A points file that ImageSets lists but the disk lacks is named, with the list that asks for it."""
    gone = data_copy / "points" / "1.8" / "0001_003.npy"
    gone.unlink()
    code, err = tool("eval", "--data", data_copy, "--height", "1.8", "--split", "all", "--pred", tmp_path,
                     "--out", tmp_path / "e", "--no-progress")
    assert code == 2 and str(gone) in err and "ImageSets" in err


def test_stale_ground_truth_database_is_rebuilt(data_copy):
    """Re-simulating into the same folder, or editing labels in place, does not reuse the old vehicles of
    ROOT/gt_database."""
    from detbench.data.augment import AugmentConfig
    from detbench.sim.dataset import simulate_dataset
    from detbench.train import TrainingSet

    def database():
        ts = TrainingSet.from_dataset(data_copy, 1.8, [0, -20, -2, 80, 20, 4], augment=AugmentConfig.from_dict({}),
                                      progress=False)
        return ts.sampler.db

    first = database()
    assert database().info["frames_sha1"] == first.info["frames_sha1"]  # unchanged data: reused
    simulate_dataset(data_copy, frames=12, heights=[0.5, 1.8], seed=1, frames_per_scene=4, overwrite=True,
                     progress=False)
    second = database()
    assert second.info["frames_sha1"] != first.info["frames_sha1"]
    assert not np.array_equal(second.boxes[:3], first.boxes[:3])
    label = data_copy / "labels" / f"{second.frame_ids[0]}.txt"
    rows = label.read_text().splitlines()
    rows[0] = " ".join([str(float(rows[0].split()[0]) + 0.5), *rows[0].split()[1:]])
    label.write_text("\n".join(rows) + "\n")
    third = database()
    assert third.info["frames_sha1"] != second.info["frames_sha1"]


@pytest.mark.parametrize("seed", [2**63, 2**64, 2**128])
def test_big_seeds_give_their_own_data_and_are_recorded(seed, tmp_path):
    """Seeds 2^63, 2^64 and 2^128 give their own data, not seed 0's, and the dataset records them."""
    from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config
    from detbench.sim.dataset import simulate_dataset

    cfg = load_sim_config("paper")

    def first_frame(s):
        step = next(iter(HighwaySimulator(cfg, seed=s).run(1, [lidar_preset(1.8)], frames_per_scene=1,
                                                           with_points=False)))
        return step[0].boxes

    assert not np.array_equal(first_frame(seed), first_frame(0))
    root = simulate_dataset(tmp_path / "d", frames=2, heights=[1.8], seed=seed, frames_per_scene=1, progress=False)
    assert json.loads((root / "dataset.json").read_text())["source"]["seed"] == seed
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        HighwaySimulator(cfg, seed=-1)


@pytest.mark.parametrize("damage", ["empty", "nan", "label"])
def test_bad_training_frame_stops_training_before_it_starts(damage, data_copy, capsys, tmp_path, monkeypatch):
    """A bad training frame (empty points, NaN points, a malformed label) stops training before its first step,
    named, with no checkpoint written, even where nothing else reads it first: without ground-truth sampling
    (whose database reads every training frame) the anchor-size sampling reads only the first training frame,
    as it reads at most 400 of a larger dataset, so the damaged last frame is found by the pre-check alone."""
    from tests.faults.faultkit import train_argv
    from detbench.train.run import collect_train_boxes
    from detbench.utils.cli import run_main

    train_ids = (data_copy / "ImageSets" / "train.txt").read_text().split()
    pts = data_copy / "points" / "1.8" / f"{train_ids[-1]}.npy"
    label = data_copy / "labels" / f"{train_ids[-1]}.txt"
    if damage == "empty":
        pts.write_bytes(b"")
        named = f"{pts}: the file is empty (0 bytes)"
    elif damage == "nan":
        arr = np.load(pts)
        arr[3, 0] = np.nan
        np.save(pts, arr)
        named = f"{pts}: 1 point(s) have NaN"
    else:
        label.write_text(label.read_text() + "1 2 3\n")
        named = f"{label}:{len(label.read_text().splitlines())}: 3 columns, expected 8"
    before = snapshot(data_copy)
    train = tools.train
    monkeypatch.setattr(train, "collect_train_boxes", lambda ts, limit=400: collect_train_boxes(ts, limit=1))
    out = tmp_path / "run"
    capsys.readouterr()
    code = run_main(train.main, train_argv(data_copy, out, "--set", "augment.gt_sampling.enabled=false"))
    err = capsys.readouterr().err
    assert code == 2 and named in err, err[-3000:]
    assert f"remove its id from {data_copy / 'ImageSets' / 'train.txt'}" in err and "Traceback" not in err
    assert not out.exists() and snapshot(data_copy) == before
