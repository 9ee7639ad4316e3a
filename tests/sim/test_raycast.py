"""Ray-casting geometry of detbench.sim on hand-made scenes (fast)."""
import math

import numpy as np
import pytest

from detbench.sim import LidarConfig, build_parts, cast_lidar, lidar_preset, make_scene
from detbench.sim.vehicles import VehicleCatalog, label_box_local
from detbench.sim.simulator import load_sim_config


def _box_parts(length, width, height, clearance=0.0):
    """A vehicle made of one box from `clearance` to `height` (vehicle frame)."""
    return np.array([[0.0, 0.0, (clearance + height) / 2, length / 2, width / 2, (height - clearance) / 2]])


def _lidar(**kw):
    base = dict(height=1.0, vfov_deg=(-1.0, 1.0), channels=3, hfov_deg=10.0, h_samples=11, max_range=150.0)
    base.update(kw)
    return LidarConfig(**base)


def _sensor_angles(points, lidar):
    """Elevation and azimuth (radians) of points in the sensor frame (pitch undone)."""
    p = points[:, :3].astype(np.float64) - np.array([0.0, 0.0, lidar.height])
    a = math.radians(lidar.pitch_deg)
    c, s = math.cos(a), math.sin(a)
    xs = c * p[:, 0] - s * p[:, 2]
    zs = s * p[:, 0] + c * p[:, 2]
    return np.arctan2(zs, np.hypot(xs, p[:, 1])), np.arctan2(p[:, 1], xs)


def test_single_vehicle_hit_at_analytic_distance():
    lidar = _lidar()
    scene = make_scene([(_box_parts(4.0, 2.0, 1.6), 22.0, 0.0, 0.0)])
    res = cast_lidar(lidar, scene)
    assert res.counts[0] > 0
    # the central ray (azimuth 0, elevation 0) hits the rear face at x = 22 - 2 = 20 m, z = 1.0
    mid = np.flatnonzero((np.abs(res.points[:, 1]) < 1e-6) & (np.abs(res.points[:, 2] - 1.0) < 1e-6))
    assert mid.size == 1
    assert res.points[mid[0], 0] == pytest.approx(20.0, abs=1e-5)
    # every ray lands on the rear face x = 20 at z = h + (horizontal distance) tan(its channel's elevation)
    el, _ = _sensor_angles(res.points, lidar)
    grid = lidar.elevations()
    el_grid = grid[np.abs(el[:, None] - grid[None, :]).argmin(axis=1)]
    face = res.point_box == 0
    assert face.sum() == 3 * 7  # 3 channels x the 7 columns within +-atan(1 / 20)
    np.testing.assert_allclose(res.points[face, 0], 20.0, atol=1e-4)
    horiz = np.hypot(res.points[face, 0], res.points[face, 1])
    np.testing.assert_allclose(res.points[face, 2], 1.0 + horiz * np.tan(el_grid[face]), atol=1e-4)


def test_rotated_vehicle_side_hit_distance():
    # a box turned by 90 degrees shows its 4 m side (along y) at x = 30 - width/2 = 29
    lidar = _lidar()
    scene = make_scene([(_box_parts(4.0, 2.0, 1.6), 30.0, 0.0, math.pi / 2)])
    res = cast_lidar(lidar, scene)
    mid = np.flatnonzero((np.abs(res.points[:, 1]) < 1e-6) & (np.abs(res.points[:, 2] - 1.0) < 1e-6))
    assert res.points[mid[0], 0] == pytest.approx(29.0, abs=1e-5)


def test_points_lie_on_part_faces():
    rng = np.random.default_rng(3)
    vehicles = [(build_parts("sedan", 4.6, 1.8, 1.45, rng), 12.0, 3.5, 0.1),
                (build_parts("truck", 12.0, 2.5, 3.8, rng), 25.0, -3.6, -0.05),
                (build_parts("van", 5.5, 2.0, 2.4, rng), 40.0, 0.3, 0.0)]
    scene = make_scene(vehicles)
    res = cast_lidar(lidar_preset("h3-0.5"), scene)
    for k, (parts, x, y, hd) in enumerate(vehicles):
        pts = res.points[res.point_box == k, :3].astype(np.float64)
        assert len(pts) > 20
        c, s = math.cos(hd), math.sin(hd)
        lx = c * (pts[:, 0] - x) + s * (pts[:, 1] - y)
        ly = -s * (pts[:, 0] - x) + c * (pts[:, 1] - y)
        local = np.stack([lx, ly, pts[:, 2]], axis=1)
        d = np.abs(local[:, None, :] - parts[None, :, :3]) - parts[None, :, 3:]  # (N, P, 3) outside distance
        inside_tol = (d <= 1e-3).all(axis=2)  # within 1 mm of the part
        on_face = inside_tol & (np.abs(d) <= 1e-3).any(axis=2)
        assert on_face.any(axis=1).all(), "a point is not on any part face"
        strictly_inside = (d < -1e-3).all(axis=2)
        assert not strictly_inside.any(), "a point lies inside a part"


