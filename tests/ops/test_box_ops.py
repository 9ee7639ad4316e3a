"""points_in_boxes, nms_bev and the box helpers of detbench.ops."""
from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

from detbench.ops import (
    ResidualBoxCoder,
    boxes_iou_bev,
    boxes_to_corners_3d,
    boxes_to_corners_bev,
    limit_period,
    nms_bev,
    normalize_heading,
    points_in_boxes,
    points_in_boxes_mask,
)
from detbench.ops.nms import _nms_torch
from detbench.ops.points_in_boxes import _points_in_boxes_mask_torch, _points_in_boxes_torch


def pib_all_paths(points, boxes, lift=0.0):
    """[(counts, box_index)] as numpy from: numpy (numba), torch CPU (numba), torch vectorised."""
    tp, tb = torch.as_tensor(points), torch.as_tensor(boxes)
    outs = [points_in_boxes(points, boxes, lift), points_in_boxes(tp, tb, lift), _points_in_boxes_torch(tp, tb, lift)]
    return [(np.asarray(c), np.asarray(i)) for c, i in outs]


def random_boxes(rng, n, spread=20.0):
    return np.c_[
        rng.uniform(-spread, spread, (n, 2)),
        rng.uniform(0.5, 1.5, n),
        rng.uniform(1.0, 6.0, (n, 3)),
        rng.uniform(-math.pi, math.pi, n),
    ]


