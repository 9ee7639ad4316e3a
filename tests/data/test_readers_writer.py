"""Data layer: writer -> reader round trip, split by scene, .bin and sensor-frame points,
and one clear error (file, line, fix) for each kind of bad input."""
import json
import math
import warnings

import numpy as np
import pytest

from detbench.data import (
    DatasetError, DatasetWriter, Frame, Height3Dataset, MissingFileError, Sensor, format_labels, ground_to_sensor,
    parse_labels, read_info, read_points, sensor_to_ground, split_ids, split_scenes,
)
from detbench.data.layout import assign_splits
from detbench.data.validate import validate_dataset

HEIGHTS = (0.5, 1.0, 1.8)
SIM_HEIGHTS = (0.5, 1.8)


def make_frames(scene: int, index: int, rng, heights=HEIGHTS, num_boxes=4, num_points=300):
    """One instant at every height: shared labels, different points."""
    fid = f"{scene:04d}_{index:03d}"
    m = num_boxes
    boxes = np.c_[rng.uniform(0, 120, m), rng.uniform(-12, 12, m), np.full(m, 0.8), rng.uniform(3.8, 5, m),
                  np.full(m, 1.9), np.full(m, 1.6), rng.uniform(-math.pi, math.pi, m)].astype(np.float32)
    classes = np.array(["car", "truck", "suv", "van"][:m] + ["car"] * max(0, m - 4))
    out = []
    for h in heights:
        pts = rng.normal(0, 20, size=(num_points, 4)).astype(np.float32)
        pts[:, 3] = rng.uniform(0, 1, num_points)
        sensor = Sensor(height=h, pitch_deg=2.5 if h == 1.8 else 0.0, name=f"h3-{h}")
        out.append(Frame(fid, f"{scene:04d}", pts, boxes.copy(), classes.copy(), np.arange(m, dtype=np.int64) + 10,
                         np.array([0, 1, -1, 99][:m] + [2] * max(0, m - 4), dtype=np.int64), sensor,
                         {"speed_mps": 27.5, "lane_index": 1}, 0.5 * index))
    return out


def write_dataset(root, scenes=3, per_scene=2, seed=0, **kw):
    rng = np.random.default_rng(seed)
    written = {}
    with DatasetWriter(root, list(HEIGHTS), {"kind": "test", "seed": seed}, **kw) as w:
        for s in range(scenes):
            for i in range(per_scene):
                frames = make_frames(s, i, rng)
                w.add(frames)
                written[frames[0].frame_id] = frames
    return written


# ----------------------------------------------------------------------------- round trip

def test_round_trip_bytes_and_metadata(tmp_path):
    written = write_dataset(tmp_path, scenes=3, per_scene=2)
    for hi, h in enumerate(HEIGHTS):
        ds = Height3Dataset(tmp_path, h, "all")
        assert len(ds) == 6 and ds.heights == list(HEIGHTS)
        assert ds.sensor.height == h and ds.sensor.name == f"h3-{h}"
        for f in ds:
            ref = written[f.frame_id][hi]
            assert f.points.dtype == np.float32 and f.points.tobytes() == ref.points.tobytes()
            assert f.boxes.tobytes() == ref.boxes.tobytes()
            assert f.classes.tolist() == ref.classes.tolist()
            assert f.track_ids.tolist() == ref.track_ids.tolist() and f.lanes.tolist() == ref.lanes.tolist()
            assert f.scene_id == ref.scene_id and f.timestamp == ref.timestamp and f.ego == ref.ego
            assert f.sensor == ref.sensor
    info = read_info(tmp_path)
    assert info.source == {"kind": "test", "seed": 0} and info.num_frames == 6
    assert list(info.heights) == ["0.5", "1.0", "1.8"]
    assert info.heights["1.8"].sensor.pitch_deg == 2.5
    ds = Height3Dataset(tmp_path, "1.0", "train")
    assert ds[-1].frame_id == ds.frame_ids[-1]
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_bin_points_written_and_read(tmp_path):
    written = write_dataset(tmp_path, scenes=2, per_scene=1, points_ext=".bin")
    ds = Height3Dataset(tmp_path, 0.5, "all")
    f = ds[0]
    assert ds.points_file(f.frame_id).suffix == ".bin"
    assert f.points.tobytes() == written[f.frame_id][0].points.tobytes()


