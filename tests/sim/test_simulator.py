"""HighwaySimulator: determinism, counts, traffic, frames, presets and config errors (fast)."""
import math

import numpy as np
import pytest

from detbench.config import ConfigError
from detbench.data.frame import LANE_OPPOSITE, Frame
from detbench.data.regions import DETECTED_BOTTOM_LIFT
from detbench.sim import HighwaySimulator, LidarConfig, lidar_preset, load_sim_config, sim_presets
from detbench.sim.road import Road, RoadLayout


def _run(cfg, seed, n, lidars, fps=None, with_points=True):
    return list(HighwaySimulator(cfg, seed).run(n, lidars, frames_per_scene=fps, with_points=with_points))


@pytest.fixture(scope="module")
def small_lidars():
    # coarse scans keep the tests fast; noise and drop-off exercise the random streams
    return [lidar_preset(0.5, channels=32, h_samples=180, range_noise_m=0.02, dropout=0.1),
            lidar_preset(1.8, channels=32, h_samples=180, range_noise_m=0.02, dropout=0.1)]


def test_same_seed_identical_bytes_different_seed_differs(small_lidars):
    cfg = load_sim_config()
    a = _run(cfg, 7, 4, small_lidars, fps=2)
    b = _run(cfg, 7, 4, small_lidars, fps=2)
    c = _run(cfg, 8, 4, small_lidars, fps=2)
    for fa, fb in zip(a, b):
        for x, y in zip(fa, fb):
            assert x.points.tobytes() == y.points.tobytes()
            assert x.boxes.tobytes() == y.boxes.tobytes()
            assert list(x.classes) == list(y.classes) and x.track_ids.tobytes() == y.track_ids.tobytes()
            assert x.hit_counts.tobytes() == y.hit_counts.tobytes()
    assert any(x.boxes.shape != y.boxes.shape or not np.array_equal(x.boxes, y.boxes) for x, y in zip(
        [f[0] for f in a], [f[0] for f in c]))


def test_frames_layout(small_lidars):
    cfg = load_sim_config()
    steps = _run(cfg, 1, 5, small_lidars, fps=3)
    assert [s[0].frame_id for s in steps] == ["0000_000", "0000_001", "0000_002", "0001_000", "0001_001"]
    for step in steps:
        assert len(step) == 2
        f0, f1 = step
        assert isinstance(f0, Frame) and f0.frame_id == f1.frame_id and f0.scene_id == f1.scene_id
        np.testing.assert_array_equal(f0.boxes, f1.boxes)  # same traffic at every height
        assert f0.sensor.height == 0.5 and f1.sensor.height == 1.8 and f1.sensor.pitch_deg == 2.5
        f0.check()
        assert f0.boxes.dtype == np.float32 and f0.points.dtype == np.float32
        assert f0.track_ids.dtype == np.int64 and f0.lanes.dtype == np.int64
        # boxes stand on the road: z = dz / 2
        np.testing.assert_allclose(f0.boxes[:, 2], f0.boxes[:, 5] / 2, atol=1e-5)
        assert ((f0.boxes[:, 6] >= -math.pi) & (f0.boxes[:, 6] < math.pi)).all()
        # region: centre x in [-20, 170], |y| <= 25
        assert (f0.boxes[:, 0] >= -20).all() and (f0.boxes[:, 0] <= 170).all()
        assert (np.abs(f0.boxes[:, 1]) <= 25).all()
        assert set(f0.classes) <= {"car", "suv", "taxi", "van", "truck", "bus"}
        assert len(set(f0.track_ids.tolist())) == len(f0.track_ids)
        for key in ("speed_mps", "lane_index", "s_m", "road_curvature_1pm", "lanes_per_direction"):
            assert key in f0.ego
        assert f0.timestamp == pytest.approx(int(f0.frame_id[-3:]) * 0.5)
    # track ids persist between consecutive frames of a scene
    assert set(steps[0][0].track_ids) & set(steps[1][0].track_ids)


