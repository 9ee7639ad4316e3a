"""PillarNet and its stages: heat-map targets, decoding round trip, OD-IoU loss, pillar encoder,
empty inputs, gradients and a short overfit on synthetic frames."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from detbench.data.batch import collate
from detbench.ops import boxes_iou3d, boxes_iou3d_aligned
from models.pillarnet import PillarNet
from models.stages import VoxelGrid
from models.stages.center_head import (CenterHead, CenterHeadConfig, CenterHeadOutput, CenterPostConfig,
                                       build_center_targets, decode_regression, gaussian_radius)
from models.stages.losses import centernet_focal_loss, od_iou_loss
from models.stages.pillar_encoder import DynamicPillarEncoder
from tests.helpers import ROOT



@pytest.fixture(autouse=True)
def one_torch_thread():
    """Run these many-small-op tests on one torch thread, then restore the setting.

    On the shared 2-core machine, with other processes busy, OpenMP's spin-waiting made the
    same tests up to 10x slower with 2 threads (the work per op is too small to split).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def default_cfg() -> dict:
    return yaml.safe_load((ROOT / "configs" / "pillarnet.yaml").read_text())["model"]


def small_cfg() -> dict:
    """A reduced-width PillarNet on a 51.2 m x 25.6 m region with 0.2 m pillars (256 x 128)."""
    cfg = default_cfg()
    cfg["point_cloud_range"] = [0.0, -12.8, -0.6, 51.2, 12.8, 4.2]
    cfg["voxel_size"] = [0.2, 0.2, 4.8]
    cfg["encoder"] = {"pillar_channels": [16], "channels": [16, 16, 32, 32, 64], "blocks": [1, 1, 1, 1, 1]}
    cfg["neck"] = {"semantic_channels": 64, "semantic_blocks": 1, "up_channels": 32, "out_channels": 32,
                   "fuse_blocks": 1}
    cfg["head"].update(shared_channels=32, head_channels=32)
    return cfg


def box_surface_points(boxes: np.ndarray, per_box: int, rng: np.random.Generator) -> np.ndarray:
    """(len(boxes) * per_box, 4) points on the four sides and the top of each box, plus intensity."""
    out = []
    for x, y, z, dx, dy, dz, h in boxes:
        face = rng.integers(0, 5, per_box)
        u, v = rng.uniform(-0.5, 0.5, per_box), rng.uniform(-0.5, 0.5, per_box)
        lx, ly, lz = u * dx, v * dy, v * dz
        lx = np.where(face == 0, 0.5 * dx, np.where(face == 1, -0.5 * dx, lx))
        ly = np.where(face == 2, 0.5 * dy, np.where(face == 3, -0.5 * dy, np.where(face < 2, u * dy, ly)))
        lz = np.where(face == 4, 0.5 * dz, lz)
        c, s = math.cos(h), math.sin(h)
        out.append(np.stack([x + lx * c - ly * s, y + lx * s + ly * c, z + lz, rng.uniform(0, 1, per_box)], 1))
    return np.concatenate(out).astype(np.float32)


def synthetic_frame(rng: np.random.Generator, boxes: np.ndarray, per_box: int = 400, ground: int = 2000):
    pts = box_surface_points(boxes, per_box, rng)
    g = np.stack([rng.uniform(0, 51, ground), rng.uniform(-12.7, 12.7, ground), rng.uniform(-0.02, 0.02, ground),
                  rng.uniform(0, 0.2, ground)], 1).astype(np.float32)
    return np.concatenate([pts, g]), boxes.astype(np.float32)


BOXES_A = np.array([[10.3, 2.1, 0.8, 4.5, 1.9, 1.6, 0.2],
                    [25.7, -4.4, 1.6, 12.0, 2.5, 3.2, -3.0],
                    [38.2, 6.5, 0.75, 4.2, 1.8, 1.5, 1.4]], np.float32)
BOXES_B = np.array([[14.9, -7.3, 0.8, 4.8, 2.0, 1.6, 3.1],
                    [31.1, 1.2, 1.0, 6.0, 2.2, 2.0, -0.7]], np.float32)


