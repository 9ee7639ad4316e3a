"""Datasets both ways between detbench and OpenPCDet's custom format.

The export is read here the way OpenPCDet reads a custom dataset, re-implemented from its
documented format (docs/CUSTOM_DATASET_TUTORIAL.md) and the reading steps of
pcdet/datasets/custom/custom_dataset.py: ImageSets lines stripped, each label line split on
single spaces with the class last and float32 values, `gt_boxes[:, :7]` in info generation,
points from `np.load`, classes mapped through MAP_CLASS_TO_KITTI for evaluation.
"""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from detbench.data import DatasetWriter, Frame, Height3Dataset, Sensor, read_info
from detbench.data.convert import main as convert_main
from detbench.data.openpcdet import guess_points_frame, parse_class_map
from detbench.data.openpcdet_export import EXPORT_MANIFEST, export_openpcdet
from detbench.data.readers import format_labels
from detbench.data.regions import detected_point_counts
from detbench.data.transforms import ground_to_sensor
from detbench.data.validate import validate_dataset
from detbench.utils.atomic import read_json
from detbench.utils.cli import run_main
import tools.analyze
import tools.eval
import tools.export_openpcdet
import tools.simulate
from tests.helpers import ROOT, box_points

KITTI_EVAL = {"Car", "Pedestrian", "Cyclist", "Van", "Person_sitting"}


# ----------------------------------------------------------------------------- OpenPCDet's reading, re-implemented

def opc_imageset(root: Path, split: str) -> list[str] | None:
    path = root / "ImageSets" / f"{split}.txt"
    return [x.strip() for x in open(path).readlines()] if path.exists() else None


def opc_get_label(root: Path, idx: str) -> tuple[np.ndarray, np.ndarray]:
    label_file = root / "labels" / f"{idx}.txt"
    assert label_file.exists()
    boxes, names = [], []
    for line in open(label_file).readlines():
        parts = line.strip().split(" ")
        boxes.append(parts[:-1])
        names.append(parts[-1])
    return np.array(boxes, dtype=np.float32), np.array(names)


def opc_get_lidar(root: Path, idx: str) -> np.ndarray:
    path = root / "points" / f"{idx}.npy"
    assert path.exists()
    return np.load(path)


def opc_infos(root: Path, split: str, num_features: int) -> list[dict]:
    """What create_custom_infos stores for a split: lidar_idx, num_features, names and gt_boxes_lidar[:, :7]."""
    infos = []
    for idx in opc_imageset(root, split):
        boxes, names = opc_get_label(root, idx)
        infos.append({"point_cloud": {"num_features": num_features, "lidar_idx": idx},
                      "annos": {"name": names, "gt_boxes_lidar": boxes[:, :7]}})
    return infos


def opc_load(root: Path) -> dict:
    """The export as OpenPCDet sees it: {split: {frame id: (points, boxes, names)}} plus its config."""
    cfg = yaml.safe_load((root / "custom_dataset.yaml").read_text())
    nf = len(cfg["POINT_FEATURE_ENCODING"]["src_feature_list"])
    out = {"cfg": cfg}
    for mode in ("train", "test"):
        split = cfg["DATA_SPLIT"][mode]
        frames = {}
        for info in opc_infos(root, split, nf):
            idx = info["point_cloud"]["lidar_idx"]
            pts = opc_get_lidar(root, idx)
            assert pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == nf
            names = info["annos"]["name"]
            # evaluation maps every ground-truth class through MAP_CLASS_TO_KITTI (a KeyError otherwise)
            assert all(cfg["MAP_CLASS_TO_KITTI"][n] in KITTI_EVAL for n in names)
            frames[idx] = (pts, info["annos"]["gt_boxes_lidar"], names)
        out[split] = frames
    return out


# ----------------------------------------------------------------------------- a hand-built dataset

def road_points(rng, n=1500):
    return np.c_[rng.uniform(3, 60, n), rng.uniform(-6, 6, n), np.zeros(n), rng.uniform(0, 1, n)]