def test_hit_counts_equal_points_in_boxes(small_lidars):
    from detbench.ops import points_in_boxes

    # dense traffic, so that the comparison covers many points whatever the calibration
    cfg = load_sim_config("paper", ["traffic.density_per_km_lane=16"])
    lidars = small_lidars + [lidar_preset(1.0)]
    with_pts = _run(cfg, 3, 3, lidars, fps=3)
    no_pts = _run(cfg, 3, 3, lidars, fps=3, with_points=False)
    checked = 0
    for step, step2 in zip(with_pts, no_pts):
        for f, g in zip(step, step2):
            counts, box_index = points_in_boxes(f.points, f.boxes, bottom_lift=DETECTED_BOTTOM_LIFT)
            np.testing.assert_array_equal(counts, f.hit_counts)
            np.testing.assert_array_equal(box_index, f.point_box)
            np.testing.assert_array_equal(g.hit_counts, f.hit_counts)  # with_points=False: same counts
            assert g.points.shape == (0, 4)
            checked += int(counts.sum())
    assert checked > 1000


def test_lift_rule_on_wheels():
    # points on the wheels below 5 cm never count
    from detbench.sim import build_parts, cast_lidar, make_scene

    rng = np.random.default_rng(0)
    car = build_parts("sedan", 4.5, 1.8, 1.45, rng)
    lidar = LidarConfig(height=0.3, vfov_deg=(-10.0, 10.0), channels=200, hfov_deg=20, h_samples=60)
    res = cast_lidar(lidar, make_scene([(car, 8.0, 0.0, 0.0)]), bottom_lift=DETECTED_BOTTOM_LIFT)
    on_car = res.point_box == 0
    assert on_car.any()
    assert (res.points[on_car, 2] >= DETECTED_BOTTOM_LIFT).all()
    near_ground = ((res.points[:, 2] < DETECTED_BOTTOM_LIFT) & (np.abs(res.points[:, 1]) < 0.9)
                   & (res.points[:, 0] > 5.7))
    assert near_ground.any() and (res.point_box[near_ground] == -1).all()


def test_vehicles_never_overlap_over_a_scene():
    from detbench.ops import boxes_iou_bev

    cfg = load_sim_config("dense")
    lid = [LidarConfig(height=1.0, channels=4, h_samples=16)]
    sim = HighwaySimulator(cfg, 2)
    n = 0
    for step in sim.run(120, lid, frames_per_scene=120, with_points=False):
        b = step[0].boxes
        iou = boxes_iou_bev(b, b)
        np.fill_diagonal(iou, 0.0)
        assert iou.max() == 0.0, step[0].frame_id
        n += len(b)
    assert n > 120 * 5


def test_lanes_match_lateral_offsets_on_a_straight_road():
    cfg = load_sim_config("straight", overrides=["traffic.ego_lane_change_every_s=[]",
                                                 "traffic.lane_change.enabled=false",
                                                 "traffic.lateral_jitter_m=0.0",
                                                 "traffic.opposite_density_per_km_lane=12.0"])
    steps = _run(cfg, 4, 6, [LidarConfig(height=1.0, channels=4, h_samples=16)], fps=6, with_points=False)
    seen_opp = seen_own = 0
    for (f,) in steps:
        own = f.lanes != LANE_OPPOSITE
        np.testing.assert_allclose(f.boxes[own, 1], 3.5 * f.lanes[own], atol=0.05)
        np.testing.assert_allclose(np.abs(np.abs(f.boxes[~own, 6]) - math.pi), 0.0, atol=1e-3)
        # opposite lanes lie left of the median: y > (ego lane + 1/2) lane widths + median
        assert (f.boxes[~own, 1] > 3.5 * (f.ego["lane_index"] + 0.5) + 3.0 - 0.05).all()
        seen_opp += int((~own).sum())
        seen_own += int(own.sum())
    assert seen_opp > 0 and seen_own > 0


def test_lane_profile():
    from detbench.sim.traffic import lane_profile

    np.testing.assert_allclose(lane_profile([1.06, 1.02, 0.98, 0.94], 3), [1.06, 1.0, 0.94])
    np.testing.assert_allclose(lane_profile([], 2), [1.0, 1.0])
    np.testing.assert_allclose(lane_profile([2.0], 3), [2.0, 2.0, 2.0])


