"""The road model (detbench/data/road.py): the surface fit on tilted and curved roads, frames without road,
vehicle bodies kept above the margin, determinism, the config, and the drop wiring of every input path."""
import math

import numpy as np
import pytest

from detbench.config import ConfigError
from detbench.data.augment import AugmentConfig, crop_to_range
from detbench.data.frame import Frame, Sensor
from detbench.data.road import RoadConfig, crop_model_input, fit_road, road_mask
from detbench.train.dataset import TrainingSet
from detbench.train.inference import frame_sample

PCR = [0.0, -16.0, -0.6, 153.6, 16.0, 4.2]
CFG = RoadConfig.from_dict({"drop": True})


def ring_ground(surface, height=1.8, az_step_deg=0.375, x_max=150.0, y_max=16.0):
    """Ground returns of the simulator's LiDAR (128 channels over -12.5..12.5 deg, 480 columns over 180 deg)
    at `height` over a road z = surface(x, y): one ring per channel below the horizon, at the range where the
    ray meets a flat road, with z taken from the surface."""
    elev = np.radians(np.linspace(-12.5, 12.5, 128))
    elev = elev[elev < 0]
    r = height / np.tan(-elev)
    az = np.radians(np.arange(-90.0, 90.0, az_step_deg))
    rr, aa = np.meshgrid(r, az, indexing="ij")
    x, y = (rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel()
    keep = (x >= 0) & (x < x_max) & (np.abs(y) <= y_max)
    x, y = x[keep], y[keep]
    return np.stack([x, y, surface(x, y), np.full_like(x, 0.3)], axis=1).astype(np.float32)


def vehicle(surface, cx, cy, length=4.5, width=1.8, clearance=0.3, top=1.5, n=400, seed=0):
    """Points filling a vehicle body from `clearance` to `top` metres above the road under it, and the
    footprint (x0, x1, y0, y1) whose ground it hides."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(cx - length / 2, cx + length / 2, n)
    y = rng.uniform(cy - width / 2, cy + width / 2, n)
    z = surface(x, y) + rng.uniform(clearance, top, n)
    pts = np.stack([x, y, z, np.full_like(x, 0.6)], axis=1).astype(np.float32)
    return pts, (cx - length / 2, cx + length / 2, cy - width / 2, cy + width / 2)


def scene(surface, cars=((15.0, -5.0), (32.0, 3.5), (60.0, -1.5), (95.0, 6.0)), clearance=0.3):
    """Ground rings with vehicles on them (their footprints hide the ground); (points, is_ground, is_car)."""
    ground = ring_ground(surface)
    bodies = []
    for i, (cx, cy) in enumerate(cars):
        pts, (x0, x1, y0, y1) = vehicle(surface, cx, cy, clearance=clearance, seed=i)
        hidden = (ground[:, 0] >= x0) & (ground[:, 0] <= x1) & (ground[:, 1] >= y0) & (ground[:, 1] <= y1)
        ground = ground[~hidden]
        bodies.append(pts)
    cars_pts = np.concatenate(bodies)
    points = np.concatenate([ground, cars_pts])
    return points, np.r_[np.ones(len(ground), bool), np.zeros(len(cars_pts), bool)], \
        np.r_[np.zeros(len(ground), bool), np.ones(len(cars_pts), bool)]


def surface_error(fit, surface, xs=(10.0, 40.0, 80.0, 120.0), ys=(-12.0, 0.0, 12.0)):
    gx, gy = np.meshgrid(np.asarray(xs), np.asarray(ys))
    return float(np.abs(fit.height(gx, gy) - surface(gx, gy)).max())


def tilted(x, y):
    return x * math.tan(math.radians(3.0)) + y * math.tan(math.radians(-2.0))


def curved(x, y):
    # a vertical curve (2.25 m rise at 150 m) under a parabolic crown (0.2 m down at |y| = 16 m)
    return 1e-4 * x * x - 0.2 * (y / 16.0) ** 2


@pytest.mark.parametrize("surface,tol", [(tilted, 0.02), (curved, 0.05)], ids=["tilted", "curved"])
def test_fit_follows_roads_that_are_not_flat(surface, tol):
    points, is_ground, is_car = scene(surface)
    mask, fit = road_mask(points, CFG)
    assert fit.ok
    err = surface_error(fit, surface)
    assert err < tol, f"surface off by {err:.3f} m"
    assert mask[is_ground].mean() > 0.995, f"road points labelled road: {mask[is_ground].mean():.4f}"
    assert not mask[is_car].any(), f"{mask[is_car].sum()} vehicle body points labelled road"


def test_tilted_road_defeats_a_fixed_height_window():
    """The tilted road is metres away from z = 0 far out: a z < margin rule would miss it; the fit does not."""
    points, is_ground, _ = scene(tilted)
    assert (np.abs(points[is_ground, 2]) > 2.0).any()
    mask, _ = road_mask(points, CFG)
    far = is_ground & (points[:, 0] > 80)
    assert mask[far].all()


def test_frame_with_no_road_labels_nothing():
    cars = [vehicle(lambda x, y: np.zeros_like(x), cx, cy, seed=i)[0]
            for i, (cx, cy) in enumerate([(12, -4), (20, 3), (35, 0), (50, -6), (70, 5)])]
    rng = np.random.default_rng(1)
    for c in cars:  # each body at its own height, as vehicles of different clearance
        c[:, 2] += rng.uniform(0.0, 1.0)
    points = np.concatenate(cars)
    mask, fit = road_mask(points, CFG)
    assert not fit.ok and not mask.any()
    assert np.isinf(fit.height(np.array([10.0]), np.array([0.0]))).all()
    empty, fit0 = road_mask(np.zeros((0, 4), np.float32), CFG)
    assert empty.shape == (0,) and not fit0.ok


def test_too_few_points_label_nothing():
    ground = ring_ground(lambda x, y: np.zeros_like(x))[:10]
    mask, fit = road_mask(ground, CFG)
    assert not fit.ok and not mask.any()


@pytest.mark.parametrize("clearance", [0.17, 0.3, 1.0])
def test_points_above_the_margin_are_kept(clearance):
    """A vehicle body from `clearance` up keeps every point; the road under the margin is road."""
    flat = lambda x, y: np.zeros_like(x)  # noqa: E731
    points, is_ground, is_car = scene(flat, clearance=clearance)
    mask, _ = road_mask(points, CFG)
    assert not mask[is_car].any()
    assert mask[is_ground].all()
    assert CFG.margin < 0.17


def test_margin_separates_at_its_height():
    flat = lambda x, y: np.zeros_like(x)  # noqa: E731
    ground = ring_ground(flat)
    probe = np.array([[20.0, 1.0, CFG.margin - 0.02, 0.5], [20.0, 1.5, CFG.margin + 0.02, 0.5]], np.float32)
    mask, _ = road_mask(np.concatenate([ground, probe]), CFG)
    assert mask[-2] and not mask[-1]


def test_output_is_deterministic():
    points, _, _ = scene(curved)
    m1, f1 = road_mask(points, CFG)
    m2, f2 = road_mask(points.copy(), CFG)
    assert np.array_equal(m1, m2) and np.array_equal(f1.coefs, f2.coefs)
    _, f3 = road_mask(points, CFG, seed=5)  # another seed, other samples, the same surface to the millimetre
    assert surface_error(f3, curved) < 0.03


def test_a_band_without_road_borrows_its_neighbour():
    """Road only up to 60 m, a wall of points at 100 m: the far bands take the surface of the last band
    with road (tilted), not a plane through the wall."""
    ground = ring_ground(tilted, x_max=60.0)
    rng = np.random.default_rng(0)
    wx, wy = rng.uniform(100, 101, 300), rng.uniform(-10, 10, 300)
    wall = np.stack([wx, wy, tilted(wx, wy) + rng.uniform(0.5, 3.0, 300), np.full(300, 0.5)], axis=1)
    wall = wall.astype(np.float32)
    fit = fit_road(np.concatenate([ground, wall]), CFG)
    assert fit.own[0] and not fit.own[-1]
    assert abs(float(fit.height(np.array([100.0]), np.array([0.0]))[0]) - tilted(100.0, 0.0)) < 0.3
    mask, _ = road_mask(np.concatenate([ground, wall]), CFG, fit=fit)
    assert not mask[len(ground):].any()


def test_config_is_checked():
    with pytest.raises(ConfigError, match="unknown config key"):
        RoadConfig.from_dict({"drop": True, "margn": 0.1})
    with pytest.raises(ConfigError, match="margin"):
        RoadConfig.from_dict({"margin": 0.0})
    with pytest.raises(ConfigError, match="drop"):
        RoadConfig.from_dict({"drop": "yes"})
    assert RoadConfig.of_run_config({"model": {}}).drop is False  # a config without the section drops nothing
    assert RoadConfig.of_run_config({"road": {"drop": True}}).drop is True


def test_every_model_config_says_its_drop():
    from detbench.train.run_config import load_run_config

    models = ("pointrcnn", "second", "pillarnet", "ct3d")
    # the paper preset follows the published configurations: SECOND keeps the ground
    drops = {m: load_run_config(m, "paper")["road"]["drop"] for m in models}
    assert drops == {"pointrcnn": True, "second": False, "pillarnet": True, "ct3d": True}
    # the cpu preset (and quick, which shares its networks) drops the road for SECOND too
    for preset in ("cpu", "quick"):
        assert all(load_run_config(m, preset)["road"]["drop"] for m in models), preset
    with pytest.raises(ConfigError, match="road.mrgin"):
        load_run_config("second", "quick", overrides=["road.mrgin=0.1"])


def _frame(points, boxes):
    m = len(boxes)
    return Frame(frame_id="000000", scene_id="0000", points=np.asarray(points, np.float32),
                 boxes=np.asarray(boxes, np.float32), classes=np.array(["car"] * m), track_ids=np.arange(m),
                 lanes=np.zeros(m, np.int64), sensor=Sensor(name="t", height=1.8))


def _flat_frame():
    flat = lambda x, y: np.zeros_like(x)  # noqa: E731
    points, is_ground, is_car = scene(flat, cars=((15.0, -5.0), (32.0, 3.5)))
    boxes = np.array([[15.0, -5.0, 0.75, 4.5, 1.8, 1.5, 0.0], [32.0, 3.5, 0.75, 4.5, 1.8, 1.5, 0.0]], np.float32)
    return _frame(points, boxes)


def test_training_sample_with_drop_holds_no_road():
    frame = _flat_frame()
    kept = TrainingSet([frame], PCR, augment=AugmentConfig.none(), road=CFG).get(0, augment=False)
    assert len(kept.points) > 0
    assert (kept.points[:, 2] >= CFG.margin - 0.01).all(), "a point within the margin of the road z = 0 is left"
    assert len(kept.gt_boxes) == 2  # boxes are never dropped for the road
    same = TrainingSet([frame], PCR, augment=AugmentConfig.none(), road=RoadConfig.off()).get(0, augment=False)
    plain, _, _ = crop_to_range(frame.points, frame.boxes, PCR)
    assert np.array_equal(same.points, plain)
    assert np.array_equal(TrainingSet([frame], PCR, augment=AugmentConfig.none()).get(0, augment=False).points, plain)


def test_inference_input_follows_the_same_preparation():
    frame = _flat_frame()
    dropped = frame_sample(frame, PCR, CFG).points
    expected, _, _ = crop_model_input(frame.points, frame.boxes, PCR, CFG)
    assert np.array_equal(dropped, expected) and len(dropped) < len(frame.points) / 2
    assert np.array_equal(frame_sample(frame, PCR).points, crop_to_range(frame.points, frame.boxes, PCR)[0])


def test_evaluation_uses_the_checkpoints_road_setting():
    """checkpoint_predictions (tools/eval.py's path) prepares frames with the road setting stored in the
    checkpoint's config: a model trained without road sees none at evaluation; a config without the
    section (a model trained on every point) sees every point."""
    from detbench.train.inference import checkpoint_predictions
    from tests.helpers import TinyDetector

    class Recording(TinyDetector):
        seen: list

        def forward(self, batch):
            self.seen.append(int(batch.points.shape[0]))
            return super().forward(batch)

    frame = _flat_frame()
    model = Recording()
    counts = {}
    for name, cfg in (("drop", {"model": {"point_cloud_range": PCR}, "road": {"drop": True}}),
                      ("none", {"model": {"point_cloud_range": PCR}})):
        model.seen = []
        preds = checkpoint_predictions(model, {"config": cfg, "model_name": "tiny"}, [frame], progress=False)
        assert list(preds) == [frame.frame_id]
        counts[name] = model.seen[0]
    assert counts["none"] == len(crop_to_range(frame.points, frame.boxes, PCR)[0])
    assert counts["drop"] == len(crop_model_input(frame.points, frame.boxes, PCR, CFG)[0]) < counts["none"] / 2


def test_augmented_samples_lose_exactly_the_road_after_pasting(tmp_path):
    """With ground-truth sampling, flip, rotation and scaling (which keep the road at z = 0), a sample
    with drop true is its drop-false twin (same seed, epoch, index) without the points below the margin:
    the pasted vehicles' copied road goes too, their bodies stay, and no box is dropped."""
    from detbench.data.gt_database import build_gt_database
    from tests.helpers import FRAMES, PC_RANGE

    aug = AugmentConfig.from_dict({"gt_sampling": {"enabled": True, "sample_count": 4, "filter_by_min_points": 5}})
    db = build_gt_database(FRAMES, tmp_path / "db", progress=False)
    on = TrainingSet(FRAMES, PC_RANGE, augment=aug, gt_database=db, seed=3, road=CFG)
    off = TrainingSet(FRAMES, PC_RANGE, augment=aug, gt_database=db, seed=3, road=RoadConfig.off())
    pasted = 0
    for epoch, index in ((0, 0), (1, 3), (2, 5)):
        a, b = on[(epoch, index)], off[(epoch, index)]
        assert np.array_equal(a.gt_boxes, b.gt_boxes)
        pasted += len(b.gt_boxes) - len(off.get(index, epoch, augment=False).gt_boxes)
        assert np.array_equal(a.points, b.points[b.points[:, 2] >= CFG.margin])
        assert (b.points[:, 2] < CFG.margin).sum() > 100  # there was road to drop
    assert pasted > 0


def test_noisy_road_is_still_road():
    """A real LiDAR's range noise (2 cm in z here) on a curved road: the road stays road, bodies stay bodies."""
    points, is_ground, is_car = scene(curved)
    points[is_ground, 2] += np.random.default_rng(4).normal(0.0, 0.02, is_ground.sum()).astype(np.float32)
    mask, fit = road_mask(points, CFG)
    assert surface_error(fit, curved) < 0.05
    assert mask[is_ground].mean() > 0.99, f"road points labelled road: {mask[is_ground].mean():.4f}"
    assert not mask[is_car].any()
