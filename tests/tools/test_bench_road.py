"""tools/bench_road.py: command line and report files; the library part it runs (detbench.benchmarks.road:
the road model's figures against the simulator's truth, z = 0)."""
import json

import numpy as np
import pytest

from detbench.benchmarks.road import active_voxels, road_truth_frame, road_truth_markdown, road_truth_report
from detbench.data.road import RoadConfig
from tools import bench_road as bench

PCR = [0.0, -16.0, -0.6, 153.6, 16.0, 4.2]
VOXEL = [0.1, 0.1, 0.15]


def _flat_scene():
    """Road rings at z = 0 ahead of a 1.8 m LiDAR and two cars (bodies from 0.3 m, wheels from the road)."""
    elev = np.radians(np.linspace(-12.5, 12.5, 128))
    elev = elev[elev < 0]
    az = np.radians(np.arange(-90.0, 90.0, 0.375))
    rr, aa = np.meshgrid(1.8 / np.tan(-elev), az, indexing="ij")
    x, y = (rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel()
    keep = (x >= 0) & (x < 150) & (np.abs(y) <= 16)
    road = np.stack([x[keep], y[keep], np.zeros(keep.sum()), np.full(keep.sum(), 0.3)], axis=1)
    rng = np.random.default_rng(0)
    boxes = np.array([[20.0, -3.0, 0.75, 4.5, 1.8, 1.5, 0.0], [45.0, 4.0, 0.75, 4.5, 1.8, 1.5, 0.0]])
    cars = []
    for b in boxes:
        n = 300
        body = np.stack([rng.uniform(b[0] - 2.2, b[0] + 2.2, n), rng.uniform(b[1] - 0.85, b[1] + 0.85, n),
                         rng.uniform(0.3, 1.45, n), np.full(n, 0.6)], axis=1)
        wheel = np.stack([np.full(20, b[0] + 1.2), np.full(20, b[1] - 0.8), np.linspace(0.01, 0.6, 20),
                          np.full(20, 0.6)], axis=1)
        inside = (np.abs(road[:, 0] - b[0]) < 2.25) & (np.abs(road[:, 1] - b[1]) < 0.9)
        road = road[~inside]
        cars += [body, wheel]
    return np.concatenate([road, *cars]).astype(np.float32), boxes.astype(np.float32)


def test_help_states_units(capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for opt in ("--out", "--preset", "--data", "--heights", "--frames", "--split", "--set"):
        assert opt in text
    assert "metres" in text and "ms" in text


def test_active_voxels_counts_distinct_cells():
    pts = np.array([[0.01, 0.01, 0.0], [0.02, 0.05, 0.1], [0.15, 0.0, 0.0], [0.15, 0.0, 0.2]], np.float32)
    assert active_voxels(pts, VOXEL, [0, 0, 0, 1, 1, 1]) == 3
    assert active_voxels(np.zeros((0, 4), np.float32), VOXEL, PCR) == 0


def test_frame_figures_against_the_flat_truth():
    points, boxes = _flat_scene()
    r = road_truth_frame(points, boxes, RoadConfig.from_dict({}), PCR, VOXEL)
    assert r["fit_ok"] and max(r["height_error_m"]) < 0.01
    assert r["true_road_labelled"] == r["true_road"] > 10000
    # the wheels' lowest 0.15 m are road; the bodies from 0.3 m are not: 2 x 4 of 2 x 320 vehicle points
    assert 0 < r["vehicle_points_labelled"] <= 2 * 5
    assert r["detected_vehicles"] == 2 and r["vehicles_emptied"] == 0
    assert r["points_after"] == r["points_before"] - r["true_road_labelled"] - r["vehicle_points_labelled"] \
        - r["other_points_labelled"]
    assert r["voxels_after"] < r["voxels_before"] / 5


def test_report_and_markdown():
    points, boxes = _flat_scene()

    class F:
        pass

    f = F()
    f.points, f.boxes = points, boxes
    rep = road_truth_report({1.8: [f, f]}, RoadConfig.from_dict({}), PCR, VOXEL)
    s = rep["heights"]["1.8"]
    assert s["frames"] == 2 and s["vehicles_emptied"] == 0 and s["true_road_labelled_share"] == 1.0
    assert s["height_error_m"]["120"]["max"] < 0.01
    md = road_truth_markdown(rep)
    assert "| 1.8 | 0.000 / 0.000 |" in md and "0 / 4" in md


def test_main_writes_reports(tmp_path):
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path / "data"
    simulate_dataset(root, frames=4, heights=[1.0], seed=0, frames_per_scene=2, progress=False)
    out = tmp_path / "out"
    assert bench.main(["--data", str(root), "--frames", "2", "--split", "all", "--out", str(out)]) == 0
    rep = json.loads((out / "bench_road.json").read_text())
    s = rep["heights"]["1"]
    assert s["frames"] == 2 and s["true_road_labelled_share"] > 0.99 and s["vehicles_emptied"] == 0
    assert (out / "bench_road.md").read_text().startswith("# The road model")