def test_road_curve_geometry():
    layout = RoadLayout(3, 3.5, 2.0, 1.0)
    radius = 300.0
    road = Road(layout, 0.0, np.full(1001, 1.0 / radius), step=1.0)
    x, y, th, k = road.centre(np.array([0.0, 100.0 * math.pi]))
    # a quarter... of a circle: after s = R * angle the heading equals the angle and the point is on the circle
    assert th[1] == pytest.approx(100.0 * math.pi / radius, rel=1e-9)
    assert math.hypot(x[1] - 0.0, y[1] - radius) == pytest.approx(radius, rel=1e-5)
    wx, wy, _ = road.to_world(np.array([100.0]), np.array([-5.0]))
    cx, cy, cth, _ = road.centre(np.array([100.0]))
    assert math.hypot(wx[0] - cx[0], wy[0] - cy[0]) == pytest.approx(5.0, rel=1e-9)
    with pytest.raises(ValueError, match="outside the generated road"):
        road.centre(np.array([5000.0]))


def test_lidar_presets():
    p18 = lidar_preset("h3-1.8")
    assert (p18.height, p18.pitch_deg, p18.vfov_deg, p18.hfov_deg, p18.channels, p18.h_samples, p18.max_range) == \
        (1.8, 2.5, (-12.5, 12.5), 180.0, 128, 480, 150.0)
    dirs = p18.ray_directions()  # (channels, h_samples, 3) in the ground frame
    ahead = dirs[:, np.argmax(dirs[0, :, 0])]  # the column looking straight ahead
    el = np.degrees(np.arcsin(np.clip(ahead[:, 2], -1, 1)))
    # ahead, relative to the road, the field is Table II's -15..10 deg
    assert el.min() == pytest.approx(-15.0, abs=0.05) and el.max() == pytest.approx(10.0, abs=0.05)
    assert lidar_preset(1.8) == p18 and lidar_preset("1.0") == lidar_preset("h3-1.0")
    p07 = lidar_preset(0.7)
    assert p07.height == 0.7 and p07.vfov_deg == (-12.5, 12.5) and p07.pitch_deg == 0.0 and p07.name == "h3-0.7"
    l8 = lidar_preset("Leading Ideal L8")
    assert (l8.hfov_deg, l8.max_range, l8.h_samples, l8.channels, l8.height) == (120.0, 200.0, 1200, 125, 1.8)
    assert lidar_preset("neta-s").channels == 96 and lidar_preset("AVATR 3").height == 0.4
    assert lidar_preset("h3-0.5").sensor.to_dict()["vfov_deg"] == [-12.5, 12.5]
    with pytest.raises(ValueError, match="unknown LiDAR preset"):
        lidar_preset("velodyne-hdl64")
    with pytest.raises(ValueError, match="height"):
        lidar_preset(-1.0)
    with pytest.raises(ValueError, match="dropout"):
        lidar_preset(1.0, dropout=1.5)


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="density_per_km_lane"):
        load_sim_config("paper", ["traffic.density_per_km_lan=3"])
    with pytest.raises(ConfigError, match="lanes_per_direction"):
        load_sim_config("paper", ["road.lanes_per_direction=0"])
    with pytest.raises(ConfigError, match="unknown simulator preset"):
        load_sim_config("nope")
    with pytest.raises(ConfigError, match="ego_lane_weights"):
        load_sim_config("paper", ["traffic.ego_lane_weights=[1, -1]"])
    load_sim_config("paper", ["road.lanes_per_direction=3"])  # per-lane lists are resampled
    cfg = load_sim_config()
    cfg["traffic"]["bogus"] = 1
    with pytest.raises(ConfigError, match="bogus"):
        HighwaySimulator(cfg, 0)
    assert "paper" in sim_presets()
    for name in sim_presets():
        load_sim_config(name)


def test_run_arguments_checked():
    sim = HighwaySimulator(load_sim_config(), 0)
    with pytest.raises(ValueError, match="LidarConfig"):
        next(sim.run(1, [1.0]))
    with pytest.raises(ValueError, match="frames_per_scene"):
        next(sim.run(1, [lidar_preset(1.0)], frames_per_scene=0))
    assert list(sim.run(0, [lidar_preset(1.0)])) == []


