"""Augmentation and ground-truth sampling: invariants on synthetic frames built here."""
import json
import math

import numpy as np
import pytest

from detbench.config import ConfigError
from detbench.data.augment import (
    AUGMENT_DEFAULTS, AugmentConfig, augment_frame, crop_to_range, flip_x, rotate_z, scale_world,
)
from detbench.data.frame import Frame, Sensor
from detbench.data.gt_database import (
    INDEX_FILE, GTSampler, GTSamplingConfig, build_gt_database, build_or_load_gt_database, load_gt_database,
)
from detbench.data.regions import DETECTED_BOTTOM_LIFT, lidar_detected
from detbench.ops import boxes_iou_bev, points_in_boxes
from tests.helpers import box_points

PC_RANGE = [0.0, -20.0, -2.0, 80.0, 20.0, 4.0]


def make_frame(seed, frame_id="0000_000", n_vehicles=3, with_hidden=True):
    """Road points plus vehicles in lanes; optionally one vehicle with no points (not LiDAR-detected)."""
    rng = np.random.default_rng(seed)
    boxes, pts = [], []
    lanes = rng.permutation([-7.0, -3.5, 0.0, 3.5, 7.0])[:n_vehicles]
    for _k, y in enumerate(lanes):
        x = rng.uniform(8, 60)
        dims = (rng.uniform(4, 5), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.8))
        box = [x, y, dims[2] / 2, *dims, float(rng.uniform(-0.1, 0.1))]
        boxes.append(box)
        p = box_points(box, int(rng.integers(20, 60)), rng, margin=0.01, intensity=None)
        p = p[p[:, 2] > 0.3]
        pts.append(p)
    if with_hidden:
        boxes.append([70.0, 10.5, 0.8, 4.5, 1.8, 1.6, 0.0])  # no points: not detected
    road = np.stack([rng.uniform(0, 80, 400), rng.uniform(-20, 20, 400), rng.uniform(0, 0.02, 400),
                     rng.uniform(0, 1, 400)], axis=1).astype(np.float32)
    points = np.concatenate(pts + [road], axis=0).astype(np.float32)
    boxes = np.asarray(boxes, dtype=np.float32)
    m = len(boxes)
    return Frame(frame_id, frame_id[:4], points, boxes, np.array(["car"] * m), np.arange(m, dtype=np.int64),
                 np.zeros(m, dtype=np.int64), Sensor(height=1.8)).check()


# ---------------------------------------------------------------- global transforms
def test_flip_twice_is_identity_and_headings_wrap():
    f = make_frame(0)
    boxes = f.boxes.copy()
    boxes[0, 6] = -math.pi  # the edge of [-pi, pi): -(-pi) = pi must wrap back to -pi
    p1, b1 = flip_x(f.points, boxes)
    assert np.array_equal(p1[:, 1], -f.points[:, 1]) and np.array_equal(p1[:, [0, 2, 3]], f.points[:, [0, 2, 3]])
    assert ((b1[:, 6] >= -math.pi) & (b1[:, 6] < math.pi)).all()
    p2, b2 = flip_x(p1, b1)
    assert np.array_equal(p2, f.points)
    assert np.array_equal(b2, boxes)


def test_rotation_and_scaling_preserve_point_box_membership():
    rng = np.random.default_rng(1)
    f = make_frame(1)
    inside = np.concatenate([box_points(b, 300, rng, margin=0.02, intensity=None) for b in f.boxes])
    outside = np.stack([rng.uniform(0, 80, 500), rng.uniform(-20, 20, 500), rng.uniform(3.5, 4, 500),
                        rng.uniform(0, 1, 500)], axis=1).astype(np.float32)  # above every vehicle
    points = np.concatenate([inside, outside])
    c0, i0 = points_in_boxes(points, f.boxes)
    assert c0.tolist() == [300] * len(f.boxes)
    for angle in (-0.7, 0.05, 0.4, math.pi - 0.01):
        p, b = rotate_z(points, f.boxes, angle)
        assert ((b[:, 6] >= -math.pi) & (b[:, 6] < math.pi)).all()
        c, i = points_in_boxes(p, b)
        assert np.array_equal(c, c0) and np.array_equal(i, i0)
    p, b = scale_world(points, f.boxes, 1.05)
    c, i = points_in_boxes(p, b)
    assert np.array_equal(i, i0)
    assert np.allclose(b[:, 2], b[:, 5] / 2, atol=1e-5)  # still standing on the road


def test_crop_to_range_half_open():
    pts = np.array([[0, 0, 0, 1], [80, 0, 0, 1], [79.9, 19.9, 3.9, 0], [-0.1, 0, 0, 0]], dtype=np.float32)
    boxes = np.array([[10, 0, 1, 4, 2, 2, 0], [80, 0, 1, 4, 2, 2, 0], [5, -25, 1, 4, 2, 2, 0]], dtype=np.float32)
    p, b, keep = crop_to_range(pts, boxes, PC_RANGE)
    assert len(p) == 2 and keep.tolist() == [True, False, False] and len(b) == 1
    with pytest.raises(ConfigError, match="max > min"):
        crop_to_range(pts, boxes, [0, 0, 0, -1, 1, 1])


