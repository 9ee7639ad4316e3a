"""PointRCNN: point sampling, point-head targets, the model end to end, presets."""
import numpy as np
import pytest
import torch

import models
from detbench.train.run_config import load_run_config
from models.stages.point_head import point_targets
from models.stages.pointnet2 import sample_frame_points
from test_second import batch_of, box_points

CAR = [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.3]


def tiny_cfg():
    cfg = load_run_config("pointrcnn", "smoke")["model"]
    cfg["sampling"]["num_points"] = 256
    cfg["point_head"]["mean_size"] = [4.5, 1.9, 1.6]
    return cfg


def test_point_targets_on_a_hand_made_scene():
    # inside the car, in its 0.2 m margin, far outside; a filler point
    xyz = torch.tensor([[[10.0, 2.0, 0.8], [10.0 + 2.25 * np.cos(0.3) + 0.1 * np.cos(0.3),
                                            2.0 + 2.25 * np.sin(0.3) + 0.1 * np.sin(0.3), 0.8],
                         [30.0, 0.0, 0.5], [10.1, 2.0, 0.8]]], dtype=torch.float32)
    valid = torch.tensor([[True, True, True, False]])
    t = point_targets(xyz, valid, torch.tensor([[CAR]]), torch.ones(1, 1, dtype=torch.bool), extra_width=0.2)
    assert t.labels.tolist() == [[1, -1, 0, -1]]
    assert torch.allclose(t.boxes[0, 0], torch.tensor(CAR)) and not t.boxes[0, 2].any()
    none = point_targets(xyz, valid, torch.zeros(1, 0, 7), torch.zeros(1, 0, dtype=torch.bool))
    assert none.labels.tolist() == [[0, 0, 0, -1]]


def test_sampling_keeps_far_points_first_and_fills_small_frames():
    g = torch.Generator().manual_seed(0)
    near = torch.rand(300, 4, generator=g) * torch.tensor([30.0, 10.0, 2.0, 1.0])
    far = torch.rand(20, 4, generator=g) * torch.tensor([50.0, 10.0, 2.0, 1.0]) + torch.tensor([60.0, 0, 0, 0])
    frame0 = torch.cat([near, far])
    frame1 = near[:10]
    points = torch.cat([torch.cat([torch.zeros(len(frame0), 1), frame0], 1),
                        torch.cat([torch.ones(len(frame1), 1), frame1], 1)])
    s = sample_frame_points(points, 3, 64, far_threshold=40.0, generator=g)  # frame 2 is empty
    assert s.points.shape == (192, 4) and s.num_points == 64
    f0, f1, f2 = s.points[:64], s.points[64:128], s.points[128:]
    assert int((torch.hypot(f0[:, 0], f0[:, 1]) > 40).sum()) == 20  # every far point kept
    assert len({tuple(p.tolist()) for p in f0}) == 64  # no repeats while there are enough points
    assert {tuple(p.tolist()) for p in f1} == {tuple(p.tolist()) for p in frame1}  # all 10, repeated
    assert s.valid[:128].all() and not s.valid[128:].any() and (f2[:, 2] == -10).all()
    a = sample_frame_points(points, 3, 64, generator=torch.Generator().manual_seed(1))
    b = sample_frame_points(points, 3, 64, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a.points, b.points)


def test_empty_sparse_and_normal_frames_give_finite_losses_and_predictions():
    torch.manual_seed(0)
    model = models.build_model("pointrcnn", tiny_cfg())
    empty = np.zeros((0, 4), np.float32)
    few = np.array([[5.0, 0.0, 0.5, 0.3], [6.0, 1.0, 0.5, 0.3]], np.float32)  # fewer points than the budget
    car = np.concatenate([box_points(CAR, n=400), np.random.default_rng(0).uniform([0, -8, 0, 0], [40, 8, 0.1, 1],
                                                                                   (400, 4)).astype(np.float32)])
    batch = batch_of([empty, few, car], [np.zeros((0, 7)), np.zeros((0, 7)), np.array([CAR])])
    out = model(batch)
    loss, parts = model.loss(out, batch)
    loss.backward()
    assert torch.isfinite(loss) and parts["num_fg_points"] > 0
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    model.eval()
    with torch.no_grad():
        dets = model.predict(model(batch), batch)
        again = model.predict(model(batch), batch)
        model.set_output_stage("proposals")
        first = model.predict(model(batch), batch)
    assert len(dets) == len(first) == 3
    assert all(torch.equal(a.boxes, b.boxes) for a, b in zip(dets, again))  # evaluation is deterministic
    assert all(torch.isfinite(d.boxes).all() for d in dets + first)