def test_type_deck_holds_the_mix_in_proportion():
    from detbench.sim.vehicles import TypeDeck

    names = ["car", "van", "truck", "bus"]
    probs = np.array([0.5, 0.2, 0.25, 0.05])
    deck = TypeDeck(names, probs, 20, np.random.default_rng(0))
    draws = [deck.draw() for _ in range(20 * 500)]
    # every deck of 20 holds floor or ceil of 20 p cards of each type ...
    for k in range(0, len(draws), 20):
        chunk = draws[k:k + 20]
        for name, p in zip(names, probs):
            assert math.floor(20 * p) <= chunk.count(name) <= math.ceil(20 * p)
    # ... and over many decks each type keeps its probability (the bus, 1 card per deck on average)
    for name, p in zip(names, probs):
        assert abs(draws.count(name) / len(draws) - p) < 0.01
    # within a deck the order is shuffled
    assert draws[:20] != sorted(draws[:20])


def test_each_lane_ring_holds_its_share_of_vehicles():
    from detbench.sim.traffic import Traffic
    from detbench.sim.vehicles import VehicleCatalog

    cfg = load_sim_config("paper", ["traffic.density_per_km_lane=10.0", "traffic.opposite_density_per_km_lane=4.0"])
    t = cfg["traffic"]
    layout = HighwaySimulator(cfg, 0).layout
    ring = float(t["window_behind_m"]) + float(t["window_ahead_m"])
    counts_own, counts_opp = [], []
    for seed in range(12):
        tr = Traffic(t, layout, VehicleCatalog(cfg["vehicles"]), np.random.default_rng(seed))
        for cw, per_km, out in ((tr.own, 10.0, counts_own), (tr.opp, 4.0, counts_opp)):
            for lane in range(layout.lanes_per_direction):
                n = int((cw.lane == lane).sum())
                # exactly floor or ceil of density x ring (the ego counts in its lane)
                assert math.floor(per_km * ring / 1000) <= n <= math.ceil(per_km * ring / 1000)
                out.append(n)
        # the ring is filled without overlaps: sorted positions in each lane are a vehicle length + gap apart
        for cw in (tr.own, tr.opp):
            for lane in range(layout.lanes_per_direction):
                idx = np.flatnonzero(cw.lane == lane)
                order = idx[np.argsort(cw.x[idx])]
                x, L = cw.x[order], cw._len[order]
                gaps = np.diff(x) - 0.5 * (L[1:] + L[:-1])
                closure = x[0] + ring - x[-1] - 0.5 * (L[0] + L[-1])
                assert gaps.min() >= tr.idm.min_gap_hard and closure >= tr.idm.min_gap_hard
    assert abs(np.mean(counts_own) - 10.0 * ring / 1000) < 0.5
    assert abs(np.mean(counts_opp) - 4.0 * ring / 1000) < 0.5


def test_ego_never_stalls_for_a_whole_scene():
    # the ego changes lanes within a scene even when no neighbouring lane has traffic close ahead
    cfg = load_sim_config("sparse", ["traffic.ego_lane_change_every_s=[5,10]"])
    lid = [LidarConfig(height=1.0, channels=4, h_samples=16)]
    lanes = [step[0].ego["lane_index"] for step in HighwaySimulator(cfg, 3).run(120, lid, frames_per_scene=120,
                                                                                   with_points=False)]
    assert len(set(lanes)) >= 2


def test_an_overfull_lane_ring_drops_vehicles_instead_of_overlapping():
    from detbench.sim.traffic import Traffic
    from detbench.sim.vehicles import VehicleCatalog

    cfg = load_sim_config("paper", ["traffic.density_per_km_lane=150.0", "traffic.opposite_density_per_km_lane=150.0",
                                    "vehicles.spawn_classes=[truck, bus]"])
    t = cfg["traffic"]
    ring = float(t["window_behind_m"]) + float(t["window_ahead_m"])
    tr = Traffic(t, HighwaySimulator(cfg, 0).layout, VehicleCatalog(cfg["vehicles"]), np.random.default_rng(0))
    for cw in (tr.own, tr.opp):
        for lane in range(cw.n_lanes):
            idx = np.flatnonzero(cw.lane == lane)
            assert 0 < idx.size < 150 * ring / 1000  # 150/km of 5-10 m trucks and buses cannot fit
            order = idx[np.argsort(cw.x[idx])]
            x, L = cw.x[order], cw._len[order]
            gaps = np.diff(x) - 0.5 * (L[1:] + L[:-1])
            closure = x[0] + ring - x[-1] - 0.5 * (L[0] + L[-1])
            assert gaps.min() >= tr.idm.min_gap_hard - 1e-9 and closure >= tr.idm.min_gap_hard - 1e-9