# ----------------------------------------------------------------------------- targets
def test_gaussian_radius_roots_hold_the_overlap():
    h, w, o = torch.tensor([45.0, 5.6], dtype=torch.float64), torch.tensor([18.0, 2.25], dtype=torch.float64), 0.1
    r = gaussian_radius(h, w, o).double()
    h, w = h.double(), w.double()
    moved = (h - r) * (w - r) / (2 * h * w - (h - r) * (w - r))
    shrunk = (h - 2 * r) * (w - 2 * r) / (h * w)
    grown = h * w / ((h + 2 * r) * (w + 2 * r))
    ious = torch.stack([moved, shrunk, grown])  # the minimum radius sits on one constraint, the others exceed it
    assert torch.all(ious >= o - 1e-9)
    assert torch.allclose(ious.min(dim=0).values, torch.full_like(r, o), atol=1e-9)
    assert float(gaussian_radius(torch.tensor([90.0]), torch.tensor([36.0]), o)) > float(r[0])  # grows with size


def test_gaussian_targets_on_hand_made_boxes():
    grid = VoxelGrid((0.0, -16.0, -0.6, 153.6, 16.0, 4.2), (0.1, 0.1, 4.8))
    # stride 8: 0.8 m cells; a car's radius falls below the floor of 2 cells
    box = torch.tensor([[[20.43, 1.23, 0.8, 4.5, 1.8, 1.6, 0.4]]])  # away from cell borders
    t = build_center_targets(box, torch.ones(1, 1, dtype=torch.bool), grid, 8, min_radius=2, min_overlap=0.1)
    heat = t.heatmap[0, 0]
    cx, cy = int(20.43 / 0.8), int((1.23 + 16) / 0.8)
    assert heat[cy, cx] == 1.0 and int((heat == 1.0).sum()) == 1
    assert int(t.index[0, 0]) == cy * heat.shape[1] + cx
    nz = heat.nonzero()
    assert int((nz[:, 0] - cy).abs().max()) == 2 and int((nz[:, 1] - cx).abs().max()) == 2  # radius 2 window
    sigma = 5 / 6
    assert float(heat[cy, cx + 2]) == pytest.approx(math.exp(-4 / (2 * sigma ** 2)), rel=1e-5)
    # offsets, z, log sizes, sin/cos of the regression target
    reg = t.reg[0, 0]
    assert torch.allclose(reg[:2], torch.tensor([20.43 / 0.8 - cx, (1.23 + 16) / 0.8 - cy]), atol=1e-5)
    assert torch.allclose(reg[2:], torch.tensor([0.8, math.log(4.5), math.log(1.8), math.log(1.6), math.sin(0.4),
                                                 math.cos(0.4)]), atol=1e-6)
    # stride 1 (0.1 m cells): the radius comes from the box size (45 x 18 cells)
    t1 = build_center_targets(box, torch.ones(1, 1, dtype=torch.bool), grid, 1, min_radius=2, min_overlap=0.1)
    r = int(math.floor(float(gaussian_radius(torch.tensor(45.0), torch.tensor(18.0), 0.1))))
    assert r >= 5
    nz = t1.heatmap[0, 0].nonzero()
    cx1, cy1 = 204, 172
    assert t1.heatmap[0, 0, cy1, cx1] == 1.0
    assert int((nz[:, 1] - cx1).abs().max()) == r and int((nz[:, 0] - cy1).abs().max()) == r
    # boxes off the map and padding rows are masked out
    off = torch.tensor([[[200.0, 0.0, 0.8, 4.0, 2.0, 1.5, 0.0], [0.0] * 7]])
    t2 = build_center_targets(off, torch.tensor([[True, False]]), grid, 8, min_radius=2, min_overlap=0.1)
    assert not t2.mask.any() and float(t2.heatmap.sum()) == 0.0


def test_focal_loss_is_small_for_a_perfect_heat_map_and_large_for_a_wrong_one():
    target = torch.zeros(1, 1, 8, 8)
    target[0, 0, 3, 4] = 1.0
    good = torch.full_like(target, -12.0)
    good[0, 0, 3, 4] = 12.0
    bad = -good
    lg, n = centernet_focal_loss(good, target)
    lb, _ = centernet_focal_loss(bad, target)
    assert int(n) == 1 and float(lg) < 1e-6 < 1.0 < float(lb)
    assert torch.isfinite(centernet_focal_loss(torch.full_like(target, 1e4), target)[0])