def test_kitti_bin_reader_with_extra_columns(tmp_path):
    pts = np.arange(40, dtype=np.float32).reshape(8, 5)
    p = tmp_path / "000001.bin"
    pts.tofile(p)
    got = read_points(p, columns=5)
    assert got.shape == (8, 4) and got.dtype == np.float32 and np.array_equal(got, pts[:, :4])
    kitti = tmp_path / "000002.bin"
    pts[:, :4].tofile(kitti)
    assert np.array_equal(read_points(kitti), pts[:, :4])


def test_truncated_bin(tmp_path):
    p = tmp_path / "x.bin"
    np.arange(10, dtype=np.float32).tofile(p)  # 40 bytes: 2.5 points
    with pytest.raises(DatasetError, match=r"x\.bin: file size 40 bytes is not a multiple of 16"):
        read_points(p)


def test_labels_format_is_bit_exact_and_openpcdet_like():
    rng = np.random.default_rng(3)
    boxes = rng.normal(0, 30, size=(50, 7)).astype(np.float32)
    boxes[:, 3:6] = np.abs(boxes[:, 3:6])
    boxes[:, 6] = rng.uniform(-math.pi, math.pi, 50).astype(np.float32)
    text = format_labels(boxes, ["car"] * 50)
    assert len(text.splitlines()[0].split()) == 8
    b2, c2 = parse_labels(text)
    assert b2.tobytes() == boxes.tobytes() and c2.tolist() == ["car"] * 50
    # float32(-pi) lies just below -pi in float64: it must survive unchanged; 4 rad is wrapped
    edge = np.array([[1, 2, 0.5, 4, 2, 1, -math.pi], [1, 2, 0.5, 4, 2, 1, math.pi], [1, 2, 0.5, 4, 2, 1, 4.0]],
                    np.float32)
    b3, _ = parse_labels(format_labels(edge, ["car"] * 3))
    assert b3[:2].tobytes() == edge[:2].tobytes()
    assert b3[2, 6] == pytest.approx(4.0 - 2 * math.pi, abs=1e-6)


# ----------------------------------------------------------------------------- split

def test_split_by_scene_never_by_frame(tmp_path):
    write_dataset(tmp_path, scenes=6, per_scene=3)
    train, test = Height3Dataset(tmp_path, 1.8, "train"), Height3Dataset(tmp_path, 1.8, "test")
    tr_sc, te_sc = set(train.scene_ids().values()), set(test.scene_ids().values())
    assert not tr_sc & te_sc
    assert te_sc == {"0002", "0005"}  # every third scene
    assert len(train) + len(test) == 18 and len(test) == 6
    assert split_ids(tmp_path, "all") == sorted(train.frame_ids + test.frame_ids)
    assert validate_dataset(tmp_path).ok


def test_frames_without_vehicles_join_neither_split(tmp_path):
    """drop_frames_without: a frame with no vehicle in the range is written but listed in no split (the
    paper's 987 frames); the scenes are split first, so the rule never moves a scene."""
    rng = np.random.default_rng(0)
    empty = set()
    with DatasetWriter(tmp_path, list(HEIGHTS), {"kind": "test"}, drop_frames_without="large") as w:
        for s in range(6):
            for i in range(3):
                frames = make_frames(s, i, rng)
                if i == 1 and s % 2 == 0:  # every vehicle behind the ego: none in any range
                    for f in frames:
                        f.boxes[:, 0] -= 130.0
                    empty.add(frames[0].frame_id)
                w.add(frames)
    train, test = Height3Dataset(tmp_path, 1.0, "train"), Height3Dataset(tmp_path, 1.0, "test")
    assert {sc for sc in test.scene_ids().values()} == {"0002", "0005"}  # the same scenes as without the rule
    assert not empty & set(train.frame_ids + test.frame_ids) and len(train) + len(test) == 18 - 3
    info = json.loads((tmp_path / "dataset.json").read_text())["split"]
    assert info["dropped"]["frames"] == 3 and info["dropped"]["test"] == 1 and info["dropped"]["train"] == 2
    assert info["num_test"] == 5 and info["num_train"] == 10
    rep = validate_dataset(tmp_path)
    assert rep.ok and not rep.warnings and "join neither split" in rep.notes[0]
    with pytest.raises(ValueError, match="unknown range_name"):
        DatasetWriter(tmp_path / "x", list(HEIGHTS), {"kind": "test"}, drop_frames_without="huge")


