"""The height sweep (detbench.studies.sweep, tools/sweep.py) and the placement scores (detbench.studies.placement)."""
import json
import math

import numpy as np
import pytest

from detbench.data.frame import Frame, Sensor
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies.ability import stacked_masks
from detbench.studies.placement import (
    OccupancyGrid, VoxelGrid, binary_entropy_bits, evidence, evidence_sums, importance_weights, ray_coverage,
    scores_from_sums, smig,
)
from detbench.studies.sweep import HeightSweep
import tools.sweep


# ---------------------------------------------------------------------------- placement scores
def test_importance_weights_and_evidence_sums():
    # ego lane: cars at 10 m and 30 m and 60 m; a car two lanes left at 20 m; one at 120 m in the ego lane
    boxes = np.array([[10, 0, 0.8, 4.5, 1.8, 1.5, 0], [30, 0, 0.8, 4.5, 1.8, 1.5, 0], [60, 0, 0.8, 4.5, 1.8, 1.5, 0],
                      [20, 7, 0.8, 4.5, 1.8, 1.5, 0], [120, 0, 0.8, 4.5, 1.8, 1.5, 0]], dtype=np.float32)
    lanes = np.array([0, 0, 0, 2, 0])
    w = importance_weights(stacked_masks(boxes, lanes))
    # small (x <= 50, |y| <= 5): 10 m top3 (3), 30 m top6 (2); moderate adds 60 m (1) and the 20 m car at y 7 (1)
    np.testing.assert_array_equal(w[0], [3, 2, 0, 0, 0])
    np.testing.assert_array_equal(w[1], [3, 2, 1, 1, 0])
    np.testing.assert_array_equal(w[2], [3, 2, 1, 1, 1])
    counts = np.array([100, 10, 0, 3, 0])
    s = evidence_sums(w, counts, scale=10.0)
    q = 1 - np.exp(-counts / 10.0)
    # rows w_all, w_detected, w q(n), w n over detected; large range (every car inside)
    np.testing.assert_allclose(s[:, 2], [8, 6, 3 * q[0] + 2 * q[1] + q[3], 3 * 100 + 2 * 10 + 3])
    sc = scores_from_sums(s)
    assert sc["ldr_w"][2] == pytest.approx(6 / 8)
    assert sc["evidence"][2] == pytest.approx((3 * q[0] + 2 * q[1] + q[3]) / 6)
    assert sc["evidence_all"][2] == pytest.approx((3 * q[0] + 2 * q[1] + q[3]) / 8)
    assert sc["points"][2] == pytest.approx(323 / 6)
    assert evidence([0])[0] == 0 and evidence([10], 10)[0] == pytest.approx(1 - math.exp(-1))
    empty = scores_from_sums(np.zeros((4, 3)))
    assert all(np.isnan(v).all() for v in empty.values())


def test_occupancy_grid_counts_each_voxel_once_per_frame():
    g = VoxelGrid()
    pog = OccupancyGrid(g)
    box = np.array([[10.0, 0.0, 0.75, 4.0, 2.0, 1.5, 0.0]])
    pog.add(np.concatenate([box, box]))  # the same box twice in one frame counts once
    pog.add(np.zeros((0, 7)))
    pog.add(np.array([[200.0, 0.0, 1.0, 4.0, 2.0, 2.0, 0.0]]))  # outside the grid
    p = pog.probabilities()
    assert pog.frames == 3
    assert int((p > 0).sum()) == 8 * 4 * 3  # 4 x 2 x 1.5 m at 0.5 m voxels
    assert p.max() == pytest.approx(1 / 3)
    # turned 90 degrees: the same number of voxel centres, now 4 along y
    pog2 = OccupancyGrid(g)
    pog2.add(np.array([[10.0, 0.0, 0.75, 4.0, 2.0, 1.5, math.pi / 2]]))
    occ = np.argwhere(pog2.counts > 0)
    assert len(occ) == 96 and np.ptp(occ[:, 1]) + 1 == 8 and np.ptp(occ[:, 0]) + 1 == 4


