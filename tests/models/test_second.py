"""SECOND and its stages: anchors, target assignment, box coding, losses, empty inputs, configs."""
import math

import numpy as np
import pytest
import torch

import models
from detbench.config import ConfigError
from detbench.ops import ResidualBoxCoder, boxes_iou_bev
from detbench.train.run_config import load_run_config
from models.stages import AnchorGenerator, AnchorHeadOutput, VoxelGrid, assign_targets
from tests.helpers import GRID, TINY, batch_of, box_points

def test_anchor_layout():
    gen = AnchorGenerator([[4.0, 2.0, 1.5]], rotations=(0.0, math.pi / 2))
    anchors = gen(GRID, stride=8)
    nx, ny, _ = GRID.grid_size
    assert anchors.shape == ((nx // 8) * (ny // 8) * 2, 7)
    first = anchors[:2]
    assert torch.allclose(first[:, 0], torch.tensor([0.8, 0.8]))  # cell centre: 0 + 0.5 * 1.6 m
    assert torch.allclose(first[:, 1], torch.tensor([-3.2 + 0.8] * 2))
    assert torch.allclose(first[:, 2], torch.tensor([0.75, 0.75]))  # bottom on the road
    assert torch.allclose(first[:, 6], torch.tensor([0.0, math.pi / 2]))
    assert torch.allclose(anchors[2, :2], torch.tensor([0.8 + 1.6, -2.4]))  # next cell along x


def test_assign_targets_thresholds_and_best_anchor():
    anchors = torch.tensor([[10.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0],     # identical to gt 0 -> positive
                            [10.6, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0],     # IoU 3.4/4.6 = 0.739 -> positive
                            [11.6, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0],     # IoU 2.4/5.6 = 0.43 -> negative
                            [11.2, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0],     # IoU 2.8/5.2 = 0.54 -> ignored
                            [50.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0],     # far -> negative
                            [30.9, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0]])    # only anchor near gt 1 (IoU 0.29)
    gt = torch.tensor([[10.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0], [29.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0]])
    t = assign_targets(anchors, gt, 0.6, 0.45)
    assert t.labels.tolist() == [1, 1, 0, -1, 0, 1]  # the last is gt 1's best anchor, forced positive
    assert torch.equal(t.boxes[5], gt[1]) and torch.equal(t.boxes[1], gt[0])
    empty = assign_targets(anchors, torch.zeros(0, 7), 0.6, 0.45)
    assert empty.labels.tolist() == [0] * 6


def test_box_coding_roundtrip():
    g = torch.Generator().manual_seed(0)
    anchors = torch.cat([torch.rand(50, 3, generator=g) * 20, torch.rand(50, 3, generator=g) + 1,
                         (torch.rand(50, 1, generator=g) - 0.5) * 6], 1)
    boxes = anchors + torch.randn(50, 7, generator=g) * 0.3
    boxes[:, 3:6] = boxes[:, 3:6].abs() + 0.1
    coder = ResidualBoxCoder()
    assert torch.allclose(coder.decode(coder.encode(boxes, anchors), anchors), boxes, atol=1e-5)


def test_direction_decoding_flips_backward_boxes():
    head = models.build_model("second", TINY).head
    n = head.anchors.shape[0]
    deltas = torch.zeros(1, n, 7)
    deltas[0, 0, 6] = math.pi  # anchor 0 (heading 0) regressed to heading pi: the sine loss cannot tell
    dir_logits = torch.zeros(1, n, 2)
    # bins (dir_offset pi/4): bin 0 holds headings in [pi/4, 5pi/4), bin 1 in [-3pi/4, pi/4)
    dir_logits[0, 0] = torch.tensor([-5.0, 5.0])
    boxes, scores = head.decode(AnchorHeadOutput(torch.zeros(1, n), deltas, dir_logits))
    assert abs(float(boxes[0, 0, 6])) < 1e-5  # turned back to face +x
    dir_logits[0, 0] = torch.tensor([5.0, -5.0])
    boxes, _ = head.decode(AnchorHeadOutput(torch.zeros(1, n), deltas, dir_logits))
    assert abs(abs(float(boxes[0, 0, 6])) - math.pi) < 1e-5
    assert torch.allclose(scores, torch.full_like(scores, 0.5))
    assert head._dir_targets(torch.tensor([0.0, math.pi, math.pi / 2, -math.pi / 2])).tolist() == [1, 0, 0, 1]


def test_empty_and_one_point_frames():
    torch.manual_seed(0)
    model = models.build_model("second", TINY)
    empty = batch_of([np.zeros((0, 4), np.float32)], [np.zeros((0, 7))])
    out = model(empty)
    loss, parts = model.loss(out, empty)
    assert torch.isfinite(loss) and parts["num_pos"] == 0
    loss.backward()
    model.eval()
    with torch.no_grad():
        dets = model.predict(model(empty), empty)
    assert len(dets) == 1 and dets[0].boxes.shape == (0, 7)
    model.train()
    one = batch_of([np.array([[5.0, 0.0, 0.5, 0.3]], np.float32)], [np.array([[5.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0]])])
    loss, parts = model.loss(model(one), one)
    assert torch.isfinite(loss) and parts["num_pos"] >= 1


def test_overfit_two_frames_raises_score_on_the_cars():
    torch.manual_seed(0)
    cars = [np.array([[4.6, 1.0, 0.8, 4.5, 1.9, 1.6, 0.1], [9.0, -1.5, 0.8, 4.2, 1.8, 1.5, 1.4]]),
            np.array([[6.0, -0.5, 0.9, 4.8, 2.0, 1.8, -0.2]])]
    pts = [np.concatenate([box_points(b, rng=i, on_faces=True) for i, b in enumerate(bs)]) for bs in cars]
    batch = batch_of(pts, cars)
    model = models.build_model("second", TINY)
    opt = torch.optim.AdamW(model.parameters(), lr=0.01)
    first = None
    for _ in range(25):
        loss, _ = model.loss(model(batch), batch)
        first = first if first is not None else float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.1 * first
    # train-mode BatchNorm (batch statistics): 25 steps are too few for the running statistics
    # (momentum 0.01) to settle, and this test is about learning, not about BatchNorm
    with torch.no_grad():
        dets = model.predict(model(batch), batch)
    for d, gt in zip(dets, cars):
        assert len(d.boxes) >= 1
        iou = boxes_iou_bev(d.boxes.double(), torch.as_tensor(gt))
        assert float(iou.max(dim=0).values.min()) > 0.3  # every car is found roughly


def test_prepare_config_sizes_anchors_from_data():
    cfg = {**TINY, "head": {**TINY["head"], "anchor_sizes": "auto"}}
    boxes = np.array([[0, 0, 0, 4.0, 2.0, 1.5, 0], [0, 0, 0, 5.0, 2.2, 1.7, 0]])
    out = models.prepare_model_config("second", cfg, boxes)
    assert out["head"]["anchor_sizes"] == [[4.5, 2.1, 1.6]]
    assert cfg["head"]["anchor_sizes"] == "auto"  # the input is not modified
    with pytest.raises(ValueError, match="no LiDAR-detected"):
        models.prepare_model_config("second", cfg, np.zeros((0, 7)))
    with pytest.raises(ValueError, match="still 'auto'"):
        models.build_model("second", cfg)


def test_grid_checks_are_clear():
    with pytest.raises(ValueError, match="whole number of voxels"):
        VoxelGrid((0, -16, -0.6, 153.65, 16, 4.2), (0.1, 0.1, 0.15))
    cfg = {**TINY, "point_cloud_range": [0.0, -3.2, -0.6, 12.0, 3.2, 4.2]}  # 60 voxels: not a multiple of 16
    with pytest.raises(ValueError, match="divide by the network stride 16"):
        models.build_model("second", cfg)
    with pytest.raises(ValueError, match="unknown model 'secnd'.*did you mean 'second'"):
        models.build_model("secnd", TINY)


def test_run_config_presets_and_unknown_keys():
    cfg = load_run_config("second", "smoke")
    assert cfg["model"]["name"] == "second" and cfg["train"]["epochs"] == 2
    assert cfg["model"]["backbone3d"]["channels"] == [8, 16, 16, 16]  # the model's own smoke change
    cfg = load_run_config("second", "cpu", overrides=["train.lr=1e-3"])
    assert cfg["train"]["lr"] == pytest.approx(1e-3)
    with pytest.raises(ConfigError, match="'train.lrr'.*did you mean 'lr'"):
        load_run_config("second", "smoke", overrides=["train.lrr=1"])
    with pytest.raises(ConfigError, match="unknown preset"):
        load_run_config("second", "fast")


def test_voxel_features_locate_the_point_in_its_voxel_at_float16():
    """The mean x, y enter the sparse backbone as offsets from the voxel's centre (within half a voxel of zero;
    z and intensity absolute), so float16 keeps the point's place in its voxel at 150 m, where an absolute x
    would be rounded to 0.125 m; offset plus centre gives back the absolute mean; `absolute` is kept for
    checkpoints of earlier versions."""
    from models.stages import MeanVFE, VFEConfig

    grid = VoxelGrid((0.0, -16.0, -0.6, 153.6, 16.0, 4.2), (0.1, 0.1, 0.15))
    rng = np.random.default_rng(0)
    pts = np.c_[np.zeros(400), rng.uniform([0.0, -16, -0.6, 0], [153.6, 16, 4.2, 1], (400, 4))].astype(np.float32)
    pts[:200, 1] = rng.uniform(140.0, 153.6, 200)
    points = torch.from_numpy(pts)
    off, ab = MeanVFE(grid, VFEConfig("offset"))(points, 1), MeanVFE(grid, VFEConfig("absolute"))(points, 1)
    assert torch.equal(off.indices, ab.indices) and torch.equal(off.features[:, 2:], ab.features[:, 2:])
    assert float(off.features[:, :2].abs().max()) <= 0.05 + 1e-6
    centre = torch.tensor([0.0, -16.0]) + (off.indices[:, [3, 2]].double() + 0.5) * 0.1
    assert torch.allclose(off.features[:, :2].double() + centre, ab.features[:, :2].double(), atol=2e-5)
    far = ab.features[:, 0] > 140
    half_err = lambda t: float((t.half().double() - t.double()).abs()[far].max())  # noqa: E731
    assert half_err(off.features[:, 0]) < 1e-4 < 0.01 < half_err(ab.features[:, 0])
    assert half_err(ab.features[:, 2]) < 0.002  # z (-0.6 to 4.2 m) is float16-safe as it is


@pytest.mark.parametrize("name", ["second", "ct3d"])
def test_the_first_sparse_convolution_sees_offsets_under_autocast(name):
    """What enters SECOND's (and CT3D's first stage's) sparse backbone under autocast: x, y within half a voxel
    of zero, as configs/second.yaml sets it."""
    cfg = load_run_config(name, "smoke")["model"]
    model = models.build_model(name, models.prepare_model_config(name, cfg, np.array([[20, 0, 0.8, 4.5, 1.9, 1.6, 0]])))
    seen = []
    model.backbone3d.register_forward_pre_hook(lambda m, args: seen.append(args[0].features))
    car = np.array([140.0, 3.0, 0.8, 4.5, 1.9, 1.6, 0.2], np.float32)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        model.eval()(batch_of([box_points(car, 300)], [car[None]]))
    half_voxel = cfg["voxel_size"][0] / 2
    assert seen and float(seen[0][:, :2].abs().max()) <= half_voxel + 1e-6 and float(seen[0][:, 0].abs().max()) > 0