def test_split_rule_is_deterministic_and_bounded():
    scenes = [f"{i:04d}" for i in range(40)]
    tr, te = split_scenes(scenes[::-1], 1 / 3)
    assert len(te) == 13 and not set(tr) & set(te) and sorted(tr + te) == scenes
    assert (tr, te) == split_scenes(scenes, 1 / 3)
    assert split_scenes(["a", "b"], 0.9) == (["a"], ["b"])  # at least one train scene
    assert split_scenes(["a", "b"], 0.0) == (["a", "b"], [])
    with pytest.raises(ValueError):
        split_scenes(scenes, 1.0)


def test_single_scene_warns_and_uses_time_block():
    ids = [f"0000_{i:03d}" for i in range(9)]
    with pytest.warns(UserWarning, match="single scene"):
        tr, te, rule = assign_splits(ids, {f: "0000" for f in ids}, 1 / 3)
    assert te == ids[6:] and tr == ids[:6] and rule["rule"] == "time-block"


def test_single_scene_dataset_still_loads(tmp_path):
    with pytest.warns(UserWarning, match="single scene"):
        write_dataset(tmp_path, scenes=1, per_scene=3)
    assert len(Height3Dataset(tmp_path, 0.5, "train")) == 2
    assert len(Height3Dataset(tmp_path, 0.5, "test")) == 1
    assert read_info(tmp_path).split["rule"] == "time-block"


# ----------------------------------------------------------------------------- sensor frame

def test_sensor_ground_round_trip_and_pitch_sign():
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 30, size=(1000, 4)).astype(np.float64)
    g = sensor_to_ground(pts, 1.8, 2.5)
    back = ground_to_sensor(g, 1.8, 2.5)
    np.testing.assert_allclose(back, pts, atol=1e-9)
    assert np.array_equal(g[:, 3], pts[:, 3])
    # the sensor's optical axis, pitched down, meets the road ahead at height / tan(pitch)
    d = 1.8 / math.tan(math.radians(2.5))
    ray = np.array([[1.0, 0.0, 0.0]]) * (1.8 / math.sin(math.radians(2.5)))
    np.testing.assert_allclose(sensor_to_ground(ray, 1.8, 2.5)[0], [d, 0.0, 0.0], atol=1e-9)
    # pitch 0 is a pure lift by the height
    np.testing.assert_allclose(sensor_to_ground(pts, 0.5, 0.0)[:, 2], pts[:, 2] + 0.5)


def test_sensor_frame_points_converted_on_load(tmp_path):
    written = write_dataset(tmp_path, scenes=2, per_scene=1)
    info = json.loads((tmp_path / "dataset.json").read_text())
    info["heights"]["1.8"]["points_frame"] = "sensor"
    (tmp_path / "dataset.json").write_text(json.dumps(info))
    fid = "0000_000"
    ref = written[fid][2]
    sensor_pts = ground_to_sensor(ref.points.astype(np.float64), 1.8, 2.5).astype(np.float32)
    np.save(tmp_path / "points" / "1.8" / f"{fid}.npy", sensor_pts)
    got = Height3Dataset(tmp_path, 1.8, "all").load(fid)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-4)
    assert got.points.dtype == np.float32


# ----------------------------------------------------------------------------- missing side file

def test_without_meta_lanes_from_lateral_and_track_ids(tmp_path):
    write_dataset(tmp_path, scenes=3, per_scene=2)
    info = json.loads((tmp_path / "dataset.json").read_text())
    info["has_meta"] = False
    (tmp_path / "dataset.json").write_text(json.dumps(info))
    for p in (tmp_path / "meta").iterdir():
        p.unlink()
    (tmp_path / "labels" / "0000_000.txt").write_text(
        "10 0.2 0.8 4.5 1.9 1.6 0 car\n20 3.6 0.8 4.5 1.9 1.6 0 car\n30 -1.8 0.8 4.5 1.9 1.6 0 car\n"
        "40 -5.4 0.8 4.5 1.9 1.6 0 car\n")
    f = Height3Dataset(tmp_path, 1.0, "all").load("0000_000")
    assert f.lanes.tolist() == [0, 1, -1, -2] and f.track_ids.tolist() == [-1] * 4 and f.scene_id == "0000"
    f4 = Height3Dataset(tmp_path, 1.0, "all", lane_width=4.0).load("0000_000")
    assert f4.lanes.tolist() == [0, 1, 0, -1]