def test_ego_spawned_in_a_queue_starts_at_its_own_headway():
    # ego_in_platoon: the ego follows the vehicle ahead like any vehicle; at follow_fraction 0.95 it nearly always
    # does, at its own headway gap (min_gap + v T, not a platoon gap), and the ring still closes (one free gap)
    from detbench.sim.traffic import Traffic, _leader
    from detbench.sim.vehicles import VehicleCatalog

    cfg = load_sim_config("paper", ["traffic.platoon.ego_in_platoon=true", "traffic.platoon.follow_fraction=0.95",
                                    "traffic.ego_time_headway_s=[0.6,0.6]", "traffic.density_per_km_lane=10.0"])
    t = cfg["traffic"]
    layout = HighwaySimulator(cfg, 0).layout
    ring = float(t["window_behind_m"]) + float(t["window_ahead_m"])
    close = 0
    for seed in range(10):
        tr = Traffic(t, layout, VehicleCatalog(cfg["vehicles"]), np.random.default_rng(seed))
        own = tr.own
        j, d = _leader(0, own.lane[0], own.x, own.lane, own.lane_from, 1, tr.ring)
        gap = d - 0.5 * (own._len[0] + own._len[j])
        want = tr.idm.min_gap + own.v0[0] * tr.lane_factor[own.lane[0]] * 0.6
        assert gap >= want - 1e-6
        close += gap < want + 1.0
        idx = np.flatnonzero(own.lane == own.lane[0])  # the ego's lane ring holds its share and no overlap
        order = idx[np.argsort(own.x[idx])]
        x, L = own.x[order], own._len[order]
        assert (np.diff(x) - 0.5 * (L[1:] + L[:-1])).min() >= tr.idm.min_gap_hard
        assert x[0] + ring - x[-1] - 0.5 * (L[0] + L[-1]) >= tr.idm.min_gap_hard
    assert close >= 8  # it followed (at exactly its headway gap) in nearly every scene
    # without it the ego heads a queue: the vehicle ahead is at a free gap (far more than the headway)
    cfg = load_sim_config("paper", ["traffic.platoon.ego_in_platoon=false", "traffic.platoon.follow_fraction=0.95"])
    far = 0
    for seed in range(10):
        tr = Traffic(cfg["traffic"], layout, VehicleCatalog(cfg["vehicles"]), np.random.default_rng(seed))
        own = tr.own
        j, d = _leader(0, own.lane[0], own.x, own.lane, own.lane_from, 1, tr.ring)
        far += d > 40.0
    assert far >= 8


def _digest_lines(frames_per_instant) -> str:
    import hashlib

    lines = []
    for frames in frames_per_instant:
        for f in frames:
            h = hashlib.sha256()
            for a in (f.points, f.boxes, f.hit_counts, f.point_box, f.track_ids, f.lanes):
                h.update(np.ascontiguousarray(a).tobytes())
            lines.append(f"{f.frame_id} {f.sensor.height:g} {len(f.points)} {h.hexdigest()}")
    return "\n".join(lines) + "\n"


def test_default_simulation_output_is_pinned():
    # the paper's three sensors on the default preset, full clouds and counts: every byte is pinned, so a change
    # of the sensor model (poses, rigs, the ego's body) that touches the single-sensor path fails here
    from tests.helpers import assert_golden

    lidars = [lidar_preset(h) for h in (0.5, 1.0, 1.8)]
    assert_golden("sim_default_digest.txt", _digest_lines(_run(load_sim_config(), 0, 4, lidars, fps=2)))
