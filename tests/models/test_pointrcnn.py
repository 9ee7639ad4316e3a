"""PointRCNN: point sampling, point-head targets, the model end to end, presets."""
import numpy as np
import pytest
import torch

import models
from detbench.train.run_config import load_run_config
from models.stages.point_head import point_targets
from models.stages.pointnet2 import sample_frame_points, thin_to_voxels
from tests.helpers import batch_of, box_points

CAR = [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.3]


def point_head_cfg(box_coding: str):
    """PointHead's configured values (configs/pointrcnn.yaml) with narrow branches, a fixed mean size and the
    given box coding."""
    from models.stages.point_head import PointHeadConfig

    ph = load_run_config("pointrcnn", "paper")["model"]["point_head"]
    ph.update(cls_fc=[32], reg_fc=[32], mean_size=[4.5, 1.9, 1.6], box_coding=box_coding)
    return PointHeadConfig.from_config(ph, "model.point_head")


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
    t = point_targets(xyz, valid, torch.tensor([[CAR]]), torch.ones(1, 1, dtype=torch.bool), extra_width=0.2,
                      bottom_lift=0.0)
    assert t.labels.tolist() == [[1, -1, 0, -1]]
    assert torch.allclose(t.boxes[0, 0], torch.tensor(CAR)) and not t.boxes[0, 2].any()
    none = point_targets(xyz, valid, torch.zeros(1, 0, 7), torch.zeros(1, 0, dtype=torch.bool), extra_width=0.2,
                         bottom_lift=0.0)
    assert none.labels.tolist() == [[0, 0, 0, -1]]


def test_sampling_keeps_far_points_first_and_fills_small_frames():
    g = torch.Generator().manual_seed(0)
    near = torch.rand(300, 4, generator=g) * torch.tensor([30.0, 10.0, 2.0, 1.0])
    far = torch.rand(20, 4, generator=g) * torch.tensor([50.0, 10.0, 2.0, 1.0]) + torch.tensor([60.0, 0, 0, 0])
    frame0 = torch.cat([near, far])
    frame1 = near[:10]
    points = torch.cat([torch.cat([torch.zeros(len(frame0), 1), frame0], 1),
                        torch.cat([torch.ones(len(frame1), 1), frame1], 1)])
    s = sample_frame_points(points, 3, 64, far_threshold=40.0, generator=g, shuffle=False,
                            voxel_size=0.0)  # frame 2 is empty
    assert s.points.shape == (192, 4) and s.num_points == 64
    f0, f1, f2 = s.points[:64], s.points[64:128], s.points[128:]
    assert int((torch.hypot(f0[:, 0], f0[:, 1]) > 40).sum()) == 20  # every far point kept
    assert len({tuple(p.tolist()) for p in f0}) == 64  # no repeats while there are enough points
    assert {tuple(p.tolist()) for p in f1} == {tuple(p.tolist()) for p in frame1}  # all 10, repeated
    assert s.valid[:128].all() and not s.valid[128:].any() and (f2[:, 2] == -10).all()
    a = sample_frame_points(points, 3, 64, 40.0, generator=torch.Generator().manual_seed(1), shuffle=False,
                            voxel_size=0.0)
    b = sample_frame_points(points, 3, 64, 40.0, generator=torch.Generator().manual_seed(1), shuffle=False,
                            voxel_size=0.0)
    assert torch.equal(a.points, b.points)


def test_voxel_thinning_keeps_one_point_per_cell_and_leaves_sparse_points_alone():
    g = torch.Generator().manual_seed(0)
    dense = torch.rand(3000, 4, generator=g) * torch.tensor([1.0, 1.0, 0.5, 1.0]) + torch.tensor([5.0, 0.0, 0.2, 0.0])
    sparse = torch.tensor([[60.0 + 0.5 * k, -3.0, 0.5, 0.2] for k in range(20)])  # 0.5 m apart: one a cell
    pts = torch.cat([dense, sparse])
    keep = thin_to_voxels(pts, 0.25, torch.Generator().manual_seed(1))
    cells = torch.floor(pts[keep, :3] / 0.25).to(torch.int64)
    assert len(torch.unique(cells, dim=0)) == len(keep)  # one point a cell
    assert len(keep) == len(torch.unique(torch.floor(pts[:, :3] / 0.25).to(torch.int64), dim=0))  # every cell
    assert set(range(3000, 3020)) <= set(keep.tolist())  # the far vehicle keeps all its points
    assert torch.equal(keep, thin_to_voxels(pts, 0.25, torch.Generator().manual_seed(1)))  # seeded: repeatable
    assert len(thin_to_voxels(pts[:0], 0.25)) == 0
    frame = torch.cat([torch.zeros(len(pts), 1), pts], 1)
    s = sample_frame_points(frame, 1, 64, 40.0, torch.Generator().manual_seed(2), shuffle=True, voxel_size=0.25)
    assert s.points.shape == (64, 4) and int((s.points[:, 0] > 40).sum()) == 20  # far points first, as without
    near = s.points[s.points[:, 0] < 40, :3]  # 44 of the dense patch's 48 cells: each sampled point its own cell
    assert len(near) == 44 and len(torch.unique(torch.floor(near / 0.25).to(torch.int64), dim=0)) == 44