# ----------------------------------------------------------------------------- bad input

def _fresh(tmp_path):
    write_dataset(tmp_path, scenes=3, per_scene=2)
    return Height3Dataset(tmp_path, 0.5, "all")


@pytest.mark.parametrize("line, pattern", [
    ("1 2 0.8 4 2 1.5 0", r"0000_000\.txt:2: 7 columns, expected 8"),
    ("1 2 0.8 4 2 1.5 0 car extra", r"0000_000\.txt:2: 9 columns, expected 8"),
    ("1 abc 0.8 4 2 1.5 0 car", r"0000_000\.txt:2: column 'y' is 'abc', not a number"),
    ("1 2 nan 4 2 1.5 0 car", r"0000_000\.txt:2: column 'z' is nan; label values must be finite"),
    ("1 2 0.8 inf 2 1.5 0 car", r"0000_000\.txt:2: column 'dx' is inf"),
    ("1 2 0.8 4 -2 1.5 0 car", r"0000_000\.txt:2: size dy is -2; box sizes must be > 0"),
    ("1 2 0.8 4 2 1.5 car 0", r"0000_000\.txt:2: column 'heading' is 'car'"),
    ("1 2 0.8 4 2 1.5 0 bicycle", r"0000_000\.txt:2: class 'bicycle' is not in the dataset's classes"),
])
def test_bad_label_line(tmp_path, line, pattern):
    ds = _fresh(tmp_path)
    (tmp_path / "labels" / "0000_000.txt").write_text("1 2 0.8 4 2 1.5 0 car\n" + line + "\n")
    with pytest.raises(DatasetError, match=pattern):
        ds.load("0000_000")


@pytest.mark.parametrize("arr, pattern", [
    (np.zeros((5, 3), np.float32), r"shape \(5, 3\), expected \(N, 4\)"),
    (np.zeros((5,), np.float32), r"shape \(5,\), expected \(N, 4\)"),
    (np.zeros((5, 4), np.float64), r"dtype float64, expected float32"),
    (np.array([[0, 0, 0, 0], [np.nan, 1, 1, 0]], np.float32),
     r"1 point\(s\) have NaN or inf values \(first at row 1\)"),
    (np.array([[0, np.inf, 0, 0]], np.float32), r"NaN or inf"),
])
def test_bad_points_array(tmp_path, arr, pattern):
    ds = _fresh(tmp_path)
    path = tmp_path / "points" / "0.5" / "0000_001.npy"
    np.save(path, arr)
    with pytest.raises(DatasetError, match=r"0000_001\.npy: .*" + pattern):
        ds.load("0000_001")


def test_corrupt_npy(tmp_path):
    ds = _fresh(tmp_path)
    (tmp_path / "points" / "0.5" / "0000_001.npy").write_bytes(b"not numpy at all")
    with pytest.raises(DatasetError, match=r"0000_001\.npy: cannot read as \.npy"):
        ds.load("0000_001")