def ref_membership(points, boxes, lift):
    """(N, M) membership by half-plane tests against the corners (independent of the kernel)."""
    n, m = len(points), len(boxes)
    out = np.zeros((n, m), dtype=bool)
    for j, b in enumerate(boxes):
        x, y, z, dx, dy, dz, h = b
        c, s = math.cos(h), math.sin(h)
        corners = [(x + u * c - v * s, y + u * s + v * c)
                   for u, v in ((dx / 2, dy / 2), (-dx / 2, dy / 2), (-dx / 2, -dy / 2), (dx / 2, -dy / 2))]
        inside = np.ones(n, dtype=bool)
        for k in range(4):
            (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
            inside &= (x1 - x0) * (points[:, 1] - y0) - (y1 - y0) * (points[:, 0] - x0) >= 0
        inside &= (points[:, 2] >= z - dz / 2 + lift) & (points[:, 2] <= z + dz / 2)
        out[:, j] = inside
    return out


# ----------------------------------------------------------------------------------------
# points_in_boxes
# ----------------------------------------------------------------------------------------
def test_bottom_lift_road_points():
    """A box on the road with lift 0.05 m: 0.04 m above the road does not count, 0.06 m does."""
    box = np.array([[20.0, -3.5, 0.75, 4.5, 1.9, 1.5, 0.4]], dtype=np.float32)
    pts = np.array([[20.0, -3.5, 0.04, 0.3], [20.0, -3.5, 0.06, 0.3]], dtype=np.float32)
    for counts, idx in pib_all_paths(pts, box, 0.05):
        assert list(counts) == [1]
        assert list(idx) == [-1, 0]
    for counts, _ in pib_all_paths(pts, box):  # without lift both count
        assert list(counts) == [2]


def test_borders_are_inclusive():
    box = np.array([[0.0, 0.0, 1.0, 4.0, 2.0, 2.0, 0.0]])
    pts = np.array([
        [2.0, 0.0, 1.0],    # front face
        [-2.0, 1.0, 1.0],   # rear-left edge
        [0.0, -1.0, 2.0],   # right face, top
        [0.0, 0.0, 0.25],   # bottom + lift exactly
        [2.0 + 1e-9, 0.0, 1.0],
        [0.0, 0.0, 2.0 + 1e-9],
        [0.0, 0.0, 0.25 - 1e-9],
    ])
    for _, idx in pib_all_paths(pts, box, 0.25):
        assert list(idx) == [0, 0, 0, 0, -1, -1, -1]


def test_random_scene_matches_reference_numpy_and_torch(monkeypatch):
    rng = np.random.default_rng(0)
    boxes = random_boxes(rng, 30)
    boxes[5] = boxes[4]  # an exact duplicate: its points go to box 4 in box_index
    boxes[7, :2] = boxes[6, :2] + 0.5  # overlapping pair
    n = 20_000
    pts = np.c_[rng.uniform(-25, 25, (n, 2)), rng.uniform(-0.5, 8.0, n), rng.uniform(0, 1, n)].astype(np.float32)
    ref = ref_membership(pts.astype(np.float64), boxes, 0.05)
    ref_idx = np.where(ref.any(1), ref.argmax(1), -1)
    assert ref[:, 6].any() and (ref[:, 6] & ref[:, 7]).any() and ref.sum() > 500
    counts, idx = points_in_boxes(pts, boxes, bottom_lift=0.05)
    assert counts.dtype == np.int64 and idx.dtype == np.int64 and counts.shape == (30,) and idx.shape == (n,)
    np.testing.assert_array_equal(counts, ref.sum(0))
    np.testing.assert_array_equal(idx, ref_idx)
    assert counts[5] == counts[4] and not (idx == 5).any()
    # the parallel kernel (used for large clouds) gives the same answer
    monkeypatch.setattr(importlib.import_module("detbench.ops.points_in_boxes"), "PARALLEL_MIN_POINTS", 0)
    pc, pi = points_in_boxes(pts, boxes, bottom_lift=0.05)
    np.testing.assert_array_equal(pc, counts)
    np.testing.assert_array_equal(pi, idx)
    tp, tb = torch.from_numpy(pts), torch.from_numpy(boxes)
    for tc, ti in (points_in_boxes(tp, tb.float(), 0.05), _points_in_boxes_torch(tp, tb, 0.05)):
        assert tc.dtype == torch.int64 and ti.dtype == torch.int64
        np.testing.assert_array_equal(tc.numpy(), ref.sum(0))
        np.testing.assert_array_equal(ti.numpy(), ref_idx)
    np.testing.assert_array_equal(points_in_boxes_mask(pts, boxes, 0.05), ref)
    np.testing.assert_array_equal(points_in_boxes_mask(tp, tb, 0.05).numpy(), ref)
    np.testing.assert_array_equal(_points_in_boxes_mask_torch(tp, tb, 0.05).numpy(), ref)


def test_torch_chunking_gives_same_result(monkeypatch):
    pib = importlib.import_module("detbench.ops.points_in_boxes")  # the package re-exports a function of that name

    rng = np.random.default_rng(1)
    boxes = torch.from_numpy(random_boxes(rng, 7, spread=5.0))
    pts = torch.from_numpy(np.c_[rng.uniform(-8, 8, (3000, 2)), rng.uniform(0, 3, 3000)])
    full = points_in_boxes(pts, boxes)
    monkeypatch.setattr(pib, "_TORCH_CHUNK_ELEMS", 50)
    chunked = _points_in_boxes_torch(pts, boxes, 0.0)
    assert torch.equal(full[0], chunked[0]) and torch.equal(full[1], chunked[1])
    assert torch.equal(_points_in_boxes_mask_torch(pts, boxes, 0.0), points_in_boxes_mask(pts, boxes))
    assert full[0].sum() > 0


def test_far_from_origin_and_nan_points():
    box = np.array([[10000.0, -2000.0, 0.8, 4.0, 2.0, 1.6, 0.7]])
    c, s = math.cos(0.7), math.sin(0.7)
    local = np.array([[1.999, 0.999], [2.001, 0.0], [0.0, 1.001], [-1.99, -0.99]])
    pts = np.c_[10000.0 + local[:, 0] * c - local[:, 1] * s, -2000.0 + local[:, 0] * s + local[:, 1] * c,
                np.full(4, 0.8)]
    pts = np.vstack([pts, [np.nan, np.nan, np.nan]])
    for counts, idx in pib_all_paths(pts, box):
        assert list(idx) == [0, -1, -1, 0, -1] and int(counts[0]) == 2


def test_empty_inputs_and_errors():
    pts = np.zeros((5, 4), np.float32)
    c, i = points_in_boxes(pts, np.zeros((0, 7)))
    assert c.shape == (0,) and list(i) == [-1] * 5
    c, i = points_in_boxes(np.zeros((0, 4), np.float32), np.ones((3, 7)))
    assert list(c) == [0, 0, 0] and i.shape == (0,)
    tc, ti = points_in_boxes(torch.zeros((0, 4)), torch.zeros((0, 7)))
    assert tc.shape == (0,) and ti.shape == (0,) and ti.dtype == torch.int64
    assert points_in_boxes_mask(pts, np.zeros((0, 7))).shape == (5, 0)
    with pytest.raises(ValueError, match=r"points_in_boxes.*points.*\(N, >=3\)"):
        points_in_boxes(np.zeros((5, 2)), np.ones((1, 7)))
    with pytest.raises(ValueError, match=r"points_in_boxes.*boxes.*\(M, 7\)"):
        points_in_boxes(pts, np.ones((1, 6)))
    with pytest.raises(ValueError, match="bottom_lift"):
        points_in_boxes(pts, np.ones((1, 7)), bottom_lift="high")
    with pytest.raises(ValueError, match="NaN"):
        points_in_boxes(pts, np.full((1, 7), np.nan))


# ----------------------------------------------------------------------------------------
# nms_bev
# ----------------------------------------------------------------------------------------
def ref_nms(boxes, scores, thr):
    iou = boxes_iou_bev(boxes, boxes)
    order = sorted(range(len(scores)), key=lambda k: (-scores[k], k))
    keep = []
    for k in order:
        if all(iou[k, j] <= thr for j in keep):
            keep.append(k)
    return keep


def test_nms_matches_greedy_reference_on_all_paths():
    rng = np.random.default_rng(4)
    boxes = random_boxes(rng, 300, spread=12.0)
    scores = np.round(rng.uniform(0, 1, 300), 2)  # many ties
    for thr in (0.0, 0.1, 0.5):
        ref = ref_nms(boxes, scores, thr)
        assert list(nms_bev(boxes, scores, thr)) == ref
        assert nms_bev(torch.from_numpy(boxes), torch.from_numpy(scores), thr).tolist() == ref
        assert _nms_torch(torch.from_numpy(boxes), torch.from_numpy(scores), thr, 10**9).tolist() == ref
        assert list(nms_bev(boxes, scores, thr, max_keep=5)) == ref[:5]
        assert _nms_torch(torch.from_numpy(boxes), torch.from_numpy(scores), thr, 5).tolist() == ref[:5]
    assert 5 < len(ref_nms(boxes, scores, 0.1)) < 300


def test_nms_ties_threshold_and_empty():
    b = np.array([[0, 0, 0, 4, 2, 1.5, 0.0]] * 3 + [[10, 0, 0, 4, 2, 1.5, 0.0]])
    s = np.array([0.5, 0.9, 0.9, 0.1])
    assert list(nms_bev(b, s, 0.5)) == [1, 3]  # equal scores: the earlier box wins
    assert list(nms_bev(b, s, 1.0)) == [1, 2, 0, 3]  # suppression needs IoU > threshold
    out = nms_bev(b, s, 0.5)
    assert out.dtype == np.int64
    assert nms_bev(np.zeros((0, 7)), np.zeros(0), 0.5).shape == (0,)
    t = nms_bev(torch.zeros((0, 7)), torch.zeros(0), 0.5)
    assert t.shape == (0,) and t.dtype == torch.int64
    assert _nms_torch(torch.zeros((0, 7)), torch.zeros(0), 0.5, 10).shape == (0,)
    assert list(nms_bev(b, s, 0.5, max_keep=0)) == []
    with pytest.raises(ValueError, match=r"nms_bev: scores must have shape \(4,\)"):
        nms_bev(b, s[:3], 0.5)
    with pytest.raises(ValueError, match="iou_threshold"):
        nms_bev(b, s, 1.5)


# ----------------------------------------------------------------------------------------
# box helpers
# ----------------------------------------------------------------------------------------
def test_limit_period_and_normalize_heading():
    vals = np.array([-10.0, -math.pi, -1.0, 0.0, 1.0, math.pi, 3 * math.pi, 7.5, np.nextafter(math.pi, 0)])
    for conv in (lambda v: v, torch.from_numpy):
        out = np.asarray(normalize_heading(conv(vals)))
        assert np.all(out >= -math.pi) and np.all(out < math.pi)
        np.testing.assert_allclose(np.cos(out), np.cos(vals), atol=1e-12)
        np.testing.assert_allclose(np.sin(out), np.sin(vals), atol=1e-12)
    assert normalize_heading(math.pi) == -math.pi
    assert normalize_heading(-math.pi) == -math.pi
    assert normalize_heading(1.0) == 1.0
    assert limit_period(0.75, offset=0.0, period=0.5) == pytest.approx(0.25)
    assert isinstance(limit_period(torch.tensor([4.0])), torch.Tensor)
    # rounding pitfall: just below pi must not come out just below -pi
    x = torch.tensor([np.nextafter(np.float32(math.pi), np.float32(0))], dtype=torch.float32)
    r = normalize_heading(x)
    assert -math.pi <= float(r) < math.pi


def test_corners_bev_and_3d():
    box = np.array([[1.0, 2.0, 0.75, 4.0, 2.0, 1.5, math.pi / 2]])
    bev = boxes_to_corners_bev(box)
    np.testing.assert_allclose(bev[0], [[0, 4], [0, 0], [2, 0], [2, 4]], atol=1e-12)
    c3 = boxes_to_corners_3d(box)
    assert c3.shape == (1, 8, 3)
    np.testing.assert_allclose(c3[0, :4, :2], bev[0])
    np.testing.assert_allclose(c3[0, 4:, :2], bev[0])
    np.testing.assert_allclose(c3[0, :4, 2], 0.0)
    np.testing.assert_allclose(c3[0, 4:, 2], 1.5)
    rng = np.random.default_rng(6)
    boxes = random_boxes(rng, 20)
    bev = boxes_to_corners_bev(boxes)
    # counter-clockwise: positive shoelace area equal to dx * dy
    x, y = bev[..., 0], bev[..., 1]
    area = 0.5 * (x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1)
    np.testing.assert_allclose(area, boxes[:, 3] * boxes[:, 4], rtol=1e-12)
    # corners pulled 0.1 % towards the centre are inside their box, pushed out are not
    c3 = boxes_to_corners_3d(boxes)
    inner = boxes[:, None, :3] + 0.999 * (c3 - boxes[:, None, :3])
    outer = boxes[:, None, :3] + 1.001 * (c3 - boxes[:, None, :3])
    _, idx = points_in_boxes(inner.reshape(-1, 3), boxes)
    assert not points_in_boxes_mask(outer.reshape(-1, 3), boxes)[np.arange(160), np.repeat(np.arange(20), 8)].any()
    mask = points_in_boxes_mask(inner.reshape(-1, 3), boxes)
    assert all(mask[8 * j:8 * j + 8, j].all() for j in range(20)) and (idx >= 0).all()
    tb = boxes_to_corners_3d(torch.from_numpy(boxes).float())
    assert tb.dtype == torch.float32
    np.testing.assert_allclose(tb.numpy(), boxes_to_corners_3d(boxes), atol=1e-4)
    assert boxes_to_corners_bev(np.zeros((0, 7))).shape == (0, 4, 2)
    assert boxes_to_corners_3d(torch.zeros((0, 7))).shape == (0, 8, 3)


@pytest.mark.parametrize("sincos", [False, True])
def test_residual_coder_round_trip(sincos):
    rng = np.random.default_rng(8)
    coder = ResidualBoxCoder(encode_angle_by_sincos=sincos)
    anchors = torch.from_numpy(np.c_[random_boxes(rng, 200), rng.normal(size=(200, 2))])
    boxes = torch.from_numpy(np.c_[random_boxes(rng, 200), rng.normal(size=(200, 2))])
    deltas = coder.encode(boxes, anchors)
    assert deltas.shape == (200, coder.code_size + 2)
    back = coder.decode(deltas, anchors)
    torch.testing.assert_close(back[:, :6], boxes[:, :6], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(back[:, 7:], boxes[:, 7:], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(normalize_heading(back[:, 6].numpy() - boxes[:, 6].numpy()), 0.0, atol=1e-9)
    # an anchor encodes to zeros; hand-computed residual
    np.testing.assert_allclose(coder.encode(anchors, anchors)[:, :coder.code_size].numpy(), 0.0, atol=1e-12)
    a = torch.tensor([[0.0, 0.0, 1.0, 3.0, 4.0, 2.0, 0.0]])
    g = torch.tensor([[5.0, -2.5, 2.0, 6.0, 4.0, 1.0, 0.5]])
    d = coder.encode(g, a)[0]
    torch.testing.assert_close(d[:6], torch.tensor([1.0, -0.5, 0.5, math.log(2), 0.0, math.log(0.5)]))
    # broadcasting over a batch axis, float32, zero-size boxes stay finite
    dd = coder.encode(boxes[None, :5].float(), anchors[None, :5].float())
    assert dd.shape == (1, 5, coder.code_size + 2) and dd.dtype == torch.float32
    z = boxes[:1].clone()
    z[:, 3:6] = 0
    assert torch.isfinite(coder.encode(z, anchors[:1])).all()
    with pytest.raises(TypeError, match="torch.Tensor"):
        coder.encode(boxes.numpy(), anchors)
    with pytest.raises(ValueError, match=r"decode: `deltas` must have shape"):
        coder.decode(deltas[:, :3], anchors)
    with pytest.raises(ValueError, match="extra columns"):
        coder.decode(deltas[:, :-1], anchors)