def test_a_valid_roi_without_points_trains(monkeypatch):
    """A frame whose only ground-truth box lies far from every point: its jittered copies become
    foreground RoIs that pool no point. The pooled `empty` flag is set for such a real, regressed
    RoI, and loss and gradients stay finite."""
    import models.stages.pointrcnn_head as roi_head_module

    pooled = []

    def spy(*args, **kwargs):
        pooled.append(pool(*args, **kwargs))
        return pooled[-1]

    pool = roi_head_module.roi_point_pool
    monkeypatch.setattr(roi_head_module, "roi_point_pool", spy)
    cfg = tiny_cfg()
    cfg["roi_head"]["targets"].update(gt_jitter_copies=4, gt_jitter=[0.05] * 7)  # copies well above reg_fg_thresh
    torch.manual_seed(0)
    model = models.build_model("pointrcnn", cfg)
    far = [40.0, -6.0, 0.8, 4.5, 1.9, 1.6, -0.4]  # 30 m from the nearest point
    batch = batch_of([box_points(CAR, n=400)], [np.array([far])])
    out = model(batch)
    loss, parts = model.loss(out, batch)
    loss.backward()
    assert len(pooled) == 1
    empty = pooled[0].empty.reshape(out.refine.roi_mask.shape)
    assert (empty & out.refine.roi_mask & out.refine.targets.reg_mask).any()
    assert not pooled[0].points[pooled[0].empty].any()
    assert torch.isfinite(loss) and parts["num_fg_rois"] > 0 and parts["loss_rcnn_reg"] > 0
    grads = [p.grad for p in model.refine.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.any() for g in grads)
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_presets_and_mean_size_from_data():
    cfg = load_run_config("pointrcnn", "paper")["model"]
    assert cfg["sampling"]["num_points"] == 16384 and cfg["backbone"]["npoints"] == [4096, 1024, 256, 64]
    assert cfg["roi_head"]["num_points"] == 512 and cfg["roi_head"]["targets"]["cls_score_type"] == "binary"
    assert cfg["roi_head"]["proposals"]["test"]["nms_threshold"] == 0.85
    boxes = np.array([[0, 0, 0, 4.0, 2.0, 1.5, 0], [0, 0, 0, 6.0, 2.2, 2.5, 0]], np.float32)
    prepared = models.prepare_model_config("pointrcnn", cfg, boxes)
    assert prepared["point_head"]["mean_size"] == [5.0, 2.1, 2.0] and cfg["point_head"]["mean_size"] == "auto"
    for preset in ("smoke", "cpu", "paper"):
        c = models.prepare_model_config("pointrcnn", load_run_config("pointrcnn", preset)["model"], boxes)
        assert models.build_model("pointrcnn", c).STAGES["backbone"] == ["backbone"]
    with pytest.raises(ValueError, match="auto"):
        models.build_model("pointrcnn", cfg)


@pytest.mark.slow
def test_overfit_a_few_frames():
    torch.manual_seed(0)
    cars = [np.array([[8.0, 1.0, 0.8, 4.5, 1.9, 1.6, 0.1], [15.0, -2.5, 0.8, 4.2, 1.8, 1.5, 1.4]]),
            np.array([[12.0, -0.5, 0.9, 4.8, 2.0, 1.8, -0.2]])]
    rng = np.random.default_rng(0)
    pts = [np.concatenate([box_points(b, seed=i) for i, b in enumerate(bs)]
                          + [rng.uniform([0, -8, 0, 0], [30, 8, 0.05, 1], (300, 4)).astype(np.float32)])
           for bs in cars]
    batch = batch_of(pts, cars)
    model = models.build_model("pointrcnn", tiny_cfg())
    opt = torch.optim.AdamW(model.parameters(), lr=0.003)
    hist = []
    for _ in range(300):
        loss, parts = model.loss(model(batch), batch)
        hist.append(parts)
        opt.zero_grad()
        loss.backward()
        opt.step()
    mean = lambda k, sl: float(np.mean([h[k] for h in hist[sl]]))  # noqa: E731
    print({k: (round(mean(k, slice(0, 10)), 4), round(mean(k, slice(-10, None)), 4))
           for k in ("loss_point_cls", "loss_point_box", "loss_rcnn_cls", "loss_rcnn_reg", "loss_rcnn_corner")})
    assert mean("loss_point_cls", slice(-10, None)) < 0.3 * mean("loss_point_cls", slice(0, 10))
    assert mean("loss_point_box", slice(-10, None)) < 0.5 * mean("loss_point_box", slice(0, 10))
    # the second stage learns too
    assert mean("loss_rcnn_reg", slice(-10, None)) < 0.7 * mean("loss_rcnn_reg", slice(0, 10))
    assert mean("loss_rcnn_corner", slice(-10, None)) < 0.7 * mean("loss_rcnn_corner", slice(0, 10))
    from detbench.ops import boxes_iou3d
    model.eval()
    with torch.no_grad():
        out = model(batch)
        dets = model.predict(out, batch)
    # a live box branch: the residuals differ between RoIs (a dead one, every ReLU of its last hidden
    # layer off, gives the same residual for every RoI: what lr 0.01 did on the cpu preset)
    deltas = out.refine.box_deltas[out.refine.roi_mask]
    print(f"{len(deltas)} RoIs, residual std across them {deltas.std(dim=0).tolist()}")
    assert len(deltas) >= 2 and (deltas[:, :2].std(dim=0) > 1e-4).all()
    for d, gt in zip(dets, cars):
        assert len(d.boxes) >= 1
        assert float(boxes_iou3d(d.boxes.double(), torch.as_tensor(gt)).max(dim=0).values.min()) > 0.3


def test_roi_head_with_no_roi_slots():
    """A zero RoI budget (R = 0) gives (B, 0, C) features, not a reshape error."""
    model = models.build_model("pointrcnn", tiny_cfg())
    head = model.roi_head
    n = 64
    xyz, feats = torch.randn(2 * n, 3), torch.randn(2 * n, model.backbone.out_channels)
    out = head(xyz, feats, torch.rand(2 * n), torch.zeros(2, 0, 7), n)
    assert out.shape == (2, 0, head.out_channels)