def test_object_npy_rejected(tmp_path):
    ds = _fresh(tmp_path)
    np.save(tmp_path / "points" / "0.5" / "0000_001.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DatasetError, match=r"0000_001\.npy: cannot read as \.npy"):
        ds.load("0000_001")


def test_listed_id_absent(tmp_path):
    _fresh(tmp_path)
    (tmp_path / "points" / "1.8" / "0001_001.npy").unlink()
    with pytest.raises(MissingFileError, match=r"1 file\(s\) of frames listed in ImageSets are absent.*"
                                               r"points/1\.8/0001_001\.npy"):
        Height3Dataset(tmp_path, 1.8, "all")
    with open(tmp_path / "ImageSets" / "train.txt", "a") as fh:
        fh.write("9999_000\n")
    with pytest.raises(MissingFileError, match=r"9999_000"):
        Height3Dataset(tmp_path, 0.5, "train")
    # without the up-front check the error comes when the frame is read, naming the file
    ds = Height3Dataset(tmp_path, 1.0, "train", check_files=False)
    with pytest.raises(MissingFileError, match=r"labels/9999_000\.txt: label file not found"):
        ds.load("9999_000")


def test_missing_files_and_folders(tmp_path):
    with pytest.raises(MissingFileError, match="dataset folder not found"):
        Height3Dataset(tmp_path / "nope", 1.0)
    (tmp_path / "points").mkdir()
    with pytest.raises(MissingFileError, match=r"dataset\.json: dataset\.json not found: a writer did not finish"):
        Height3Dataset(tmp_path, 1.0)
    _fresh(tmp_path / "d")
    (tmp_path / "d" / "ImageSets" / "test.txt").unlink()
    with pytest.raises(MissingFileError, match=r"test\.txt: split list not found"):
        Height3Dataset(tmp_path / "d", 1.0, "test")
    (tmp_path / "d" / "meta" / "0000_000.json").unlink()
    with pytest.raises(MissingFileError, match=r"meta/0000_000\.json"):
        Height3Dataset(tmp_path / "d", 1.0, "train")


def test_unknown_height_lists_available(tmp_path):
    _fresh(tmp_path)
    with pytest.raises(DatasetError, match=r"no height 1\.2 m in this dataset; available heights: 0\.5, 1\.0, 1\.8"):
        Height3Dataset(tmp_path, 1.2)


def test_bad_imagesets(tmp_path):
    _fresh(tmp_path)
    p = tmp_path / "ImageSets" / "train.txt"
    ids = p.read_text().split()
    p.write_text("\n".join([ids[0], ids[1], ids[0]]) + "\n")
    with pytest.raises(DatasetError, match=r"train\.txt:3: frame id '0000_000' is listed twice"):
        Height3Dataset(tmp_path, 0.5, "train")
    p.write_text("../etc/passwd\n")
    with pytest.raises(DatasetError, match=r"train\.txt:1: invalid frame id"):
        Height3Dataset(tmp_path, 0.5, "train")
    test_ids = (tmp_path / "ImageSets" / "test.txt").read_text().split()
    p.write_text(test_ids[0] + "\n")
    with pytest.raises(DatasetError, match=r"in both train\.txt and test\.txt"):
        Height3Dataset(tmp_path, 0.5, "all")


def test_bad_meta(tmp_path):
    ds = _fresh(tmp_path)
    mp = tmp_path / "meta" / "0000_000.json"
    meta = json.loads(mp.read_text())
    meta["lanes"] = meta["lanes"][:-1]
    mp.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"0000_000\.json: 'lanes' has 3 entries but the label file has 4 boxes"):
        ds.load("0000_000")
    mp.write_text("{not json")
    with pytest.raises(DatasetError, match=r"0000_000\.json:1: not valid JSON"):
        ds.load("0000_000")


def test_bad_dataset_json(tmp_path):
    _fresh(tmp_path)
    p = tmp_path / "dataset.json"
    good = json.loads(p.read_text())
    bad = json.loads(p.read_text())
    bad["heights"]["1.8"]["points_frame"] = "lidar"
    p.write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"dataset\.json: heights\.1\.8\.points_frame is 'lidar'; use one of"):
        Height3Dataset(tmp_path, 1.8)
    bad = dict(good, heights={"1.80": good["heights"]["1.8"]})
    p.write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"height key '1\.80' must be written '1\.8'"):
        Height3Dataset(tmp_path, 1.8)
    p.write_text("{")
    with pytest.raises(DatasetError, match=r"dataset\.json: not valid JSON"):
        Height3Dataset(tmp_path, 1.8)


def test_one_bad_frame_does_not_corrupt_others(tmp_path):
    ds = _fresh(tmp_path)
    np.save(tmp_path / "points" / "0.5" / "0001_000.npy", np.zeros((3, 4), np.float64))
    ok, bad = [], []
    for i in range(len(ds)):
        try:
            ok.append(ds[i].frame_id)
        except DatasetError as e:
            bad.append(e.path)
    assert len(ok) == 5 and len(bad) == 1 and bad[0].endswith("0001_000.npy")
    rep = validate_dataset(tmp_path)
    assert not rep.ok and len(rep.errors) == 1 and "0001_000.npy" in rep.errors[0]


def test_validate_collects_several_problems(tmp_path):
    _fresh(tmp_path)
    (tmp_path / "labels" / "0000_001.txt").write_text("1 2 3\n")
    np.save(tmp_path / "points" / "1.8" / "0002_000.npy", np.zeros((3, 3), np.float32))
    rep = validate_dataset(tmp_path)
    assert len(rep.errors) == 2, rep.errors
    assert any("0000_001.txt:1: 3 columns" in e for e in rep.errors)
    assert any("0002_000.npy" in e for e in rep.errors)