VEHICLES = [  # x y z dx dy dz heading class, on the road (z = dz / 2)
    [12.0, 0.2, 0.75, 4.5, 1.9, 1.5, 0.05, "car"],
    [25.0, 3.6, 0.85, 4.8, 2.0, 1.7, -0.1, "suv"],
    [33.0, -3.4, 1.6, 10.0, 2.5, 3.2, 0.0, "truck"],
    [48.0, 0.0, 1.1, 5.5, 2.1, 2.2, 3.1, "van"],
]


@pytest.fixture(scope="module")
def hand_dataset(tmp_path_factory):
    """3 scenes x 2 frames at 0.5 m (level) and 1.8 m (pitched 2.5 deg, as the paper's forehead LiDAR).
    Frame 0001_001 has no vehicle; 0002_000 only an suv; the others all four vehicles."""
    root = tmp_path_factory.mktemp("opc") / "ds"
    rng = np.random.default_rng(3)
    sensors = {0.5: Sensor(0.5), 1.8: Sensor(1.8, pitch_deg=2.5)}
    with DatasetWriter(root, [0.5, 1.8], {"kind": "test fixture"}, classes=["car", "suv", "truck", "van"]) as w:
        for s in range(3):
            for i in range(2):
                fid = f"{s:04d}_{i:03d}"
                rows = [] if fid == "0001_001" else [VEHICLES[1]] if fid == "0002_000" else VEHICLES
                boxes = np.array([r[:7] for r in rows], dtype=np.float32).reshape(-1, 7)
                names = np.array([r[7] for r in rows], dtype=str)
                frames = []
                for h in (0.5, 1.8):
                    inside = [box_points(b, 12, rng, margin=0.15) for b in boxes]
                    pts = np.concatenate([road_points(rng), *inside]).astype(np.float32)
                    frames.append(Frame(fid, f"{s:04d}", pts, boxes, names, np.arange(len(rows)),
                                        np.zeros(len(rows), dtype=np.int64), sensors[h]))
                w.add(frames)
    return root


# ----------------------------------------------------------------------------- export