def test_downward_beam_hits_ground_at_height_over_tan():
    lidar = LidarConfig(height=1.8, vfov_deg=(-15.0, 10.0), channels=6, hfov_deg=90.0, h_samples=9)
    res = cast_lidar(lidar, make_scene())
    el, _ = _sensor_angles(res.points, lidar)
    low = np.abs(el - math.radians(-15.0)) < 1e-4
    assert low.sum() == lidar.h_samples
    np.testing.assert_allclose(np.hypot(res.points[low, 0], res.points[low, 1]), 1.8 / math.tan(math.radians(15.0)),
                               rtol=1e-5)
    np.testing.assert_allclose(res.points[low, 2], 0.0, atol=1e-5)
    # rays pointing up give nothing on an empty road
    assert (el <= 1e-6).all()


def test_pitch_is_applied():
    lidar = LidarConfig(height=1.8, pitch_deg=2.5, vfov_deg=(-15.0, 10.0), channels=11, hfov_deg=10.0, h_samples=11)
    res = cast_lidar(lidar, make_scene())
    centre = np.abs(res.points[:, 1]) < 1e-6
    ranges = np.sort(res.points[centre, 0])
    # the lowest channel points 17.5 deg down in the ground frame; the level channel (sensor el 0,
    # channel 6 of 11 from -15 by 2.5) points 2.5 deg down and reaches the ground at h / tan(2.5 deg)
    assert ranges[0] == pytest.approx(1.8 / math.tan(math.radians(17.5)), rel=1e-5)
    assert ranges[-1] == pytest.approx(1.8 / math.tan(math.radians(2.5)), rel=1e-5)
    dirs = lidar.ray_directions()
    assert dirs[0, 5, 2] == pytest.approx(-math.sin(math.radians(17.5)), abs=1e-12)
    # points are stored in the ground frame: sensor-frame angles recover the scan grid
    el, _ = _sensor_angles(res.points, lidar)
    grid = lidar.elevations()
    assert np.abs(el[:, None] - grid[None, :]).min(axis=1).max() < 1e-5


def test_nothing_beyond_max_range_or_outside_fov():
    rng = np.random.default_rng(0)
    cat = VehicleCatalog(load_sim_config()["vehicles"])
    vehicles = []
    for _ in range(40):
        shp = cat.sample(rng)
        vehicles.append((shp.parts, float(rng.uniform(-10, 120)), float(rng.uniform(-40, 40)),
                         float(rng.uniform(-math.pi, math.pi))))
    scene = make_scene(vehicles, occluders=[(60.0, 12.0, 0.4, 100.0, 0.3, 0.8, 0.0)])
    for lidar in (lidar_preset("h3-1.8", max_range=60.0, range_noise_m=0.05),
                  lidar_preset("xpeng-g9", max_range=80.0)):
        res = cast_lidar(lidar, scene, key=7)
        rng_ = np.linalg.norm(res.points[:, :3] - np.array([0, 0, lidar.height], np.float32), axis=1)
        assert rng_.max() <= lidar.max_range + 1e-3
        el, az = _sensor_angles(res.points, lidar)
        lo, hi = (math.radians(v) for v in lidar.vfov_deg)
        assert el.min() >= lo - 1e-4 and el.max() <= hi + 1e-4
        assert np.abs(az).max() <= math.radians(lidar.hfov_deg) / 2 + 1e-4
        assert ((res.points[:, 3] >= 0) & (res.points[:, 3] <= 1)).all()


def test_nothing_from_the_ego():
    # a 360 deg LiDAR at the ego's front: rays going backwards hit the ego body and give no point
    lidar = LidarConfig(height=0.5, vfov_deg=(-20.0, 5.0), channels=16, hfov_deg=360.0, h_samples=720)
    L, W, H = 4.6, 1.9, 1.5
    with_ego = cast_lidar(lidar, make_scene(ego=(L, W, H)))
    without = cast_lidar(lidar, make_scene())
    p = with_ego.points
    in_ego = (p[:, 0] <= 0.0) & (p[:, 0] >= -L - 0.1) & (np.abs(p[:, 1]) <= W / 2 + 0.01)
    assert not in_ego.any()
    assert len(with_ego.points) < len(without.points)  # the ego shadows the road behind it