# ----------------------------------------------------------------------------- writer misuse

def test_writer_refuses_overwrite_and_bad_frames(tmp_path):
    _fresh(tmp_path)
    with pytest.raises(FileExistsError, match="a dataset already exists"):
        with DatasetWriter(tmp_path, list(HEIGHTS), {}):
            pass
    rng = np.random.default_rng(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with DatasetWriter(tmp_path / "w", list(HEIGHTS), {}) as w:
            frames = make_frames(0, 0, rng)
            with pytest.raises(ValueError, match="got heights"):
                w.add(frames[:2])
            frames[1].boxes = frames[1].boxes + 1
            with pytest.raises(ValueError, match="labels at 1.0 m differ"):
                w.add(frames)
            w.add(make_frames(0, 0, rng))
            with pytest.raises(ValueError, match="already added"):
                w.add(make_frames(0, 0, rng))
    with pytest.raises(RuntimeError, match="unfinished"), DatasetWriter(tmp_path / "x", [1.0], {}) as w:
        w.add(make_frames(0, 0, rng, heights=(1.0,)))
        raise RuntimeError("unfinished")
    assert not (tmp_path / "x" / "dataset.json").exists()
    with pytest.raises(MissingFileError, match="a writer did not finish"):
        Height3Dataset(tmp_path / "x", 1.0)


def test_writer_overwrite_replaces_the_dataset_whole(tmp_path):
    """An overwrite leaves no file of the old dataset behind; one that stops half-way leaves the old one as it
    was; a folder holding the user's own files is refused."""
    root = tmp_path / "ds"
    write_dataset(root, scenes=3, per_scene=2, seed=0)
    old_ids = set(split_ids(root, "all"))
    assert "0002_001" in old_ids and (root / "points" / "1.8" / "0002_001.npy").is_file()
    (root / "simulate_run.md").write_text("a report of the old dataset")
    with pytest.raises(RuntimeError, match="stops"), DatasetWriter(root, [1.8], {}, overwrite=True) as w:
        w.add(make_frames(7, 0, np.random.default_rng(1), heights=(1.8,)))
        raise RuntimeError("stops")
    assert set(split_ids(root, "all")) == old_ids and (root / "points" / "0.5").is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # nothing left beside it

    with DatasetWriter(root, [1.8], {"kind": "new"}, overwrite=True) as w:
        w.add(make_frames(7, 0, np.random.default_rng(1), heights=(1.8,)))
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert files == [".detbench-owner.json", "ImageSets/test.txt", "ImageSets/train.txt", "dataset.json",
                     "labels/0007_000.txt", "meta/0007_000.json", "points/1.8/0007_000.npy"]
    assert read_info(root).source == {"kind": "new"} and sorted(p.name for p in tmp_path.iterdir()) == ["ds"]

    (root / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"ds: holds notes\.txt, which is not part of a dataset"):
        DatasetWriter(root, [1.8], {}, overwrite=True).open()
    assert (root / "notes.txt").is_file() and (root / "dataset.json").is_file()


# ----------------------------------------------------------------------------- conversion

def test_convert_openpcdet_custom_sensor_frame(tmp_path, capsys):
    from detbench.data.convert import main as convert_main

    rng = np.random.default_rng(5)
    ids = [f"{i:06d}" for i in range(6)]
    ground = {}
    for fid in ids:
        boxes = np.array([[20.0, 0.3, 0.75, 4.5, 1.9, 1.5, 0.1], [40.0, 3.7, 1.6, 10.0, 2.5, 3.2, 0.0]], np.float32)
        road = np.c_[rng.uniform(6, 40, 500), rng.uniform(-3, 3, 500), np.zeros(500), rng.uniform(0, 1, 500)]
        ground[fid] = (boxes, road.astype(np.float32))
    for h, pitch in ((0.5, 0.0), (1.8, 2.5)):
        src = tmp_path / f"{h}m"
        for sub in ("points", "labels", "ImageSets"):
            (src / sub).mkdir(parents=True)
        for fid in ids:
            boxes, road = ground[fid]
            sb = boxes.astype(np.float64).copy()
            sb[:, :3] = ground_to_sensor(sb[:, :3], h, pitch)
            (src / "labels" / f"{fid}.txt").write_text(format_labels(sb.astype(np.float32), ["Car", "Truck"]))
            np.save(src / "points" / f"{fid}.npy", ground_to_sensor(road.astype(np.float64), h, pitch)
                    .astype(np.float32))
    out = tmp_path / "h3"
    with pytest.warns(UserWarning, match="single scene"):
        rc = convert_main(["--src", f"0.5={tmp_path / '0.5m'}", "--src", f"1.8={tmp_path / '1.8m'}",
                           "--out", str(out), "--pitch", "1.8=2.5", "--frames-per-scene", "200"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert printed.count("0.00 m in the converted points (ok)") == 2
    info = read_info(out)
    assert info.heights["1.8"].points_frame == "sensor" and not info.has_meta
    for h in (0.5, 1.8):
        f = Height3Dataset(out, h, "all").load("000003")
        np.testing.assert_allclose(f.boxes, ground["000003"][0], atol=1e-4)
        np.testing.assert_allclose(f.points, ground["000003"][1], atol=1e-4)
        assert f.lanes.tolist() == [0, 1] and f.classes.tolist() == ["Car", "Truck"]
    assert validate_dataset(out).ok
    # a missing pitch: the road is at neither 0 nor -1.8 m in the levelled points, so the frame is not guessed
    with pytest.raises(SystemExit, match=r"cannot tell the frame of the 1\.8 m points.*--pitch.*--points-frame"):
        convert_main(["--src", f"0.5={tmp_path / '0.5m'}", "--src", f"1.8={tmp_path / '1.8m'}",
                      "--out", str(tmp_path / "bad")])
    # ... and with the checks off, a wrong pitch makes the heights' labels disagree
    with pytest.raises(SystemExit, match=r"labels at 1\.8 m do not match those at 0\.5 m"):
        convert_main(["--src", f"0.5={tmp_path / '0.5m'}", "--src", f"1.8={tmp_path / '1.8m'}",
                      "--out", str(tmp_path / "bad"), "--points-frame", "sensor", "--no-frame-check"])


def test_simulated_frames_round_trip(tmp_path):
    from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config

    lidars = [lidar_preset(h) for h in SIM_HEIGHTS]
    sim = HighwaySimulator(load_sim_config("paper"), seed=2)
    written = {}
    with DatasetWriter(tmp_path, list(SIM_HEIGHTS), {"kind": "simulator", "seed": 2}) as w:
        for frames in sim.run(3, lidars, frames_per_scene=1):
            w.add(frames)
            written[frames[0].frame_id] = frames
    for hi, h in enumerate(SIM_HEIGHTS):
        for f in Height3Dataset(tmp_path, h, "all"):
            ref = written[f.frame_id][hi]
            assert f.points.tobytes() == ref.points.tobytes() and f.boxes.tobytes() == ref.boxes.tobytes()
            assert f.classes.tolist() == ref.classes.tolist() and f.lanes.tolist() == ref.lanes.tolist()
            assert f.track_ids.tolist() == ref.track_ids.tolist() and f.ego == ref.ego and f.sensor == ref.sensor
    assert read_info(tmp_path).split["test_scenes"] == ["0002"]



def test_rig_keys_in_dataset_json(tmp_path):
    from detbench.data.frame import data_key, key_label, key_value
    from detbench.data.layout import parse_info

    assert data_key(1.8) == "1.8" and data_key("headlights") == "headlights" and key_value("1.80") == 1.8
    assert key_label("roof-360") == "rig roof-360" and key_label(0.5) == "0.5 m"
    with pytest.raises(ValueError, match="neither a mounting height"):
        data_key("2nd rig")
    sensor = {"height": 0.6, "pitch_deg": 0.0}
    ok = parse_info({"heights": {"headlights": {"sensor": sensor, "rig": {"name": "headlights"}}}}, tmp_path / "d.json")
    assert ok.heights["headlights"].rig == {"name": "headlights"}
    with pytest.raises(DatasetError, match="nor a rig name with a 'rig' object"):
        parse_info({"heights": {"headlights": {"sensor": sensor}}}, tmp_path / "d.json")
    with pytest.raises(DatasetError, match="points_frame must be 'ground' for a rig"):
        parse_info({"heights": {"h": {"sensor": sensor, "rig": {}, "points_frame": "sensor"}}}, tmp_path / "d.json")