def test_export_is_read_by_openpcdets_logic(hand_dataset, tmp_path, capsys):
    tool = tools.export_openpcdet
    out = tmp_path / "opc"
    assert tool.main([str(hand_dataset), "--height", "1.8", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "ground frame" in printed and "car: 4 line(s) kept as Vehicle" in printed
    assert "create_custom_infos" in printed and "--pred-frame ground" in printed
    opc = opc_load(out)
    assert opc["cfg"]["DATA_SPLIT"] == {"train": "train", "test": "val"}
    assert opc["cfg"]["DATA_PATH"] == str(out.resolve())
    assert opc["cfg"]["MAP_CLASS_TO_KITTI"] == {"Vehicle": "Car"}
    for det_split, opc_split in (("train", "train"), ("test", "val")):
        ds = Height3Dataset(hand_dataset, 1.8, det_split)
        with_boxes = [f for f in ds.frame_ids if f != "0001_001"]
        assert list(opc[opc_split]) == with_boxes  # the empty frame is not listed
        for fid in with_boxes:
            f = ds.load(fid)
            pts, boxes, names = opc[opc_split][fid]
            np.testing.assert_array_equal(pts, f.points)  # ground frame: the points as detbench reads them
            np.testing.assert_array_equal(boxes, f.boxes)
            assert names.tolist() == ["Vehicle"] * len(f.boxes)
    # the left-out frame is why: OpenPCDet's info generation cannot read an empty label file
    (out / "labels" / "0001_001.txt").write_text("")
    (out / "ImageSets" / "val.txt").write_text("0001_001\n")
    with pytest.raises(IndexError):
        opc_infos(out, "val", 4)
    m = read_json(out / EXPORT_MANIFEST)
    assert m["frame"] == "ground" and m["frames_without_boxes"]["train"] + m["frames_without_boxes"]["val"] == \
        ["0001_001"]
    assert m["class_counts"]["car"] == {"kept": 4, "dropped": 0, "as": "Vehicle"}
    assert m["sensor"] == {"height_m": 1.8, "pitch_deg": 2.5, "per_frame": [{"height_m": 1.8, "pitch_deg": 2.5,
                                                                             "frames": 5}]}
    assert "left out" in (out / "detbench_export.md").read_text()
    script = (out / "create_infos.sh").read_text()
    assert "create_custom_infos" in script and str(out.resolve()) in script


def test_export_sensor_frame_offsets_points_and_boxes(hand_dataset, tmp_path):
    for h in (0.5, 1.8):
        out = tmp_path / f"opc_{h}"
        m = export_openpcdet(hand_dataset, h, out, frame="sensor", progress=False)
        assert m["frame"] == "sensor"
        cfg = yaml.safe_load((out / "custom_dataset.yaml").read_text())
        pcr = cfg["POINT_CLOUD_RANGE"]
        assert pcr[2] == pytest.approx(-1.0 - h) and pcr[5] - pcr[2] == pytest.approx(6.0)
        voxels = [round((pcr[i + 3] - pcr[i]) / v) for i, v in enumerate((0.1, 0.1, 0.15))]
        assert voxels[0] % 16 == 0 and voxels[1] % 16 == 0 and voxels[2] == 40  # OpenPCDet's rules for voxel nets
        opc = opc_load(out)
        ds = Height3Dataset(hand_dataset, h, "train")
        s = ds.sensor
        for fid, (pts, boxes, _) in opc["train"].items():
            f = ds.load(fid)
            np.testing.assert_allclose(pts[:, :3], ground_to_sensor(f.points, s.height, s.pitch_deg)[:, :3],
                                       atol=1e-5)
            np.testing.assert_allclose(boxes[:, :3], ground_to_sensor(f.boxes[:, :3], s.height, s.pitch_deg),
                                       atol=1e-5)
            np.testing.assert_array_equal(boxes[:, 3:], f.boxes[:, 3:])
            if s.pitch_deg == 0:  # a level sensor: the frame is the ground frame shifted down by the height
                np.testing.assert_allclose(boxes[:, 2], f.boxes[:, 2] - h, atol=1e-6)
                np.testing.assert_allclose(pts[:, 2], f.points[:, 2] - h, atol=1e-6)
                # the same points fall in the same boxes
                assert detected_point_counts(pts, boxes).tolist() == \
                    detected_point_counts(f.points, f.boxes).tolist()
        assert any("pitched 2.5 deg" in n for n in m["notes"]) == (h == 1.8)


def test_export_class_map_and_folder_rules(hand_dataset, tmp_path):
    out = tmp_path / "opc"
    m = export_openpcdet(hand_dataset, 0.5, out, class_map="car=Car,truck=Truck,van=Van,*=-", progress=False)
    assert m["classes"] == ["Car", "Truck", "Van"]
    assert m["class_counts"]["suv"] == {"kept": 0, "dropped": 5, "as": None}
    assert m["map_class_to_kitti"] == {"Car": "Car", "Truck": "Car", "Van": "Van"}
    opc = opc_load(out)
    listed = set(opc["train"]) | set(opc["val"])
    assert "0002_000" not in listed and "0001_001" not in listed  # only an suv, dropped / no vehicle
    assert all(n.tolist() == ["Car", "Truck", "Van"] for _, _, n in {**opc["train"], **opc["val"]}.values())
    # an earlier export is replaced only with overwrite, OpenPCDet's infos made from it with it
    (out / "custom_infos_train.pkl").write_bytes(b"old")
    with pytest.raises(ValueError, match="--overwrite"):
        export_openpcdet(hand_dataset, 0.5, out, progress=False)
    export_openpcdet(hand_dataset, 0.5, out, overwrite=True, progress=False)
    assert not (out / "custom_infos_train.pkl").exists() and (out / "labels" / "0002_000.txt").exists()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        export_openpcdet(hand_dataset, 0.5, foreign, overwrite=True, progress=False)


def test_class_map_parsing():
    m = parse_class_map(["vehicle", "truck=Truck"])
    assert m.target("car") == "Vehicle" and m.target("TRUCK") == "Truck"
    keep = parse_class_map("vehicles-only")
    assert keep.target("Pedestrian") is None and keep.target("cyclist") is None and keep.target("Vehicle") == "Vehicle"
    mask, names = keep.apply(["Vehicle", "Pedestrian", "car"])
    assert mask.tolist() == [True, False, True] and names == ["Vehicle", "car"]
    assert parse_class_map("car=Car").target("bus") == "bus"  # not covered: kept
    for bad in ("car", "car=a b", "=x", "car=1.5"):
        with pytest.raises(ValueError, match="--class-map"):
            parse_class_map(bad)


# ----------------------------------------------------------------------------- import

def write_opc_folder(root: Path, frames: dict, split: dict | None = None):
    """An OpenPCDet custom folder: frames {id: (points, boxes, names)}; split {'train': [...], 'val': [...]}."""
    for sub in ("points", "labels", "ImageSets"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for fid, (pts, boxes, names) in frames.items():
        np.save(root / "points" / f"{fid}.npy", np.asarray(pts, dtype=np.float32))
        (root / "labels" / f"{fid}.txt").write_text(format_labels(np.asarray(boxes, np.float32), names))
    for name, ids in (split or {}).items():
        (root / "ImageSets" / f"{name}.txt").write_text("".join(f + "\n" for f in ids))


def ground_frames(n=6, seed=0, extra=()):
    rng = np.random.default_rng(seed)
    boxes = np.array([v[:7] for v in VEHICLES], dtype=np.float32)
    out = {}
    for i in range(n):
        pts = np.concatenate([road_points(rng), *(box_points(b, 12, rng, margin=0.15) for b in boxes)])
        names = ["Vehicle"] * len(boxes)
        b = boxes
        if extra:
            b = np.concatenate([boxes, np.array([e[:7] for e in extra], np.float32)])
            names = names + [e[7] for e in extra]
        out[f"{i:06d}"] = (pts, b, names)
    return out


def test_import_finds_ground_frame_points_and_keeps_ldr(tmp_path, capsys):
    """Ground-frame points are recognised as such, not converted as sensor-frame ones (which drops LDR from 1.0
    to 0.33)."""
    frames = ground_frames()
    src = tmp_path / "src"
    write_opc_folder(src, frames, {"train": ["000000", "000001", "000003", "000004"], "val": ["000002", "000005"]})
    out = tmp_path / "out"
    assert convert_main(["--src", f"1.8={src}", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "points in the ground frame (found from the road" in printed
    info = read_info(out)
    assert info.heights["1.8"].points_frame == "ground" and info.source["labels_frame"] == {"1.8": "ground"}
    ds = Height3Dataset(out, 1.8, "all")
    for f in ds:
        np.testing.assert_allclose(f.points[:, :3], frames[f.frame_id][0][:, :3], atol=1e-6)
        assert (detected_point_counts(f.points, f.boxes) > 0).all()  # LDR 1.0, as in the source
    # the source split is kept by default (it is by frame here, not by scene)
    assert Height3Dataset(out, 1.8, "test").frame_ids == ["000002", "000005"]
    assert info.split["rule"] == "kept" and validate_dataset(out).ok
    assert (out / "convert_report.md").is_file() and read_json(out / "convert_report.json")["num_frames"] == 6
    # saying the wrong frame is refused with the flag to fix
    with pytest.raises(SystemExit, match="--points-frame sensor, but the road .* says ground"):
        convert_main(["--src", f"1.8={src}", "--out", str(tmp_path / "o2"), "--points-frame", "sensor",
                      "--labels-frame", "ground", "--no-progress"])
    # --resplit re-makes it by scene (blocks of --frames-per-scene ids)
    assert convert_main(["--src", f"1.8={src}", "--out", str(tmp_path / "o3"), "--resplit", "--frames-per-scene",
                         "2", "--no-progress"]) == 0
    assert Height3Dataset(tmp_path / "o3", 1.8, "test").frame_ids == ["000004", "000005"]


def test_import_warns_when_the_kept_split_cuts_scenes(tmp_path, capsys):
    """A source split that puts frames of one scene in both splits is kept with one warning line naming how many
    scenes it cuts and --resplit; a split that keeps scenes whole, and --resplit, convert without one."""
    frames = ground_frames(n=12)  # 4 scenes of 3 consecutive ids with --frames-per-scene 3
    ids = sorted(frames)

    def convert(split, name, *extra):
        src = tmp_path / f"src_{name}"
        write_opc_folder(src, frames, split)
        out = tmp_path / name
        assert convert_main(["--src", f"1.8={src}", "--out", str(out), "--frames-per-scene", "3", "--no-progress",
                             *extra]) == 0
        err = capsys.readouterr().err
        return out, [line for line in err.splitlines() if line.startswith("warning:")]

    by_frame = {"train": [f for i, f in enumerate(ids) if i not in (4, 10)], "val": [ids[4], ids[10]]}
    out, warned = convert(by_frame, "by_frame")
    assert len(warned) == 1, warned
    assert "puts frames of 2 of 4 scenes (blocks of 3 consecutive frame ids, --frames-per-scene)" in warned[0]
    assert "pass --resplit to split by scene" in warned[0]
    info = read_info(out)
    assert info.split["rule"] == "kept" and info.source["warnings"] == [warned[0].removeprefix("warning: ")]
    assert "Warnings:" in (out / "convert_report.md").read_text()
    assert Height3Dataset(out, 1.8, "test").frame_ids == [ids[4], ids[10]]  # kept as the source has it
    # scenes whole in the source's split: no warning
    out, warned = convert({"train": ids[:9], "val": ids[9:]}, "by_scene")
    assert warned == [] and read_info(out).source["warnings"] == []
    # --resplit splits by scene, whatever the source's lists say
    out, warned = convert(by_frame, "resplit", "--resplit")
    assert warned == [] and read_info(out).split["rule"] == "by-scene"
    scene = {f: i // 3 for i, f in enumerate(ids)}
    test, train = (Height3Dataset(out, 1.8, s).frame_ids for s in ("test", "train"))
    assert test and {scene[f] for f in test}.isdisjoint(scene[f] for f in train)
    # every frame in one scene (fewer ids than --frames-per-scene): the kept split cuts that scene
    src = tmp_path / "src_one"
    write_opc_folder(src, frames, by_frame)
    assert convert_main(["--src", f"1.8={src}", "--out", str(tmp_path / "one"), "--no-progress"]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warned) == 1 and "all 12 frames form one scene (blocks of 200" in warned[0]


def test_import_sensor_frame_and_ambiguous_road(tmp_path, capsys):
    frames = ground_frames()
    src = tmp_path / "sensor"
    write_opc_folder(src, {k: (ground_to_sensor(p, 1.0), np.c_[b[:, :2], b[:, 2] - 1.0, b[:, 3:]], n)
                           for k, (p, b, n) in frames.items()})
    out = tmp_path / "out"
    assert convert_main(["--src", f"1.0={src}", "--out", str(out), "--frames-per-scene", "2", "--no-progress"]) == 0
    assert "ImageSets/train.txt not found: the split is re-made by scene" in capsys.readouterr().out
    f = Height3Dataset(out, 1.0, "all").load("000001")
    np.testing.assert_allclose(f.boxes, frames["000001"][1], atol=1e-5)
    np.testing.assert_allclose(f.points[:, :3], frames["000001"][0][:, :3], atol=1e-5)
    # no road in front of the car: the frame cannot be found, and the message names the flag
    noroad = tmp_path / "noroad"
    write_opc_folder(noroad, {k: (p[p[:, 0] > 60], b, n) for k, (p, b, n) in frames.items()})
    with pytest.raises(SystemExit, match="too few points on the road.*--points-frame sensor"):
        convert_main(["--src", f"1.0={noroad}", "--out", str(tmp_path / "o2"), "--no-progress"])
    # a road at neither 0 nor -height (a wrong --src height)
    with pytest.raises(SystemExit, match="not within .* check the height"):
        convert_main(["--src", f"1.8={src}", "--out", str(tmp_path / "o3"), "--no-progress"])
    assert guess_points_frame([0.01, -0.02], 0.25)[0] is None  # too low to tell the frames apart
    assert guess_points_frame([-0.49, -0.51], 0.5)[0] == "sensor"
    assert guess_points_frame([-0.02, -1.8], 1.8)[0] is None  # frames disagree


def test_import_class_map_counts(tmp_path, capsys):
    extra = [[8.0, 2.0, 0.9, 0.6, 0.6, 1.8, 0.0, "Pedestrian"], [15.0, -2.0, 0.8, 1.8, 0.6, 1.6, 0.0, "Cyclist"]]
    src = tmp_path / "src"
    write_opc_folder(src, ground_frames(n=3, extra=extra), {"train": ["000000", "000001"], "val": ["000002"]})
    out = tmp_path / "out"
    assert convert_main(["--src", f"1.8={src}", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "Pedestrian: 0 line(s) kept, 3 dropped" in printed and "Cyclist: 0 line(s) kept, 3 dropped" in printed
    assert "Vehicle: 12 line(s) kept, 0 dropped" in printed
    ds = Height3Dataset(out, 1.8, "all")
    assert all(f.classes.tolist() == ["Vehicle"] * 4 for f in ds) and read_info(out).classes == ["Vehicle"]
    out2 = tmp_path / "out2"
    assert convert_main(["--src", f"1.8={src}", "--out", str(out2), "--class-map", "Vehicle=car,Cyclist=-",
                         "--no-progress"]) == 0
    assert "Vehicle: 12 line(s) kept as car" in capsys.readouterr().out
    assert Height3Dataset(out2, 1.8, "all").load("000000").classes.tolist() == ["car"] * 4 + ["Pedestrian"]


def test_import_wrong_labels_frame_is_one_clear_line(tmp_path):
    """Ground-frame labels converted as sensor-frame ones: one 'error:' line naming the flag, no traceback."""
    src = tmp_path / "src"
    write_opc_folder(src, ground_frames(n=3))
    r = subprocess.run([sys.executable, "-m", "detbench.data.convert", "--src", f"1.8={src}", "--out",
                        str(tmp_path / "out"), "--labels-frame", "sensor", "--no-progress"],
                       capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.startswith("error: ")
    assert "pass --labels-frame ground" in r.stderr and "labels" in r.stderr


def test_tools_on_an_unconverted_folder_name_the_convert_command(tmp_path, capsys):
    src = tmp_path / "mine"
    write_opc_folder(src, ground_frames(n=2), {"train": ["000000"], "val": ["000001"]})
    expected = f"convert it first: python -m detbench.data.convert --src HEIGHT={src}"
    rep = validate_dataset(src)
    assert not rep.ok and expected in rep.errors[0] and "writer did not finish" not in rep.errors[0]
    with pytest.raises(SystemExit, match="convert it first"):
        tools.analyze.main(["--data", str(src), "--out", str(tmp_path / "a"), "--no-figures",
                                   "--no-progress"])
    pred = tmp_path / "pred"
    pred.mkdir()
    assert run_main(tools.eval.main, ["--data", str(src), "--height", "1.8", "--pred", str(pred), "--out",
                                   str(tmp_path / "e"), "--no-progress"]) == 2
    assert expected in capsys.readouterr().err


def test_round_trip_through_openpcdet_on_simulated_data(tmp_path):
    """simulate -> export (sensor frame, pitched 1.8 m LiDAR) -> convert back: same frames, boxes, points, LDR,
    split."""
    sim = tmp_path / "sim"
    assert tools.simulate.main(["--out", str(sim), "--scenes", "3", "--frames-per-scene", "2", "--heights",
                                       "1.8", "--seed", "2", "--no-progress"]) == 0
    exp = tmp_path / "opc"
    m = export_openpcdet(sim, 1.8, exp, frame="sensor", progress=False)
    back = tmp_path / "back"
    assert convert_main(["--src", f"1.8={exp}", "--out", str(back), "--pitch", "1.8=2.5", "--no-progress"]) == 0
    a, b = Height3Dataset(sim, 1.8, "all"), Height3Dataset(back, 1.8, "all")
    empty = m["frames_without_boxes"]["train"] + m["frames_without_boxes"]["val"]
    assert b.frame_ids == [f for f in a.frame_ids if f not in empty]
    for fid in b.frame_ids:
        fa, fb = a.load(fid), b.load(fid)
        np.testing.assert_allclose(fb.boxes, fa.boxes, atol=1e-4)
        np.testing.assert_allclose(fb.points, fa.points, atol=1e-4)
        assert (detected_point_counts(fb.points, fb.boxes) > 0).tolist() == \
            (detected_point_counts(fa.points, fa.boxes) > 0).tolist()
    assert Height3Dataset(back, 1.8, "test").frame_ids == \
        [f for f in Height3Dataset(sim, 1.8, "test").frame_ids if f not in empty]
    assert read_info(back).source["frames"]["1.8"]["frame"] == "sensor"


# ----------------------------------------------------------------------------- both directions, pinned

def _tree_text(root: Path, names: dict[str, str]) -> str:
    """Every file under `root`, sorted: text files whole, arrays as shape, dtype and a digest of their values;
    the paths in `names` (path -> placeholder) replaced, so the text does not depend on the test's folders. The
    folder's owner file (detbench.utils.folder_ownership's, the same for every folder it writes) is left out."""
    import hashlib

    out = []
    for p in sorted(q for q in root.rglob("*") if q.is_file() and not q.name.startswith(".detbench-")):
        rel = p.relative_to(root).as_posix()
        if p.suffix == ".npy":
            a = np.load(p)
            out.append(f"== {rel}: {a.dtype} {a.shape} sha256 {hashlib.sha256(a.tobytes()).hexdigest()[:16]}")
            continue
        text = p.read_text()
        for path, placeholder in names.items():
            text = text.replace(path, placeholder)
        out.append(f"== {rel}\n{text}")
    return "\n".join(out) + "\n"


def test_export_and_import_are_pinned(hand_dataset, tmp_path, capsys):
    """tools/export_openpcdet.py (sensor frame at the pitched 1.8 m, ground frame at 0.5 m, classes mapped and
    dropped) and the import of both exports back (python -m detbench.data.convert): every file each writes and
    every line each prints, for a fixed dataset."""
    import re

    from tests.helpers import assert_golden

    names = {str(tmp_path.resolve()): "TMP", str(hand_dataset.resolve()): "DATA"}
    parts = []
    for h, frame in (("1.8", "sensor"), ("0.5", "ground")):
        out = tmp_path / f"opc_{h}"
        assert tools.export_openpcdet.main([str(hand_dataset), "--height", h, "--out", str(out), "--frame", frame,
                                            "--class-map", "car=Car,truck=Truck,van=Van,*=-", "--no-progress"]) == 0
        printed = re.sub(r"\(\d+\.\d s\)", "(N s)", capsys.readouterr().out)
        parts += [f"### export {h} m, {frame} frame: printed", printed, _tree_text(out, names)]
    back = tmp_path / "back"
    assert convert_main(["--src", f"1.8={tmp_path / 'opc_1.8'}", "--src", f"0.5={tmp_path / 'opc_0.5'}",
                         "--pitch", "1.8=2.5", "--points-frame", "auto", "--frames-per-scene", "2", "--out",
                         str(back), "--no-progress"]) == 0
    parts += ["### import: printed", capsys.readouterr().out, _tree_text(back, names)]
    text = "\n".join(parts)
    for path, placeholder in names.items():
        text = text.replace(path, placeholder)
    assert_golden("openpcdet_round_trip.txt", text)