def test_augment_config_parsing_and_errors():
    cfg = AugmentConfig.from_dict({"random_world_rotation": {"world_rot_angle_deg": [-5, 5]},
                                   "gt_sampling": {"enabled": False}})
    assert cfg.rotation_range == pytest.approx((-math.radians(5), math.radians(5)))
    assert cfg.flip and not cfg.gt_sampling.enabled
    with pytest.raises(ConfigError, match="random_world_flip"):
        AugmentConfig.from_dict({"random_world_flips": {}})
    with pytest.raises(ConfigError, match="world_rot_angle_deg"):
        AugmentConfig.from_dict({"random_world_rotation": {"world_rot_angle_deg": [5, -5]}})
    with pytest.raises(ConfigError, match="sample_count"):
        AugmentConfig.from_dict({"gt_sampling": {"sample_count": -1}})
    assert set(AUGMENT_DEFAULTS) == {"random_world_flip", "random_world_rotation", "random_world_scaling",
                                     "gt_sampling"}


# ---------------------------------------------------------------- ground-truth database and sampling
@pytest.fixture(scope="module")
def frames():
    return [make_frame(s, f"{s // 3:04d}_{s % 3:03d}") for s in range(12)]


def test_database_holds_detected_vehicles_only(tmp_path, frames):
    db = build_gt_database(frames, tmp_path / "db", source={"test": 1}, progress=False)
    n_detected = sum(int(lidar_detected(f.points, f.boxes).sum()) for f in frames)
    assert len(db) == n_detected == 3 * len(frames)  # the hidden vehicle of each frame is left out
    for k in range(len(db)):
        pts = db.object_points(k)
        assert len(pts) == db.num_points[k] >= 1
        counts, _ = points_in_boxes(pts, db.boxes[k:k + 1], bottom_lift=DETECTED_BOTTOM_LIFT)
        assert counts[0] == len(pts)
    back = load_gt_database(tmp_path / "db")
    assert np.array_equal(back.points, db.points) and back.frame_ids == db.frame_ids
    index = json.loads((tmp_path / "db" / INDEX_FILE).read_text())
    assert index["num_objects"] == len(db) and len(index["objects"]) == len(db)


def test_database_is_reused_and_rebuilt_when_frames_change(tmp_path, frames):
    out = tmp_path / "db"
    build_or_load_gt_database(frames, out, source={"h": 1.8}, progress=False)
    stamp = (out / INDEX_FILE).stat().st_mtime_ns
    db = build_or_load_gt_database(frames, out, source={"h": 1.8}, progress=False)
    assert (out / INDEX_FILE).stat().st_mtime_ns == stamp and len(db) == 36
    db2 = build_or_load_gt_database(frames[:4], out, source={"h": 1.8}, progress=False)
    assert len(db2) == 12


def test_damaged_database_error_names_file(tmp_path, frames):
    out = tmp_path / "db"
    build_gt_database(frames[:2], out, progress=False)
    (out / "gt_database.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"gt_database\.npz.*delete the folder"):
        load_gt_database(out)


def test_gt_sampling_never_overlaps_and_pasted_points_lie_in_their_boxes(tmp_path, frames):
    db = build_gt_database(frames, tmp_path / "db", progress=False)
    cfg = GTSamplingConfig.from_dict({"enabled": True, "sample_count": 8, "filter_by_min_points": 5})
    sampler = GTSampler(db, cfg)
    total_added = 0
    for seed in range(20):
        f = make_frame(100 + seed)
        gt = f.boxes[lidar_detected(f.points, f.boxes)]
        pts, boxes, added = sampler.sample(f.points, gt, np.random.default_rng(seed), avoid_boxes=f.boxes)
        total_added += added
        assert len(boxes) == len(gt) + added <= max(cfg.sample_count, len(gt))
        assert np.array_equal(boxes[:len(gt)], gt)
        new = boxes[len(gt):]
        if added == 0:
            continue
        # no pasted box overlaps any vehicle of the frame (detected or hidden) or another pasted box
        assert (boxes_iou_bev(new, f.boxes) == 0).all()
        iou = boxes_iou_bev(new, new)
        assert (iou[~np.eye(added, dtype=bool)] == 0).all()
        # every point inside a pasted box is a pasted vehicle point, and each vehicle keeps its points
        counts, _ = points_in_boxes(pts, new)
        picked = [k for k in range(len(db)) if any(np.array_equal(db.boxes[k], b) for b in new)]
        assert sorted(counts.tolist()) == sorted(int(db.num_points[k]) for k in picked)
        assert (db.num_points[picked] >= cfg.filter_by_min_points).all()
        # the frame's points outside pasted boxes are untouched
        _, idx0 = points_in_boxes(f.points, new)
        kept = f.points[idx0 < 0]
        assert np.array_equal(pts[:len(kept)], kept)
    assert total_added > 10  # the test exercised pasting


def test_augment_frame_is_deterministic_per_seed(tmp_path, frames):
    db = build_gt_database(frames, tmp_path / "db", progress=False)
    cfg = AugmentConfig.from_dict({"gt_sampling": {"sample_count": 6}})
    sampler = GTSampler(db, cfg.gt_sampling)
    f = make_frame(7)
    gt = f.boxes[lidar_detected(f.points, f.boxes)]
    a = augment_frame(f.points, gt, np.random.default_rng([0, 1, 2]), cfg, sampler, f.boxes)
    b = augment_frame(f.points, gt, np.random.default_rng([0, 1, 2]), cfg, sampler, f.boxes)
    c = augment_frame(f.points, gt, np.random.default_rng([0, 2, 2]), cfg, sampler, f.boxes)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not (a[0].shape == c[0].shape and np.array_equal(a[0], c[0]))
    assert a[0].dtype == np.float32 and a[1].dtype == np.float32
    with pytest.raises(ValueError, match="gt_sampling"):
        augment_frame(f.points, gt, np.random.default_rng(0), cfg, None)