def test_empty_sparse_and_normal_frames_give_finite_losses_and_predictions():
    torch.manual_seed(0)
    model = models.build_model("pointrcnn", tiny_cfg())
    empty = np.zeros((0, 4), np.float32)
    few = np.array([[5.0, 0.0, 0.5, 0.3], [6.0, 1.0, 0.5, 0.3]], np.float32)  # fewer points than the budget
    road = np.random.default_rng(0).uniform([0, -8, 0, 0], [40, 8, 0.1, 1], (400, 4)).astype(np.float32)
    car = np.concatenate([box_points(CAR, n=400, on_faces=True), road])
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
    batch = batch_of([box_points(CAR, n=400, on_faces=True)], [np.array([far])])
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
    pts = [np.concatenate([box_points(b, rng=i, on_faces=True) for i, b in enumerate(bs)]
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
    assert len(deltas) >= 2 and (deltas[:, :2].std(dim=0) > 1e-4).all(), \
        f"{len(deltas)} RoIs, residual std across them {deltas.std(dim=0).tolist()}"
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


# --------------------------------------------------------------------------------------
# the bin-based box coding of the point head (point_head.box_coding: bin)
# --------------------------------------------------------------------------------------
def perfect_bin_output(coder, t):
    """The raw output (N, code_size) that puts all weight on the target bins with the target residuals."""
    L, K = coder.num_loc_bins, coder.num_heading_bins
    onehot = lambda b, k: torch.nn.functional.one_hot(b, k).double() * 20.0  # noqa: E731
    res = lambda b, k, v: torch.zeros(len(b), k, dtype=torch.float64).scatter_(1, b[:, None], v[:, None])  # noqa: E731
    return torch.cat([onehot(t.x_bin, L), onehot(t.y_bin, L), res(t.x_bin, L, t.x_res), res(t.y_bin, L, t.y_res),
                      t.z_res[:, None], onehot(t.h_bin, K), res(t.h_bin, K, t.h_res), t.size_res], dim=1)


def test_bin_coder_round_trip():
    from detbench.ops import PointBinCoder
    coder = PointBinCoder([4.5, 1.9, 1.6], loc_scope=3.0, loc_bin_size=0.5, num_heading_bins=12)
    assert coder.num_loc_bins == 12 and coder.code_size == 4 * 12 + 1 + 2 * 12 + 3
    g = torch.Generator().manual_seed(0)
    n = 2000
    pts = torch.randn(n, 3, generator=g, dtype=torch.float64) * 20
    centre = pts + (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 5.98  # within +-2.99 m
    size = torch.tensor([4.5, 1.9, 1.6], dtype=torch.float64) * (
        0.5 + torch.rand(n, 3, generator=g, dtype=torch.float64))
    heading = (torch.rand(n, 1, generator=g, dtype=torch.float64) - 0.5) * 2 * np.pi
    boxes = torch.cat([centre, size, heading], dim=1)
    t = coder.encode(boxes, pts)
    assert int(t.x_bin.min()) >= 0 and int(t.x_bin.max()) <= 11 and int(t.h_bin.max()) <= 11
    assert float(t.x_res.abs().max()) <= 0.5 + 1e-9 and float(t.h_res.min()) >= -1 and float(t.h_res.max()) < 1
    dec = coder.decode(perfect_bin_output(coder, t), pts)
    dh = torch.remainder(dec[:, 6] - boxes[:, 6] + np.pi, 2 * np.pi) - np.pi
    assert torch.allclose(dec[:, :6], boxes[:, :6], atol=1e-9) and float(dh.abs().max()) < 1e-9
    assert float(dec[:, 6].min()) >= -np.pi and float(dec[:, 6].max()) < np.pi


def test_bin_coder_edges_and_clamping():
    from detbench.ops import PointBinCoder
    coder = PointBinCoder([4.5, 1.9, 1.6])
    pts = torch.zeros(7, 3, dtype=torch.float64)
    # x offsets: the lower edge of the search range, a bin border, just inside the upper edge,
    # the upper edge itself, beyond it on both sides, far beyond
    dx = torch.tensor([-3.0, 0.0, 2.99, 3.0, 4.0, -5.0, 80.0], dtype=torch.float64)
    boxes = torch.zeros(7, 7, dtype=torch.float64)
    boxes[:, 0] = dx
    boxes[:, 3:6] = torch.tensor([4.5, 1.9, 1.6], dtype=torch.float64)
    boxes[:, 6] = torch.tensor([0.0, np.pi - 1e-6, -np.pi, 0.2618, -0.2619, 1.0, 2.0], dtype=torch.float64)
    t = coder.encode(boxes, pts)
    assert t.x_bin.tolist() == [0, 6, 11, 11, 11, 0, 11]
    assert abs(float(t.x_res[0]) + 0.5) < 1e-9 and abs(float(t.x_res[1]) + 0.5) < 1e-9  # a bin's lower border
    assert torch.allclose(t.x_res[2], torch.tensor(0.48, dtype=torch.float64))
    # beyond the range: clamped into the edge bins, just inside the range
    assert (t.x_res[3:5] > 0.49).all() and (t.x_res[6] > 0.49) and abs(float(t.x_res[5]) + 0.5) < 1e-9
    dec = coder.decode(perfect_bin_output(coder, t), pts)
    assert torch.allclose(dec[:3, 0], dx[:3], atol=1e-9)
    assert torch.allclose(dec[3:, 0], torch.tensor([3.0, 3.0, -3.0, 3.0], dtype=torch.float64), atol=2e-3)
    # heading: 0 sits in the middle of bin 0, +-pi in bin 6; a bin border at pi / 12
    assert t.h_bin.tolist()[:5] == [0, 6, 6, 1, 11] and abs(float(t.h_res[0])) < 1e-9
    assert t.y_bin.tolist() == [6] * 7 and (t.y_res == -0.5).all() and (t.size_res == 0).all()
    with pytest.raises(ValueError, match="whole number"):
        PointBinCoder([4.5, 1.9, 1.6], loc_scope=3.0, loc_bin_size=0.7)
    with pytest.raises(ValueError, match="code_size"):
        coder.decode(torch.zeros(2, 8), torch.zeros(2, 3))


def test_bin_coding_point_head_losses_are_finite_and_learnable():
    from models.stages.point_head import PointHead, PointHeadOutput, PointTargets
    torch.manual_seed(0)
    head = PointHead(16, point_head_cfg("bin"))
    assert head.code_size == head.bin_coder.code_size
    xyz = torch.tensor([[[10.0, 2.0, 0.8], [7.8, 1.2, 0.2], [40.0, 0.0, 0.5], [9.0, 2.0, 0.8]]])
    # point 1 lies 2.2 m behind the centre; point 3's box is 25 m away (clamped to the range's edge)
    boxes = torch.tensor([[CAR, CAR, [0.0] * 7, [34.0, 2.0, 0.8, 4.5, 1.9, 1.6, np.pi]]])
    t = PointTargets(torch.tensor([[1, 1, 0, 1]]), boxes)
    feats = torch.randn(4, 16)
    out = head(feats, 1)
    assert out.box_deltas.shape == (1, 4, head.code_size)
    loss, parts = head.loss(out, t, xyz)
    loss.backward()
    assert torch.isfinite(loss) and parts["loss_point_box"] > 0
    assert all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)
    # no foreground point at all: a zero box loss that still backpropagates
    head.zero_grad()
    none = PointTargets(torch.tensor([[0, 0, -1, 0]]), torch.zeros(1, 4, 7))
    loss0, parts0 = head.loss(head(feats, 1), none, xyz)
    loss0.backward()
    assert torch.isfinite(loss0) and parts0["loss_point_box"] == 0.0
    # the box loss is smallest at the perfect output, and decoding it gives back the boxes
    fg = t.labels[0] == 1
    tb = head.bin_coder.encode(boxes[0][fg].double(), xyz[0][fg].double())
    perfect = torch.zeros(1, 4, head.code_size)
    perfect[0, fg] = perfect_bin_output(head.bin_coder, tb).float()
    good = head.loss(PointHeadOutput(out.cls_logits.detach(), perfect), t, xyz)[1]["loss_point_box"]
    assert good < 0.01 * parts["loss_point_box"]
    dec, _ = head.decode(PointHeadOutput(out.cls_logits.detach(), perfect), xyz)
    assert torch.allclose(dec[0, :2], boxes[0, :2], atol=1e-4)
    edge = 9.0 + head.bin_coder.loc_scope  # clamped to the range's edge
    assert torch.allclose(dec[0, 3, :6], torch.tensor([edge, 2.0, 0.8, 4.5, 1.9, 1.6]), atol=2e-3)
    # an in-place training step on the bin loss lowers it (the gradients point the right way)
    opt = torch.optim.Adam(head.parameters(), lr=0.01)
    first = None
    for _ in range(100):
        loss, parts = head.loss(head(feats, 1), t, xyz)
        first = parts["loss_point_box"] if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert parts["loss_point_box"] < 0.3 * first
    with pytest.raises(ValueError, match="model.point_head.box_coding must be one of 'residual', 'bin'"):
        point_head_cfg("bins")


def test_both_box_codings_build_and_the_config_names_every_point_head_value():
    cfg = tiny_cfg()
    assert cfg["point_head"]["box_coding"] == "bin"
    bins = round(2 * cfg["point_head"]["bin"]["loc_scope"] / cfg["point_head"]["bin"]["loc_bin_size"])
    assert models.build_model("pointrcnn", cfg).point_head.code_size == 4 * bins + 1 + 2 * 12 + 3
    cfg["point_head"]["box_coding"] = "residual"
    assert models.build_model("pointrcnn", cfg).point_head.code_size == 8
    del cfg["point_head"]["box_coding"]  # the model has no value of its own: configs/pointrcnn.yaml is the home
    with pytest.raises(ValueError, match=r"configs/pointrcnn.yaml: model.point_head.box_coding is missing"):
        models.build_model("pointrcnn", cfg)


# --------------------------------------------------------------------------------------
# the mechanisms behind PointRCNN's config keys (docs/results.md, "PointRCNN ablation")
# --------------------------------------------------------------------------------------
def test_foreground_labels_lift_the_box_bottom_off_the_road():
    """CAR stands on the road (bottom at z = 0): a road point under it and one beside it in the
    margin are background with the 0.05 m lift; without it, foreground and ignored."""
    beside = [10.0 - 1.05 * np.sin(0.3), 2.0 + 1.05 * np.cos(0.3), 0.0]  # 0.1 m off the side face, on the road
    xyz = torch.tensor([[[10.0, 2.0, 0.02], beside, [10.0, 2.0, 0.3], [10.0, 2.0, 1.7]]])
    valid = torch.ones(1, 4, dtype=torch.bool)
    gt, m = torch.tensor([[CAR]]), torch.ones(1, 1, dtype=torch.bool)
    assert point_targets(xyz, valid, gt, m, extra_width=0.2, bottom_lift=0.0).labels.tolist() == [[1, -1, 1, -1]]
    assert point_targets(xyz, valid, gt, m, extra_width=0.2, bottom_lift=0.05).labels.tolist() == [[0, 0, 1, -1]]


def test_shuffled_sampling_is_deterministic_per_seed():
    """With shuffle the rows are those of the scan-ordered sample of the same seed, in a random
    order that the seed fixes (the same seed: the same order; another seed: another order)."""
    g = torch.Generator().manual_seed(0)
    frame = torch.rand(500, 4, generator=g) * torch.tensor([60.0, 10.0, 2.0, 1.0])
    points = torch.cat([torch.zeros(500, 1), frame], 1)

    def sample(seed, shuffle):
        return sample_frame_points(points, 1, 128, 40.0, generator=torch.Generator().manual_seed(seed),
                                   shuffle=shuffle, voxel_size=0.0)

    ordered, a, b, c = sample(3, False), sample(3, True), sample(3, True), sample(4, True)
    assert torch.equal(a.points, b.points) and not torch.equal(a.points, c.points)
    assert {tuple(p.tolist()) for p in a.points} == {tuple(p.tolist()) for p in ordered.points}
    assert not torch.equal(a.points, ordered.points)
    # a small frame (repeats) is shuffled too: the original rows no longer lead
    small = sample_frame_points(points[:50], 1, 128, 40.0, generator=torch.Generator().manual_seed(3), shuffle=True,
                                voxel_size=0.0)
    assert not torch.equal(small.points[:50], frame[:50])


def roi_head_of(**keys):
    cfg = tiny_cfg()
    cfg["roi_head"].update(keys)
    torch.manual_seed(0)
    return models.build_model("pointrcnn", cfg).roi_head.eval()


def test_roi_size_reaches_the_refinement():
    """Three RoIs of lengths -15 %, 0, +15 % on one vehicle pool the same points: without the size
    channels their features are identical, with either of them they differ."""
    car_pts = torch.as_tensor(box_points(CAR, n=24, on_faces=True)[:, :3])
    rois = torch.tensor([CAR] * 3)
    rois[:, 3] *= torch.tensor([0.85, 1.0, 1.15])

    def features(head):
        feats_in = torch.randn(24, head.merge_down.layers[0].in_features - head.xyz_up.out_channels,
                               generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            scores = torch.rand(24, generator=torch.Generator().manual_seed(1))
            return head(car_pts, feats_in, scores, rois[None], 24)[0]

    blind = features(roi_head_of(scaled_xyz=False, roi_size=False))
    assert torch.equal(blind[0], blind[1]) and torch.equal(blind[1], blind[2])
    for keys in ({"scaled_xyz": True, "roi_size": False}, {"scaled_xyz": False, "roi_size": True}):
        seen = features(roi_head_of(**keys))  # untrained weights: small but real differences
        assert (seen[0] - seen[1]).abs().max() > 1e-5 and (seen[1] - seen[2]).abs().max() > 1e-5, keys


def test_roi_head_batch_norm_and_detached_features():
    """batch_norm False leaves no BatchNorm in the RoI network; detach_features stops the
    refinement's loss at the backbone (its gradients reach only the second stage)."""
    bn = torch.nn.modules.batchnorm._BatchNorm
    assert not any(isinstance(m, bn) for m in roi_head_of(batch_norm=False).modules())
    assert any(isinstance(m, bn) for m in roi_head_of(batch_norm=True).modules())
    from models.stages.two_stage import refine_loss
    batch = batch_of([np.concatenate([box_points(CAR, n=300, on_faces=True),
                                      np.random.default_rng(0).uniform([0, -8, 0, 0], [30, 8, 0.05, 1], (200, 4))])],
                     [np.array([CAR])])
    for detach in (True, False):
        cfg = tiny_cfg()
        cfg["roi_head"]["detach_features"] = detach
        torch.manual_seed(0)
        model = models.build_model("pointrcnn", cfg)
        out = model(batch)
        loss, _ = refine_loss(out.refine, model.coder, model.loss_weights)
        loss.backward()
        backbone = [p.grad for p in model.backbone.parameters()]
        reached = any(g is not None and bool(g.abs().sum() > 0) for g in backbone)
        assert reached is not detach
        assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.refine.parameters())


def test_test_proposals_split_by_distance():
    """Many strong near boxes and a few weaker far ones: the plain budget goes to the near ones,
    the split budget keeps near_share of it within the distance and gives the rest to the far ones."""
    from models.stages.two_stage import select_proposals, select_proposals_by_distance
    near = torch.tensor([[5.0 + 6 * i, -8.0 + 4 * j, 0.8, 4.0, 1.8, 1.5, 0.0] for i in range(6) for j in range(5)])
    far = torch.tensor([[60.0 + 6 * i, 0.0, 0.8, 4.0, 1.8, 1.5, 0.0] for i in range(5)])
    boxes = torch.cat([near, far])[None]
    scores = torch.cat([torch.full((30,), 0.9), torch.full((5,), 0.3)])[None]
    plain = select_proposals(boxes, scores, 100, 10, 0.8)
    assert (plain.rois[0, plain.mask[0], 0] < 40).all() and int(plain.mask.sum()) == 10
    split = select_proposals_by_distance(boxes, scores, 100, 10, 0.8, None, distance=40.0, near_share=0.7)
    x = split.rois[0, :, 0]
    assert split.rois.shape == (1, 10, 7) and bool(split.mask.all())
    assert (x[:7] < 40).all() and (x[7:] > 40).all()
