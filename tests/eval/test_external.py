"""OpenPCDet's predictions into tools/eval.py: result.pkl read safely, its text layouts, the
prediction frame, class selection, and the frame-mismatch warning."""
import json
import math
import os
import pickle

import numpy as np
import pytest

from detbench.data import DatasetWriter, Frame, Height3Dataset, Sensor
from detbench.data.transforms import boxes_ground_to_sensor
from detbench.eval.external import (
    kitti_camera_to_lidar, load_predictions, parse_prediction_text, predictions_from_result_pkl,
    vertical_offset_check,
)
from detbench.utils.cli import run_main
import tools.eval

CARS = np.array([[12.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.1], [26.0, 3.5, 0.8, 4.4, 1.9, 1.6, -0.2],
                 [41.0, -3.5, 1.5, 9.0, 2.5, 3.0, 0.0], [70.0, 0.5, 0.9, 4.6, 2.0, 1.8, 3.0]], dtype=np.float32)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """3 scenes x 2 frames; the LiDAR at 1.8 m pitched 2.5 deg (the paper's forehead LiDAR) and at 0.5 m, level.
    Every vehicle has points inside (LiDAR-detected)."""
    root = tmp_path_factory.mktemp("ext") / "ds"
    pts = np.concatenate([np.c_[b[0] + np.linspace(-1, 1, 5), np.full(5, b[1]), np.full(5, b[2]), np.full(5, 0.5)]
                          for b in CARS]).astype(np.float32)
    with DatasetWriter(root, [0.5, 1.8], {"kind": "test fixture"}) as w:
        for s in range(3):
            for i in range(2):
                w.add([Frame(f"{s:04d}_{i:03d}", f"{s:04d}", pts, CARS, np.array(["car"] * 4), np.arange(4),
                             np.array([0, 1, -1, 0]), sensor) for sensor in (Sensor(0.5), Sensor(1.8, 2.5))])
    return root


def opc_entry(fid, boxes, scores, names):
    """One per-frame dict as OpenPCDet's generate_prediction_dicts makes it (frame_id a numpy string)."""
    n = len(boxes)
    return {"name": np.array(names) if n else np.zeros(0), "score": np.asarray(scores, np.float32),
            "boxes_lidar": np.asarray(boxes, np.float32).reshape(n, -1) if n else np.zeros((0, 7), np.float32),
            "pred_labels": np.ones(n, np.int64),
            "frame_id": np.array([fid])[0]}


# ----------------------------------------------------------------------------- result.pkl

def test_result_pkl_is_read_with_numpy_of_either_generation(tmp_path):
    boxes9 = np.c_[CARS, np.zeros((4, 2))]  # (M, 9): OpenPCDet's boxes with velocities
    annos = [opc_entry("0000_000", boxes9, [0.9, 0.8, 0.7, 0.6], ["Vehicle"] * 4),
             opc_entry("0000_001", np.zeros((0, 7)), [], [])]
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps(annos, protocol=4))
    got = predictions_from_result_pkl(path)
    assert list(got) == ["0000_000", "0000_001"]
    np.testing.assert_allclose(got["0000_000"].boxes, CARS, atol=1e-6)
    assert got["0000_000"].names.tolist() == ["Vehicle"] * 4 and len(got["0000_001"].boxes) == 0
    # numpy 1.x names numpy.core.multiarray in its pickles (protocol 3, Python 3.7's default, writes the
    # module names as plain text lines)
    old = pickle.dumps(annos, protocol=3).replace(b"numpy._core", b"numpy.core")
    assert b"numpy.core.multiarray" in old and b"numpy._core" not in old
    path.write_bytes(old)
    np.testing.assert_allclose(predictions_from_result_pkl(path)["0000_000"].scores, [0.9, 0.8, 0.7, 0.6], atol=1e-6)


class _Payload:
    """A pickle that deletes a file when loaded (what an untrusted result file could do)."""

    def __init__(self, victim):
        self.victim = str(victim)

    def __reduce__(self):
        return (os.remove, (self.victim,))


def test_result_pkl_refuses_code(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("still here")
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps([{"frame_id": "0000_000", "boxes_lidar": np.zeros((0, 7)), "score": np.zeros(0),
                                    "name": _Payload(victim)}]))
    with pytest.raises(ValueError, match="posix.remove|os.remove") as e:
        predictions_from_result_pkl(path)
    assert "only plain containers and numpy arrays" in str(e.value) and victim.read_text() == "still here"
    path.write_bytes(pickle.dumps({"not": "a list"}))
    with pytest.raises(ValueError, match="not OpenPCDet's list of per-frame dicts"):
        predictions_from_result_pkl(path)
    path.write_bytes(pickle.dumps([{"frame_id": "a", "score": np.zeros(0)}]))
    with pytest.raises(ValueError, match="entry 0 has no boxes_lidar"):
        predictions_from_result_pkl(path)
    path.write_bytes(pickle.dumps([opc_entry("a", CARS, [0.5] * 3, ["Vehicle"] * 4)]))
    with pytest.raises(ValueError, match="4 boxes but 3 scores"):
        predictions_from_result_pkl(path)
    path.write_bytes(b"\x80\x04truncated")
    with pytest.raises(ValueError, match="not a readable pickle"):
        predictions_from_result_pkl(path)