def _perfect_output(head: CenterHead, boxes: torch.Tensor, mask: torch.Tensor) -> CenterHeadOutput:
    """Head maps that encode the ground truth exactly (the oracle for the decoding round trip).

    The heat map is the target; every cell of a peak's Gaussian regresses that peak's box
    (offset = centre - cell), as a trained head does, with predicted IoU 1 there.
    """
    t = head.targets(boxes, mask)
    b = boxes.shape[0]
    h, w = head.map_shape
    heat = torch.logit(t.heatmap.clamp(1e-4, 1 - 1e-4))
    reg = torch.zeros(b, 8, h * w)
    iou = torch.full((b, 1, h * w), -1.0)
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    cells = torch.stack([cols.flatten(), rows.flatten()], 1).float()  # (H*W, 2) column, row
    for i in range(b):
        idx, tr = t.index[i][t.mask[i]], t.reg[i][t.mask[i]]
        centres = torch.stack([idx % w, idx // w], 1).float() + tr[:, :2]  # in cells
        owner = torch.cdist(cells, centres).argmin(dim=1)
        lit = t.heatmap[i, 0].flatten() > 0
        r = tr[owner].clone()
        r[:, :2] = centres[owner] - cells
        reg[i][:, lit] = r[lit].T
        iou[i][:, lit] = 1.0
    reg = reg.view(b, 8, h, w)
    return CenterHeadOutput(heat, reg[:, :2], reg[:, 2:3], reg[:, 3:6], reg[:, 6:8], iou.view(b, 1, h, w))


@pytest.mark.parametrize("method", ["maxpool", "nms"])
def test_head_decoding_round_trip(method):
    grid = VoxelGrid((0.0, -16.0, -0.6, 153.6, 16.0, 4.2), (0.1, 0.1, 4.8))
    cfg = default_cfg()
    cfg["head"].update(shared_channels=64, head_channels=64)
    post = CenterPostConfig.from_config({**cfg["post"], "method": method, "score_threshold": 0.3}, "model.post")
    head = CenterHead(8, grid, 8, CenterHeadConfig.from_config(cfg["head"], "model.head"), post)
    gt = torch.tensor([[[10.37, 2.11, 0.8, 4.5, 1.9, 1.6, 0.2], [25.71, -4.43, 1.6, 12.0, 2.5, 3.2, -3.0],
                        [80.05, 13.9, 0.9, 4.2, 1.8, 1.5, 3.1]],
                       [[140.2, -15.5, 0.8, 4.8, 2.0, 1.6, -1.2], [0.0] * 7, [0.0] * 7]])
    mask = torch.tensor([[True, True, True], [True, False, False]])
    dets = head.predict(_perfect_output(head, gt, mask))
    for i in range(2):
        want = gt[i][mask[i]]
        got = dets[i].boxes
        assert got.shape == want.shape
        order = torch.cdist(want[:, :2], got[:, :2]).argmin(dim=1)
        got = got[order]
        assert torch.allclose(got[:, :6], want[:, :6], atol=1e-4)  # exact up to float rounding (<< 0.1 m pillars)
        dh = torch.remainder(got[:, 6] - want[:, 6] + math.pi, 2 * math.pi) - math.pi
        assert float(dh.abs().max()) < 1e-4
        assert torch.all(dets[i].scores > 0.99)  # the peaks: heat 1, IoU 1


def test_decode_regression_matches_cell_geometry():
    grid = VoxelGrid((0.0, -16.0, -0.6, 153.6, 16.0, 4.2), (0.1, 0.1, 4.8))
    reg = torch.tensor([[0.5, 0.25, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]])
    w = 1536 // 8
    box = decode_regression(reg, torch.tensor([3 * w + 7]), grid, 8)[0]
    assert torch.allclose(box, torch.tensor([7.5 * 0.8, -16 + 3.25 * 0.8, 1.0, 1.0, 1.0, 1.0, math.pi / 2]), atol=1e-5)


# ----------------------------------------------------------------------------- OD-IoU loss
def test_od_iou_loss_identical_degenerate_and_exact():
    box = torch.tensor([[10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.7]])
    assert float(od_iou_loss(box, box, True)) == pytest.approx(0.0, abs=1e-6)
    flipped = box.clone()
    flipped[:, 6] += math.pi  # the heading is decoupled: a box turned by pi (or any angle) costs nothing
    assert float(od_iou_loss(flipped, box, True)) == pytest.approx(0.0, abs=1e-6)
    # degenerate rows: zero-size prediction, zero-size target, both zero at the same centre, far apart
    pred = torch.tensor([[10.0, 2.0, 0.8, 0.0, 0.0, 0.0, 0.0],
                         [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                         [10.0, 2.0, 0.8, 0.0, 0.0, 0.0, 1.0],
                         [50.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                         [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 3.0]], requires_grad=True)
    target = torch.tensor([[10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                           [10.0, 2.0, 0.8, 0.0, 0.0, 0.0, 0.0],
                           [10.0, 2.0, 0.8, 0.0, 0.0, 0.0, -2.0],
                           [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                           [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 3.0 - math.pi]])
    loss = od_iou_loss(pred, target, True)
    loss_values = loss.detach()
    assert torch.isfinite(loss_values).all() and float(loss_values.min()) >= 0 and float(loss_values.max()) <= 2
    assert float(loss_values[4]) == pytest.approx(0.0, abs=1e-6)
    assert float(loss_values[3]) > 1.0  # no overlap: 1 plus the distance term
    loss.sum().backward()
    assert torch.isfinite(pred.grad).all()
    assert float(pred.grad[3, 0]) > 0  # the distance term pulls the far box back
    # the IoU part equals the exact rotated 3D IoU of the prediction turned to the target's heading
    rng = np.random.default_rng(3)
    t = torch.tensor(np.c_[rng.uniform(0, 5, (50, 3)), rng.uniform(0.5, 5, (50, 3)), rng.uniform(-3, 3, 50)],
                     dtype=torch.float64)
    p = t.clone()
    p[:, :3] += torch.tensor(rng.normal(0, 0.8, (50, 3)))
    p[:, 3:6] *= torch.tensor(rng.uniform(0.6, 1.4, (50, 3)))
    p[:, 6] = torch.tensor(rng.uniform(-3, 3, 50))
    turned = p.clone()
    turned[:, 6] = t[:, 6]
    exact = torch.as_tensor(boxes_iou3d_aligned(turned.numpy(), t.numpy()))
    assert torch.allclose(1 - od_iou_loss(p, t, distance=False).double(), exact, atol=1e-5)


# ----------------------------------------------------------------------------- pillar encoder
def test_pillar_encoder_permutation_invariance():
    torch.manual_seed(0)
    grid = VoxelGrid((0.0, -12.8, -0.6, 51.2, 12.8, 4.2), (0.2, 0.2, 4.8))
    enc = DynamicPillarEncoder(grid, [16, 32])
    rng = np.random.default_rng(1)
    pts, _ = synthetic_frame(rng, BOXES_A)
    pts = np.concatenate([pts, [[60.0, 0.0, 1.0, 0.5], [10.0, 20.0, 1.0, 0.5]]]).astype(np.float32)  # 2 out of range
    batch = collate([(pts, np.zeros((0, 7)), "a"), (pts[: len(pts) // 2], np.zeros((0, 7)), "b")]).points
    perm = torch.randperm(batch.shape[0])
    for mode in ("train", "eval"):
        enc.train(mode == "train")
        a, b = enc(batch, 2), enc(batch[perm], 2)
        assert torch.equal(a.indices, b.indices)
        assert torch.allclose(a.features, b.features, atol=1e-5)
    assert a.features.shape[1] == 32 and a.spatial_shape == [128, 256]
    assert int((a.indices[:, 0] == 0).sum()) > int((a.indices[:, 0] == 1).sum()) > 0


def test_pillar_encoder_feature_definition():
    """One pillar, two points: the 9 features before the MLP are x, y, z, i, offsets to centre and mean."""
    grid = VoxelGrid((0.0, -12.8, -0.6, 51.2, 12.8, 4.2), (0.2, 0.2, 4.8))
    enc = DynamicPillarEncoder(grid, [8])
    pts = torch.tensor([[0, 1.01, 0.03, 0.5, 0.2], [0, 1.15, 0.17, 1.5, 0.4]])
    sites = torch.tensor([[0, 64, 5]], dtype=torch.int32)
    f = enc.point_features(pts, torch.tensor([0, 0]), sites)
    centre = torch.tensor([1.1, 0.1])
    assert torch.allclose(f[:, :4], pts[:, 1:])
    assert torch.allclose(f[:, 4:6], pts[:, 1:3] - centre, atol=1e-6)
    assert torch.allclose(f[:, 6:], pts[:, 1:4] - pts[:, 1:4].mean(0), atol=1e-6)


# ----------------------------------------------------------------------------- the model
def test_config_checks_give_clear_errors():
    cfg = default_cfg()
    cfg["point_cloud_range"] = [0.0, -16.0, -0.6, 150.0, 16.0, 4.2]  # 1500 pillars: not a multiple of 16
    with pytest.raises(ValueError, match="divide by the network stride 16"):
        PillarNet(cfg)
    cfg = default_cfg()
    cfg["voxel_size"] = [0.1, 0.1, 0.2]
    with pytest.raises(ValueError, match="voxel_size z must be 4.8"):
        PillarNet(cfg)
    cfg = default_cfg()
    del cfg["head"]["min_radius"]
    with pytest.raises(ValueError, match="model.head.min_radius"):
        PillarNet(cfg)
    cfg = default_cfg()
    cfg["post"]["method"] = "circle"
    with pytest.raises(ValueError, match="model.post.method must be one of 'maxpool', 'nms'"):
        PillarNet(cfg)


def test_default_model_builds_with_the_stated_grid():
    model = PillarNet(default_cfg())
    assert model.vfe.spatial_shape == (320, 1536)
    assert model.head.map_shape == (40, 192)


def test_empty_point_cloud_gives_no_boxes_and_a_finite_loss():
    torch.manual_seed(0)
    model = PillarNet(small_cfg())
    empty = collate([(np.zeros((0, 4), np.float32), BOXES_B, "e")])
    out = model(empty)
    loss, parts = model.loss(out, empty)
    assert torch.isfinite(loss)
    loss.backward()
    model.eval()
    with torch.no_grad():
        dets = model.predict(model(empty), empty)
        assert len(dets) == 1 and dets[0].boxes.shape == (0, 7) and dets[0].scores.shape == (0,)
        # an empty frame beside a non-empty one: still none for the empty frame
        pts, boxes = synthetic_frame(np.random.default_rng(0), BOXES_A)
        mixed = collate([(pts, boxes, "a"), (np.zeros((0, 4), np.float32), np.zeros((0, 7)), "e")])
        dets = model.predict(model(mixed), mixed)
        assert dets[1].boxes.shape == (0, 7)
        # a single point (batch statistics of one row) works too
        one = collate([(np.array([[10.0, 1.0, 0.5, 0.3]], np.float32), BOXES_B, "one")])
    model.train()
    loss, _ = model.loss(model(one), one)
    assert torch.isfinite(loss)


def test_forward_loss_backward_reaches_the_encoder():
    torch.manual_seed(0)
    model = PillarNet(small_cfg())
    rng = np.random.default_rng(2)
    batch = collate([synthetic_frame(rng, BOXES_A) + ("a",), synthetic_frame(rng, BOXES_B) + ("b",)])
    out = model(batch)
    assert out.head.heatmap.shape == (2, 1, 16, 32)
    loss, parts = model.loss(out, batch)
    assert torch.isfinite(loss) and set(parts) >= {"loss_hm", "loss_reg", "loss_iou", "loss_od_iou", "num_pos"}
    assert parts["num_pos"] == 2.5
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert float(model.vfe.linears[0].weight.grad.abs().sum()) > 0
    assert float(model.backbone.sparse_stages[0][0].weight.grad.abs().sum()) > 0
    model.eval()
    with torch.no_grad():
        dets = model.predict(model(batch), batch)
    assert len(dets) == 2 and all(d.boxes.shape[1] == 7 for d in dets)


def test_overfit_two_frames():
    """A reduced-width PillarNet learns two synthetic frames: the loss drops and the boxes come back."""
    torch.manual_seed(0)
    cfg = small_cfg()
    model = PillarNet(cfg)
    rng = np.random.default_rng(4)
    batch = collate([synthetic_frame(rng, BOXES_A) + ("a",), synthetic_frame(rng, BOXES_B) + ("b",)])
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=0.0)
    losses = []
    for _ in range(40):
        opt.zero_grad()
        loss, _ = model.loss(model(batch), batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 8, losses[::10]
    # predict in training mode (batch statistics): 40 steps are too few for BatchNorm's running
    # statistics (momentum 0.01) to settle, which is a matter of training length, not of learning
    with torch.no_grad():
        dets = model.predict(model(batch), batch)
    for i, gt in enumerate((BOXES_A, BOXES_B)):
        iou = boxes_iou3d(dets[i].boxes.numpy(), gt)
        assert iou.shape[0] >= len(gt)
        assert (iou.max(axis=0) > 0.5).all(), iou.max(axis=0)