def test_label_boxes_tightly_enclose_the_parts():
    # a world of types (calibration v2): the label box is the parts' tight box grown by the margin
    cfg = load_sim_config("v2")
    cat = VehicleCatalog(cfg["vehicles"])
    m = cat.label_margin
    rng = np.random.default_rng(5)
    for name in cat.names:
        for _ in range(5):
            shp = cat.sample(rng, name)
            lo = (shp.parts[:, :3] - shp.parts[:, 3:]).min(axis=0)
            hi = (shp.parts[:, :3] + shp.parts[:, 3:]).max(axis=0)
            # label: centred footprint, from the road (z = 0) to the roof, grown by the margin
            assert lo[2] == pytest.approx(0.0, abs=1e-12), name  # wheels touch the road
            np.testing.assert_allclose([-lo[0], hi[0]], [shp.length / 2 - m] * 2, atol=1e-9)
            np.testing.assert_allclose([-lo[1], hi[1]], [shp.width / 2 - m] * 2, atol=1e-9)
            assert hi[2] == pytest.approx(shp.height - m, abs=1e-9)
            assert len(shp.parts) > 1
            lb = label_box_local(shp.parts, m)
            np.testing.assert_allclose(lb[3:6], [shp.length, shp.width, shp.height], atol=1e-9)


def test_occlusion_tall_and_low_vehicles():
    rng = np.random.default_rng(1)
    car = build_parts("sedan", 4.5, 1.8, 1.45, rng)
    truck = build_parts("truck", 12.0, 2.5, 3.8, rng)
    low, high = lidar_preset("h3-0.5"), lidar_preset("h3-1.8")
    # a tall vehicle hides a car behind it from 0.5 m (and here from 1.8 m as well)
    behind_truck = make_scene([(truck, 14.0, 0.0, 0.0), (car, 35.0, 0.0, 0.0)])
    assert cast_lidar(low, behind_truck).counts[1] == 0
    assert cast_lidar(high, behind_truck).counts[1] == 0
    # a 1.8 m LiDAR sees a car behind a low car; a 0.5 m LiDAR does not
    behind_car = make_scene([(car, 12.0, 0.0, 0.0), (car, 30.0, 0.0, 0.0)])
    assert cast_lidar(low, behind_car).counts[1] == 0
    assert cast_lidar(high, behind_car).counts[1] > 0
    assert cast_lidar(low, behind_car).counts[0] > 0


def test_culling_matches_brute_force_visibility():
    # with culling the caster must hit exactly what it hits when every object is in every column
    rng = np.random.default_rng(11)
    cat = VehicleCatalog(load_sim_config()["vehicles"])
    vehicles = [(cat.sample(rng).parts, float(rng.uniform(2, 90)), float(rng.uniform(-15, 15)),
                 float(rng.uniform(-0.3, 0.3))) for _ in range(25)]
    scene = make_scene(vehicles)
    lidar = lidar_preset("h3-1.8", channels=32, h_samples=240)
    res = cast_lidar(lidar, scene)
    # brute force in numpy: nearest hit over all parts and the ground for every ray
    dirs = lidar.ray_directions().reshape(-1, 3)
    o = np.array([0.0, 0.0, lidar.height])
    best = np.full(len(dirs), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dirs[:, 2] < 0, lidar.height / -dirs[:, 2], np.inf)
        best = np.minimum(best, tg)
        for parts, x, y, hd in vehicles:
            c, s = math.cos(hd), math.sin(hd)
            ol = np.array([c * (o[0] - x) + s * (o[1] - y), -s * (o[0] - x) + c * (o[1] - y), o[2]])
            dl = np.stack([c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2]], 1)
            for p in parts:
                t1 = (p[:3] - p[3:] - ol) / dl
                t2 = (p[:3] + p[3:] - ol) / dl
                t0 = np.nanmax(np.minimum(t1, t2), axis=1)
                tx = np.nanmin(np.maximum(t1, t2), axis=1)
                hit = (t0 <= tx) & (t0 > 0)
                best = np.where(hit & (t0 < best), t0, best)
    best[best > lidar.max_range] = np.inf
    expected = np.isfinite(best).sum()
    assert len(res.points) == expected
    np.testing.assert_allclose(np.sort(np.linalg.norm(res.points[:, :3] - o, axis=1)),
                               np.sort(best[np.isfinite(best)]), rtol=1e-5, atol=1e-4)