def test_ray_coverage_geometry():
    g = VoxelGrid()
    # a level ray at 1.25 m along +x covers one voxel row from x = 0 to the end of the grid
    cov = ray_coverage(np.array([[1.0, 0.0, 0.0]]), 1.25, 150.0, g)
    idx = np.argwhere(cov)
    assert len(idx) == 300 and set(idx[:, 2]) == {2} and set(idx[:, 1]) == {30}
    # ... 60 m of range stops it after 120 voxels; pointing backwards it never enters the grid
    assert ray_coverage(np.array([[1.0, 0.0, 0.0]]), 1.25, 60.0, g).sum() == 120
    assert ray_coverage(np.array([[-1.0, 0.0, 0.0]]), 1.25, 150.0, g).sum() == 0
    # a ray 12.5 deg down meets the road h / tan(12.5 deg) ahead: the last covered voxel moves out with height
    a = math.radians(12.5)
    d = np.array([[math.cos(a), 0.0, -math.sin(a)]])
    for h in (0.5, 1.0, 1.8):
        last = np.argwhere(ray_coverage(d, h, 150.0, g))[:, 0].max()
        assert last == int(h / math.tan(a) / 0.5)
    with pytest.raises(ValueError, match="height"):
        ray_coverage(d, 0.0, 150.0, g)


def test_smig_is_the_entropy_of_the_covered_voxels():
    assert binary_entropy_bits(np.array([0.0, 0.5, 1.0]))[1] == pytest.approx(1.0)
    p = np.zeros((4, 2, 2))
    p[0, 0, 0] = 0.5
    p[1, 0, 0] = 0.5
    p[2, 1, 1] = 0.1
    covered = np.zeros(p.shape, bool)
    covered[0, 0, 0] = covered[2, 1, 1] = True
    h01 = -(0.1 * math.log2(0.1) + 0.9 * math.log2(0.9))
    out = smig(p, covered)
    assert out["bits"] == pytest.approx(1 + h01) and out["total_bits"] == pytest.approx(2 + h01)
    region = np.zeros(p.shape, bool)
    region[:2] = True
    assert smig(p, covered, region)["fraction"] == pytest.approx(0.5)


# ---------------------------------------------------------------------------- the accumulator
def _frame(height, boxes, scene="0000", fid="0000_000"):
    return Frame(frame_id=fid, scene_id=scene, points=np.zeros((0, 4), np.float32),
                 boxes=np.asarray(boxes, np.float32), classes=np.array(["car"] * len(boxes)),
                 track_ids=np.arange(len(boxes)), lanes=np.zeros(len(boxes), np.int64), sensor=Sensor(height=height))


def test_sweep_refuses_frames_of_other_traffic_or_equal_heights():
    sweep = HeightSweep(bootstrap=0)
    b = [[10, 0, 0.8, 4.5, 1.8, 1.5, 0]]
    with pytest.raises(ValueError, match="does not share the traffic"):
        sweep.add([_frame(0.5, b), _frame(1.0, [[12, 0, 0.8, 4.5, 1.8, 1.5, 0]])], counts=[[1], [1]])
    with pytest.raises(ValueError, match="heights must differ"):
        sweep.add([_frame(0.5, b), _frame(0.5, b)], counts=[[1], [1]])