# ----------------------------------------------------------------------------- per-frame text layouts

def kitti_line(name, box, score):
    """A line of OpenPCDet's KITTI text layout for a LiDAR box, camera values as its calibration-free
    kitti_utils.transform_annotations_to_kitti_format makes them."""
    x, y, z, dx, dy, dz, heading = (float(v) for v in box)
    loc = (-y, -(z - dz / 2), x)
    ry = -heading - math.pi / 2
    alpha = -math.atan2(-y, x) + ry
    return f"{name} -1 -1 {alpha:.4f} 0 0 50 50 {dz:.4f} {dy:.4f} {dx:.4f} " \
           f"{loc[0]:.4f} {loc[1]:.4f} {loc[2]:.4f} {ry:.4f} {score:.4f}"


def test_text_layouts(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("12 0 0.8 4 2 1.6 0.1 0.9 car\n26 3.5 0.8 4.4 1.9 1.6 -0.2 0.5\n")
    got, layout = parse_prediction_text(p)
    assert layout == "detbench" and got.scores.tolist() == [0.9, 0.5] and got.names.tolist() == ["car", ""]
    p.write_text("12 0 0.8 4 2 1.6 0.1 Vehicle 0.9\n70 0.5 0.9 4.6 2 1.8 3 Pedestrian 0.3\n")
    got, layout = parse_prediction_text(p)
    assert layout == "openpcdet-custom" and got.names.tolist() == ["Vehicle", "Pedestrian"]
    np.testing.assert_allclose(got.boxes[1], [70, 0.5, 0.9, 4.6, 2, 1.8, 3])
    p.write_text("\n".join(kitti_line("Car", b, 0.8) for b in CARS) + "\n")
    got, layout = parse_prediction_text(p)
    assert layout == "kitti" and got.names.tolist() == ["Car"] * 4
    np.testing.assert_allclose(got.boxes, CARS, atol=2e-4)
    np.testing.assert_allclose(kitti_camera_to_lidar(np.array([[1.6, 2.0, 4.0, 0.0, 0.0, 12.0, -math.pi / 2]])),
                               [[12.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0]], atol=1e-12)
    for text, message in (("12 0 0.8 4 2 1.6 0.1 Vehicle\n", "without a score"),
                          ("12 0 0.8 4 2 1.6 0.1 0.9\n12 0 0.8 4 2 1.6 0.1 Car 0.9\n", "layout openpcdet-custom but"),
                          (kitti_line("Car", CARS[0], 0.5).rsplit(" ", 1)[0] + "\n", "without the score"),
                          ("1 2 3\n", "a.txt:1: expected 8 numbers")):
        p.write_text(text)
        with pytest.raises(ValueError, match=message):
            parse_prediction_text(p)


# ----------------------------------------------------------------------------- loading, frames, classes

def test_load_predictions_frames_and_classes(dataset, tmp_path):
    ds = Height3Dataset(dataset, 1.8, "test")
    other = Height3Dataset(dataset, 1.8, "train").frame_ids
    fid = ds.frame_ids[0]
    sensor_boxes = boxes_ground_to_sensor(CARS, 1.8, 2.5)
    ped = [[8.0, 2.0, -0.9, 0.6, 0.6, 1.8, 0.0]]
    annos = [opc_entry(fid, np.r_[sensor_boxes, ped], [0.9, 0.8, 0.7, 0.6, 0.95], ["Vehicle"] * 4 + ["Pedestrian"]),
             opc_entry(other[0], CARS, [0.5] * 4, ["Vehicle"] * 4)]
    path = tmp_path / "result.pkl"
    path.write_bytes(pickle.dumps(annos))
    got = load_predictions(path, ds, other, pred_frame="sensor")
    assert got.skipped == [other[0]] and list(got.predictions) == [fid]
    np.testing.assert_allclose(got.predictions[fid].boxes, CARS, atol=1e-4)  # back in the ground frame
    assert got.info["class_counts"] == {"Vehicle": {"kept": 4, "dropped": 0}, "Pedestrian": {"kept": 0, "dropped": 1}}
    assert got.info["moved_to_ground_with"] == [{"height_m": 1.8, "pitch_deg": 2.5, "frames": 1}]
    assert len(load_predictions(path, ds, other, classes=["pedestrian"]).predictions[fid].boxes) == 1
    with pytest.raises(ValueError, match="unknown frame id '0000_000'"):
        load_predictions(path, ds, [])


def test_frame_check_does_not_cry_wolf(dataset):
    ds = Height3Dataset(dataset, 0.5, "all")
    rng = np.random.default_rng(0)
    good = {f: (CARS + np.c_[rng.normal(0, 0.1, (4, 3)), np.zeros((4, 4))], np.full(4, 0.9)) for f in ds.frame_ids}
    res = vertical_offset_check(ds, good)
    assert res["matches"] == 24 and not res["likely_frame_mismatch"] and res["warning"] is None
    assert abs(res["median_dz_m"]) < 0.1
    lifted = {f: (b + np.array([0, 0, 0.6, 0, 0, 0, 0]), s) for f, (b, s) in good.items()}
    res = vertical_offset_check(ds, lifted)
    assert res["likely_frame_mismatch"] and "0.6" in res["warning"] and "Neither frame fits" in res["warning"]
    assert not vertical_offset_check(ds, {ds.frame_ids[0]: lifted[ds.frame_ids[0]]})["likely_frame_mismatch"]


def test_eval_tool_warns_on_sensor_frame_predictions(dataset, tmp_path, capsys):
    """A model trained on sensor-frame data predicts boxes 1.8 m low: evaluated as ground-frame boxes it scores
    TP 0 / AP 0; the report and stderr say why, and --pred-frame sensor gives the right figures."""
    tool = tools.eval
    for h, pitch in ((0.5, 0.0), (1.8, 2.5)):
        ds = Height3Dataset(dataset, h, "test")
        annos = [opc_entry(f, boxes_ground_to_sensor(CARS, h, pitch), [0.9, 0.8, 0.7, 0.6], ["Vehicle"] * 4)
                 for f in ds.frame_ids]
        pkl = tmp_path / f"result_{h}.pkl"
        pkl.write_bytes(pickle.dumps(annos))
        base = ["--data", str(dataset), "--height", str(h), "--pred", str(pkl), "--no-progress", "--no-extras"]
        out = tmp_path / f"wrong_{h}"
        assert run_main(tool.main, base + ["--out", str(out)]) == 0
        captured = capsys.readouterr()
        assert "warning: likely frame mismatch" in captured.err and "--pred-frame sensor" in captured.err
        rep = json.loads((out / "report.json").read_text())
        large = rep["results"]["large"]["all"]
        # boxes h m low (and, pitched, a growing offset): most vehicles are missed at 3D IoU 0.7
        assert large["tp"] <= len(ds) and large["lidar_detected"] == 4 * len(ds)
        assert rep["frame_check"]["likely_frame_mismatch"] and rep["warnings"] == [rep["frame_check"]["warning"]]
        if pitch == 0:
            assert rep["frame_check"]["median_dz_m"] == pytest.approx(-h, abs=1e-4)
        assert "**Warning: likely frame mismatch" in (out / "report.md").read_text()
        out = tmp_path / f"right_{h}"
        assert run_main(tool.main, base + ["--out", str(out), "--pred-frame", "sensor"]) == 0
        captured = capsys.readouterr()
        assert "warning" not in captured.err and "moved from the LiDAR's own frame" in captured.out
        rep = json.loads((out / "report.json").read_text())
        large = rep["results"]["large"]["all"]
        assert large["tp"] == large["lidar_detected"] == 4 * len(ds) and large["ap_r40"] == pytest.approx(1.0)
        assert rep["prediction_input"]["format"] == "openpcdet-result.pkl" and rep["prediction_input"]["frame"] == \
            "sensor" and "warnings" not in rep
        # and the reverse mistake: ground-frame boxes declared as sensor-frame
        pkl.write_bytes(pickle.dumps([opc_entry(f, CARS, [0.9, 0.8, 0.7, 0.6], ["Vehicle"] * 4)
                                      for f in ds.frame_ids]))
        assert run_main(tool.main, base + ["--out", str(out), "--pred-frame", "sensor"]) == 0
        assert "pass --pred-frame ground" in capsys.readouterr().err
    assert run_main(tool.main, ["--ckpt", str(tmp_path / "none.pt"), "--pred-frame", "sensor", "--no-progress"]) == 2


def test_eval_tool_reads_openpcdet_text_folder(dataset, tmp_path, capsys):
    ds = Height3Dataset(dataset, 0.5, "test")
    pred = tmp_path / "pred"
    pred.mkdir()
    for f in ds.frame_ids:
        lines = [" ".join(f"{v:.6g}" for v in b) + f" Vehicle {0.9 - 0.1 * i:.2f}" for i, b in enumerate(CARS)]
        (pred / f"{f}.txt").write_text("\n".join(lines + ["8 2 0.9 0.6 0.6 1.8 0 Cyclist 0.99"]) + "\n")
    out = tmp_path / "out"
    assert tools.eval.main(["--data", str(dataset), "--height", "0.5", "--pred", str(pred), "--out", str(out),
                                   "--no-progress", "--no-extras"]) == 0
    assert "Cyclist 0 kept / 2 dropped" in capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    assert rep["prediction_input"]["layouts"] == {"openpcdet-custom": 2}
    assert rep["results"]["large"]["all"]["fp"] == 0 and rep["results"]["large"]["all"]["recall"] == 1.0
    assert not rep["frame_check"]["likely_frame_mismatch"]
