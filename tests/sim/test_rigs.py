"""Rigs: the rig file, sensor poses, merged clouds, the ego's body and the self-filter (fast)."""
import dataclasses
import math

import numpy as np
import pytest

from detbench.config import ConfigError
from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config
from detbench.sim.raycast import cast_lidar
from detbench.sim.scene_objects import make_scene
from detbench.sim.rig_cast import cast_rig
from detbench.sim.rigs import RIGS_CONFIG, Rig, RigSensor, load_rigs, parse_rigs


@pytest.fixture(scope="module")
def rigs():
    return load_rigs()


def test_shipped_rigs_and_their_poses(rigs):
    assert {"paper-0.5", "paper-1.0", "paper-1.8", "forehead", "headlights", "plate", "roof-360"} <= set(rigs)
    for h in ("0.5", "1.0", "1.8"):
        r = rigs[f"paper-{h}"]
        assert r.is_single_reference and r.sensors[0].lidar == lidar_preset(float(h))
    head = rigs["headlights"]
    assert len(head.sensors) == 2 and head.ego_body
    # two 120-degree units yawed outward cover 180 degrees together
    spans = [(s.yaw_deg - s.lidar.hfov_deg / 2, s.yaw_deg + s.lidar.hfov_deg / 2) for s in head.sensors]
    assert min(a for a, _ in spans) == -90 and max(b for _, b in spans) == 90
    assert rigs["roof-360"].sensors[0].lidar.hfov_deg == 360


def test_rig_file_errors_name_file_and_key(tmp_path):
    good = {"rigs": {"mine": {"sensors": [{"preset": "h3-1.0", "z": 0.7}]}}}
    assert parse_rigs(good, tmp_path / "r.yaml")["mine"].sensors[0].lidar.height == 0.7
    with pytest.raises(ConfigError, match=r"r.yaml: rigs.mine.sensors\[0\].colour: unknown key"):
        parse_rigs({"rigs": {"mine": {"sensors": [{"preset": "h3-1.0", "colour": 1}]}}}, tmp_path / "r.yaml")
    with pytest.raises(ConfigError, match=r"r.yaml: rigs.mine.wheels: unknown key"):
        parse_rigs({"rigs": {"mine": {"wheels": 4, "sensors": [{"preset": "h3-1.0"}]}}}, tmp_path / "r.yaml")
    body = load_rigs()["forehead"].body
    inside = {"body": dataclasses.asdict(body),
              "rigs": {"sunk": {"ego_body": True, "sensors": [{"name": "grille", "preset": "h3-1.0", "x": -0.5,
                                                               "z": 0.5}]}}}
    with pytest.raises(ConfigError, match="rigs.sunk: sensor 'grille' .* inside the ego's hood"):
        parse_rigs(inside, tmp_path / "r.yaml")
    # a user's rig file with the shipped keys loads like configs/rigs.yaml
    user = tmp_path / "user.yaml"
    user.write_text(RIGS_CONFIG.read_text())
    assert load_rigs(user) == load_rigs()


def _frames(entries, n=2):
    return list(HighwaySimulator(load_sim_config(), 0).run(n, entries, frames_per_scene=2))


def test_paper_rig_is_the_single_sensor(rigs):
    lidar = lidar_preset(1.8)
    for a, b in _frames([lidar, rigs["paper-1.8"]]):
        assert a.points.tobytes() == b.points.tobytes() and a.hit_counts.tobytes() == b.hit_counts.tobytes()
        assert b.rig == "paper-1.8" and np.all(b.sensor_index == 0)


def test_merged_cloud_keeps_sensor_index_and_counts(rigs):
    for (f,) in _frames([rigs["headlights"]]):
        assert f.sensor_index.shape == (len(f.points),) and set(np.unique(f.sensor_index)) == {0, 1}
        # counts are the merged points inside each box
        assert np.array_equal(np.bincount(f.point_box[f.point_box >= 0], minlength=len(f.boxes)), f.hit_counts)
        # the left unit sees mostly the left side, the right unit the right side
        left, right = f.points[f.sensor_index == 0], f.points[f.sensor_index == 1]
        assert np.mean(left[:, 1] > 0) > 0.6 and np.mean(right[:, 1] < 0) > 0.6


def test_pose_moves_and_turns_the_sensor():
    # a wall ahead; a sensor at (x, y) yawed by 90 degrees to the left sees it only if the transform is right
    wall = make_scene(occluders=[(0.0, 10.0, 1.0, 20.0, 0.2, 2.0, 0.0)])  # along x at y = 10
    base = lidar_preset(1.0, hfov_deg=20.0, h_samples=21, channels=3, vfov_deg=(-1.0, 1.0))
    s = RigSensor("side", base, x=2.0, y=1.0, yaw_deg=90.0)
    rc = cast_rig(Rig("one", (s,)), wall, [0])
    assert len(rc.points) == 63
    assert np.allclose(rc.points[:, 1], 9.9, atol=1e-4)  # the wall's near face
    assert np.all(np.abs(rc.points[:, 0] - 2.0) <= 9.0 * math.tan(math.radians(10.0)) + 1e-3)
    # roll turns the scan: rolled by 90 degrees, the fan of columns stands vertical
    rolled = cast_rig(Rig("r", (RigSensor("r", base, yaw_deg=90.0, roll_deg=90.0),)), wall, [0])
    assert np.ptp(rolled.points[:, 2]) > 2.0 * np.ptp(rc.points[:, 2]) + 0.5


def test_body_occludes_and_self_filter_counts(rigs):
    road = make_scene()
    ws = rigs["windshield-1.0"]
    on = cast_rig(ws, road, [0])
    off = cast_rig(dataclasses.replace(ws, ego_body=False), road, [0])
    assert on.self_hits[0] > 0 and off.self_hits[0] == 0
    assert len(on.points) + on.self_hits[0] <= len(off.points) + 1  # the body takes rays, returns nothing
    kept = cast_rig(dataclasses.replace(ws, self_filter=False), road, [0])
    assert len(kept.points) == len(on.points) + on.self_hits[0]  # without the filter the body's returns stay
    plate = cast_rig(rigs["plate"], road, [0])
    assert plate.self_hits[0] == 0


def test_bumper_sensor_loses_no_vehicle_to_the_body(rigs):
    plate = rigs["plate"]
    bare = dataclasses.replace(plate, ego_body=False)
    for a, b in _frames([plate, bare], n=4):
        assert np.array_equal(a.hit_counts, b.hit_counts)


def test_single_sensor_cast_unchanged_by_keep_ego_default():
    scene = make_scene(ego=(4.8, 1.9, 1.5))
    lidar = lidar_preset(1.0, channels=8, h_samples=60)
    a, b = cast_lidar(lidar, scene), cast_lidar(lidar, scene, keep_ego=False, roll_deg=0.0)
    assert a.points.tobytes() == b.points.tobytes()