def test_sweep_accumulates_counts_scores_and_intervals():
    sweep = HeightSweep(bootstrap=300)
    b = [[10, 0, 0.8, 4.5, 1.8, 1.5, 0], [40, 0, 0.8, 4.5, 1.8, 1.5, 0]]
    for s in range(4):  # four scenes: the low LiDAR sees the far car only in scenes 0 and 1
        fid = f"{s:04d}_000"
        far_low = 5 if s < 2 else 0
        sweep.add([_frame(0.5, b, f"{s:04d}", fid), _frame(1.8, b, f"{s:04d}", fid)],
                  counts=[[200, far_low], [150, 30]])
    rep = sweep.report()
    ab = rep["ability"]["heights"]
    assert rep["heights"] == ["0.5", "1.8"] and rep["num_scenes"] == 4 and rep["same_traffic"]
    assert ab["0.5"]["small"]["all"] == {"total": 8, "detected": 6, "ldr": 0.75}
    assert ab["1.8"]["small"]["all"]["ldr"] == 1.0
    assert rep["best_height"]["small"]["all"]["height"] == "1.8"
    ev = rep["scores"]["heights"]
    # 0.5 m: weights 3 (near) and 2 (far, top6); detected far car only twice
    q = lambda n: 1 - math.exp(-n / 10)  # noqa: E731
    want = (4 * 3 * q(200) + 2 * 2 * q(5)) / (4 * 3 + 2 * 2)
    assert ev["0.5"]["small"]["evidence"]["value"] == pytest.approx(want, abs=1e-6)
    assert ev["0.5"]["small"]["ldr_w"]["value"] == pytest.approx(16 / 20)
    lo, hi = ev["0.5"]["small"]["ldr_w"]["ci95"]
    assert lo <= 0.8 <= hi and lo < hi  # scenes differ at 0.5 m
    assert ev["1.8"]["small"]["ldr_w"]["ci95"] == [1.0, 1.0]  # every scene the same
    assert "smig" not in ev["0.5"]["small"]  # no coverage given
    d = rep["ldr_vs_distance"]["heights"]["0.5"]
    assert d["total"][1] == 4 and d["detected"][4] == 2 and d["ldr"][4] == 0.5


# ---------------------------------------------------------------------------- the tool, tiny runs
def _run(tmp_path, *extra, name="out"):
    tool = tools.sweep
    out = tmp_path / name
    assert tool.main(["--frames", "24", "--frames-per-scene", "4", "--seed", "0", "--sim-preset", "dense",
                      "--bootstrap", "200", "--no-progress", "--out", str(out), *extra]) == 0
    return json.loads((out / "sweep.json").read_text()), out


def test_sweep_tool_tiny_run_structure_and_physics(tmp_path):
    rep, out = _run(tmp_path, "--heights", "0.5", "1.0", "2.2")
    for f in ("sweep.md", "ldr_vs_height.png", "scores_vs_height.png", "ldr_distance_map.png"):
        assert (out / f).stat().st_size > 0
    assert rep["heights"] == ["0.5", "1.0", "2.2"] and rep["num_frames"] == 24 and rep["num_scenes"] == 6
    ab, unc = rep["ability"]["heights"], rep["ability"]["extras"]["uncertainty"]["heights"]
    assert rep["same_traffic"]
    assert list(rep["ability"]["extras"]["uncertainty"]["differences"]) == ["1.0-0.5", "2.2-1.0"]  # adjacent pairs
    for r in RANGE_NAMES:
        for lv in LEVELS:
            assert len({ab[h][r][lv]["total"] for h in rep["heights"]}) == 1  # the same vehicles at every height
            for h in rep["heights"]:
                c = ab[h][r][lv]
                assert 0 <= c["detected"] <= c["total"] and 0.0 <= c["ldr"] <= 1.0
                lo, hi = unc[h][r][lv]["ci95"]
                assert 0.0 <= lo <= c["ldr"] <= hi <= 1.0
        for h in rep["heights"]:
            cell = rep["scores"]["heights"][h][r]
            for s in ("evidence", "evidence_all", "ldr_w"):
                v, (lo, hi) = cell[s]["value"], cell[s]["ci95"]
                assert 0.0 <= lo <= v <= hi <= 1.0
            assert cell["evidence_all"]["value"] <= cell["evidence"]["value"]
            assert 0 < cell["smig"]["value"] and 0 < cell["smig"]["fraction"] <= 1
    # the tall LiDAR sees over the vehicles ahead: in dense traffic it hits far more vehicles than at 0.5 m
    # (0.91 against 0.76 in the large range on these 24 frames; 12 frames gave only 0.84 against 0.80)
    assert ab["2.2"]["large"]["all"]["ldr"] > ab["0.5"]["large"]["all"]["ldr"] + 0.1
    # every figure title names the world it was measured in (the dense preset is the default calibration v3's world)
    from detbench.studies.sweep_plots import _world
    assert _world(rep) == "simulator calibration v3"
    assert _world({"ability": {"extras": {"source": {"kind": "dataset", "root": "/data"}}}}) == "data on disk"
    md = (out / "sweep.md").read_text()
    assert "the paper's Table IV, heights as rows" in md and "| 2.2 |" in md and "S-MIG" not in md.split("##")[0]
    # a height's counts do not depend on which other heights were swept with it
    alone, _ = _run(tmp_path, "--heights", "0.5", "--no-figures", "--no-smig", name="alone")
    assert alone["ability"]["heights"]["0.5"] == ab["0.5"]
    assert "smig" not in alone["scores"]["heights"]["0.5"]["large"]


def test_sweep_tool_sensor_settings_and_errors(tmp_path):
    rep, _ = _run(tmp_path, "--heights", "1.0", "1.8", "--lidar", "paper", "--set", "sensor.channels=32",
                  "--no-figures")
    fields = rep["ability"]["extras"]["source"]["sensor"]
    assert fields["preset"] == "paper" and fields["changes"] == {"channels": 32}
    assert fields["per_height"] == {"1.0": "h3-1.0", "1.8": "h3-1.8"}
    tool = tools.sweep
    with pytest.raises(SystemExit, match="did you mean sensor.channels"):
        tool.main(["--frames", "2", "--set", "sensor.chanels=3", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="what the sweep varies"):
        tool.main(["--frames", "2", "--set", "sensor.height=3", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="given twice"):
        tool.main(["--frames", "2", "--heights", "1.0", "1.0001", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="unknown LiDAR preset"):
        tool.main(["--frames", "2", "--lidar", "velodyne", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="density_per_km_lane"):
        tool.main(["--frames", "2", "--set", "traffic.density_per_km_lan=3", "--out", str(tmp_path / "x")])
    notsweep = tmp_path / "n.json"
    notsweep.write_text("{}")
    with pytest.raises(SystemExit, match="not a height-sweep report"):
        tool.main(["--from-json", str(notsweep), "--out", str(tmp_path / "x")])


def test_sweep_tool_correlates_from_json(tmp_path):
    rep, out = _run(tmp_path, "--heights", "0.5", "1.0", "1.5", "2.2", "--no-figures")
    paths = []
    for h in rep["heights"]:  # a "detector" whose recall is the large-range weighted LDR of the sweep
        v = rep["scores"]["heights"][h]["large"]["ldr_w"]["value"]
        cell = {"total": 10, "lidar_detected": 8, "ldr": 0.8, "tp": 1, "fp": 0, "recall": v, "ap_r40": v}
        p = tmp_path / f"r{h}.json"
        p.write_text(json.dumps({"model": "fake", "height": float(h), "iou_threshold": 0.7, "score_threshold": 0.1,
                                 "num_frames": 3, "results": {r: {lv: cell for lv in LEVELS} for r in RANGE_NAMES}}))
        paths.append(str(p))
    tool = tools.sweep
    assert tool.main(["--from-json", str(out / "sweep.json"), "--out", str(out), "--no-figures",
                      "--detector-reports", *paths, "--correlation-replicates", "200"]) == 0
    corr = json.loads((out / "sweep.json").read_text())["correlation"]
    rows = [r for r in corr["rows"] if r["score"] == "ldr_w" and r["range_name"] == "large"]
    assert rows and all(r["spearman"] == 1.0 and r["n"] == 4 for r in rows)
    assert "Placement score against trained detectors" in (out / "sweep.md").read_text()
