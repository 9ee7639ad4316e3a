"""Box geometry at the extremes, float32 and float64, on every path of each op.

Extremes: coordinates up to 1e4 m, 1 cm boxes, 100 m trucks, headings at and across +-pi,
boxes touching at a corner or a face, identical boxes, zero-size boxes. Ops: rotated 3D and
BEV IoU (`boxes_iou3d`, `boxes_iou_bev`), `nms_bev`, `ResidualBoxCoder`, `points_in_boxes`.
Paths: the numba kernels (numpy in, and torch CPU tensors), and the vectorised torch kernels
that run on CUDA (called directly here, on the CPU, in the tensors' dtype).

References are exact or float64: IoU against the rational-arithmetic reference in
tests/helpers.py (`ref_iou`), evaluated on the float32-rounded inputs and, far from the origin, on
boxes moved back by an exactly representable offset (the reference itself works in world
coordinates, whose float64 corners carry ~1e-12 m rounding at 1e4 m); membership against a
long-double distance to the box surface.

The bounds each test asserts (measured values in brackets, 2 cores, this commit):
- IoU, numba (float64 arithmetic): |error| <= 1e-11 at 1e4 m [2e-12], <= 1e-14 elsewhere [8e-16];
- IoU, vectorised torch float32: <= 1e-6 [2e-7]; float64: as numba;
- NMS keeps exactly the boxes it keeps near the origin at scale 1, at 1e4 m, for 1 cm and 100 m boxes
  and for headings written as +pi or -pi;
- box coder encode -> decode, float32: centre <= 1e-5 m at 150 m [3e-6] (required: 1 mm), <= 1 float32
  step of the coordinate at 1e4 m (0.98 mm) [3e-6]; size <= 2e-7 relative [1.5e-5 m on 100 m];
  heading <= 1e-6 rad [2.4e-7]; a zero size comes back as the coder's min_size (1e-5 m);
- points in boxes: every point further than 4 float32 steps of its box-frame coordinates from a face
  (1.2e-5 m on a 100 m truck) is decided as in long double, on both paths, in float32 and float64.
Nothing is NaN anywhere.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from detbench.ops import (
    ResidualBoxCoder, boxes_iou3d, boxes_iou3d_aligned, boxes_iou_bev, boxes_iou_bev_aligned, nms_bev,
    normalize_heading, points_in_boxes, points_in_boxes_mask,
)
from detbench.ops.iou import MODE_IOU_3D, MODE_IOU_BEV, _torch_pair_values
from detbench.ops.nms import _nms_torch
from detbench.ops.points_in_boxes import _points_in_boxes_mask_torch, _points_in_boxes_torch
from tests.helpers import ref_iou

FAR = 1e4  # metres
F32_STEP_FAR = float(np.spacing(np.float32(FAR)))  # 0.000977 m: float32 resolution at 1e4 m
IOU_TOL = {"numba_far": 1e-11, "numba": 1e-14, "torch32": 1e-6}
HEADINGS_PI = (math.pi, -math.pi, math.pi - 1e-6, -math.pi + 1e-6, 3 * math.pi)


def overlapping_pairs(rng, n, size=1.0, centre=(0.0, 0.0)):
    """(a, b): n pairs of overlapping boxes of about `size` metres around `centre`; coordinates in multiples of
    size / 256 so that a float32 copy and an exact shift keep them exact."""
    a = np.c_[rng.uniform(-1, 1, (n, 2)) * size, rng.uniform(0.3, 1.0, n) * size,
              rng.uniform(0.5, 1.5, (n, 3)) * size, rng.uniform(-math.pi, math.pi, n)]
    b = a.copy()
    b[:, :3] += rng.uniform(-0.4, 0.4, (n, 3)) * size
    b[:, 3:6] *= rng.uniform(0.7, 1.3, (n, 3))
    b[:, 6] += rng.uniform(-0.6, 0.6, n)
    for x in (a, b):
        x[:, :6] = np.round(x[:, :6] / size * 256) * size / 256
        x[:, :2] += centre
    return a, b


def extreme_pair_sets():
    """name -> (a, b, offset): the boxes, and the exact offset that moves them back near the origin."""
    rng = np.random.default_rng(19)
    out = {
        "unit": (*overlapping_pairs(rng, 60), (0.0, 0.0)),
        "far_1e4_xy": (*overlapping_pairs(rng, 60, centre=(FAR, -FAR)), (FAR, -FAR)),
        "far_1e4_y": (*overlapping_pairs(rng, 60, centre=(150.0, FAR)), (150.0, FAR)),
        "1cm": (*overlapping_pairs(rng, 60, size=0.01, centre=(40.0, 3.0)), (40.0, 3.0)),
        "1cm_far": (*overlapping_pairs(rng, 60, size=0.01, centre=(FAR, FAR)), (FAR, FAR)),
        "truck_100m": (*overlapping_pairs(rng, 60, size=60.0, centre=(100.0, 0.0)), (100.0, 0.0)),
    }
    a, b = overlapping_pairs(rng, 60)
    a[:, 6] = np.resize(HEADINGS_PI, 60)
    b[:, 6] = np.resize((-math.pi + 1e-3, math.pi - 1e-3, math.pi, -math.pi, 0.3), 60)  # across the cut
    out["heading_pi"] = (a, b, (0.0, 0.0))
    return out


def _exact_iou(a, b, offset, mode):
    off = np.r_[offset, np.zeros(5)]
    return np.array([ref_iou(x - off, y - off, mode) for x, y in zip(a, b)])


@pytest.mark.parametrize("case", list(extreme_pair_sets()))
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_iou_at_the_extremes_against_the_exact_reference(case, dtype):
    a, b, offset = extreme_pair_sets()[case]
    a, b = a.astype(dtype), b.astype(dtype)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    assert np.array_equal((a64 - np.r_[offset, np.zeros(5)]).astype(dtype).astype(np.float64)
                          + np.r_[offset, np.zeros(5)],
                          a64)  # the offset is exact: the reference sees the same boxes
    for mode, aligned, pair_mode in (("3d", boxes_iou3d_aligned, MODE_IOU_3D),
                                     ("bev", boxes_iou_bev_aligned, MODE_IOU_BEV)):
        ref = _exact_iou(a64, b64, offset, mode)
        assert (ref > 0.05).sum() >= 40  # the pairs overlap
        numba_tol = IOU_TOL["numba_far"] if max(abs(v) for v in offset) >= FAR else IOU_TOL["numba"]
        ta, tb = torch.from_numpy(a), torch.from_numpy(b)
        results = {"numba": aligned(a, b), "torch_cpu": aligned(ta, tb).double().numpy(),
                   "vectorised": _torch_pair_values(ta, tb, pair_mode).double().numpy()}
        for path, got in results.items():
            tol = IOU_TOL["torch32"] if (path != "numba" and dtype == np.float32) else numba_tol
            if path == "torch_cpu" and dtype == np.float32:
                tol = 1e-7  # numba in float64, cast to float32
            assert np.isfinite(got).all(), (case, path)
            assert np.abs(got - ref).max() <= tol, (case, mode, path, np.abs(got - ref).max())
            assert ((got >= 0) & (got <= 1)).all()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_iou_identical_touching_and_zero_size_boxes(dtype):
    # sizes and positions exact in float32 (2**-7 m = 7.8 mm for the "1 cm" box), so that the boxes built to touch
    # do touch in float32 too (a float32 150.01 m is 7.6 um off and makes two 1 cm boxes overlap: IoU 3e-4)
    base = np.array([[FAR, -FAR, 0.8125, 4.5, 1.875, 1.625, 0.0],
                     [150.0, 3.0, 2.0**-8, 2.0**-7, 2.0**-7, 2.0**-7, math.pi],
                     [60.0, 0.0, 2.0, 100.0, 2.5, 4.0, -math.pi]])
    # a box touching each one at a face (moved by its length along x) and at a corner (moved by length and width)
    face, corner = base.copy(), base.copy()
    face[:, 0] += base[:, 3]
    corner[:, 0] += base[:, 3]
    corner[:, 1] += base[:, 4]
    stacked = base.copy()
    stacked[:, 2] += base[:, 5]  # touching in z: the top face of one is the bottom of the other
    zero = base.copy()
    zero[:, 3:6] = 0.0
    flat = base.copy()
    flat[:, 5] = 0.0  # no height: BEV overlap, no volume
    for a, b, want3, wantb, tol in (
        (base, base, 1.0, 1.0, 1e-6),   # identical
        (base, face, 0.0, 0.0, 1e-6), (base, corner, 0.0, 0.0, 1e-6),
        (base, stacked, 0.0, 1.0, 1e-6),
        (base, zero, 0.0, 0.0, 0.0), (zero, zero, 0.0, 0.0, 0.0),
        (flat, flat, 0.0, 1.0, 1e-6),
    ):
        ta, tb = torch.as_tensor(a, dtype=dtype), torch.as_tensor(b, dtype=dtype)
        for name, got3, gotb in (
            ("numba", boxes_iou3d_aligned(ta, tb), boxes_iou_bev_aligned(ta, tb)),
            ("vectorised", _torch_pair_values(ta, tb, MODE_IOU_3D), _torch_pair_values(ta, tb, MODE_IOU_BEV)),
        ):
            assert torch.isfinite(got3).all() and torch.isfinite(gotb).all(), name
            np.testing.assert_allclose(got3.double().numpy(), want3, atol=tol, err_msg=name)
            np.testing.assert_allclose(gotb.double().numpy(), wantb, atol=tol, err_msg=name)
    # matrices: a zero-size box next to real ones gives zeros, never NaN
    m = boxes_iou3d(np.vstack([base, zero]), np.vstack([base, zero]))
    assert np.isfinite(m).all() and np.allclose(np.diag(m), [1, 1, 1, 0, 0, 0], atol=1e-9)
    assert np.isfinite(boxes_iou_bev(torch.as_tensor(zero, dtype=dtype).requires_grad_(True),
                                     torch.as_tensor(base, dtype=dtype)).detach().numpy()).all()


# ---------------------------------------------------------------- NMS
def _nms_paths(boxes, scores, thr):
    """Kept indices from the numba kernel (numpy, float64 tensors, float32 tensors) and the device kernel (f64, f32)."""
    tb, ts = torch.from_numpy(boxes), torch.from_numpy(scores)
    return {"numba": list(nms_bev(boxes, scores, thr)),
            "numba_f32": nms_bev(tb.float(), ts.float(), thr).tolist(),
            "device_f64": _nms_torch(tb, ts, thr, 10**9).tolist(),
            "device_f32": _nms_torch(tb.float(), ts.float(), thr, 10**9).tolist()}


def test_nms_is_translation_scale_and_heading_invariant_at_the_extremes():
    rng = np.random.default_rng(7)
    n = 80
    boxes = np.c_[rng.uniform(0, 30, n), rng.uniform(-6, 6, n), np.full(n, 0.8), rng.uniform(3.5, 5.0, n),
                  rng.uniform(1.6, 2.0, n), np.full(n, 1.6), rng.uniform(-math.pi, math.pi, n)]
    boxes[:, :6] = np.round(boxes[:, :6] * 64) / 64  # exact in float32 after any of the changes below
    scores = np.round(rng.uniform(0, 1, n), 3)
    for thr in (0.1, 0.5):
        want = _nms_paths(boxes, scores, thr)["numba"]
        assert 5 < len(want) < n
        variants = {}
        far = boxes.copy()
        far[:, :2] += (FAR, -FAR)
        variants["far_1e4"] = far
        for scale in (1 / 256, 16.0):  # 1-2 cm boxes; 60-80 m trucks
            s = boxes.copy()
            s[:, :6] *= scale
            variants[f"scale_{scale:g}"] = s
        flipped = boxes.copy()
        flipped[:, 6] = np.where(flipped[:, 6] < 0, flipped[:, 6] + 2 * math.pi, flipped[:, 6] - 2 * math.pi)
        variants["heading_plus_minus_2pi"] = flipped
        for name, v in variants.items():
            for path, got in _nms_paths(v, scores, thr).items():
                assert got == want, (thr, name, path)


def test_nms_identical_touching_and_zero_size_boxes():
    car = [50.0, 2.0, 0.8, 4.5, 1.9, 1.6, math.pi]
    same = np.array([car] * 4)
    same[1, 6] = -math.pi  # the same box written with the other end of the heading range
    same[2, 6] = math.pi - 1e-6
    scores = np.array([0.5, 0.9, 0.9, 0.1])
    for path, got in _nms_paths(same, scores, 0.5).items():
        assert got == [1], path  # identical boxes: the best (first on ties) survives
    # touching at a face and a corner: IoU 0 suppresses nothing, even at threshold 0.01
    touching = np.array([car, [54.5, 2.0, 0.8, 4.5, 1.9, 1.6, 0.0], [54.5, 3.9, 0.8, 4.5, 1.9, 1.6, math.pi]])
    touching[:, :2] += (FAR, FAR)
    for path, got in _nms_paths(touching, np.array([0.9, 0.8, 0.7]), 0.01).items():
        assert got == [0, 1, 2], path
    # zero-size boxes neither suppress nor are suppressed (IoU 0), and nothing is NaN
    zero = np.array([car, car, [50.0, 2.0, 0.8, 0.0, 0.0, 0.0, 0.0]])
    zero[1, 3:6] = 0.0
    for path, got in _nms_paths(zero, np.array([0.3, 0.9, 0.8]), 0.5).items():
        assert got == [1, 2, 0], path


# ---------------------------------------------------------------- box coder
def _coder_sets(rng, n=500):
    """name -> (boxes, anchors) as float64, anchors of the cpu preset's car size near the boxes."""
    def make(x, size, spread=2.0, heading=None):
        g = np.c_[x + rng.uniform(-spread, spread, n), rng.uniform(-15, 15, n), rng.uniform(0.5, 2.0, n),
                  np.tile(size, (n, 1)) * rng.uniform(0.9, 1.1, (n, 3)),
                  rng.uniform(-math.pi, math.pi, n) if heading is None else np.resize(heading, n)]
        a = g.copy()
        a[:, :3] += rng.uniform(-1.0, 1.0, (n, 3))
        a[:, 3:6] = (3.9, 1.6, 1.56)
        a[:, 6] = rng.choice([0.0, math.pi / 2], n)
        return g, a
    return {"150m": make(150.0, (4.5, 1.9, 1.6)), "1e4m": make(FAR, (4.5, 1.9, 1.6)),
            "1cm": make(150.0, (0.01, 0.01, 0.01)), "truck_100m": make(150.0, (100.0, 2.5, 4.0)),
            "heading_pi": make(150.0, (4.5, 1.9, 1.6), heading=HEADINGS_PI),
            "zero_size": make(150.0, (0.0, 0.0, 0.0))}


@pytest.mark.parametrize("sincos", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_box_coder_round_trip_at_the_extremes(sincos, dtype):
    coder = ResidualBoxCoder(encode_angle_by_sincos=sincos)
    eps = torch.finfo(dtype).eps
    for name, (g, a) in _coder_sets(np.random.default_rng(3)).items():
        tg, ta = torch.as_tensor(g, dtype=dtype), torch.as_tensor(a, dtype=dtype)
        deltas = coder.encode(tg, ta)
        back = coder.decode(deltas, ta)
        assert back.dtype == dtype and torch.isfinite(deltas).all() and torch.isfinite(back).all(), name
        ref = tg.double()  # the boxes as given (already rounded to dtype)
        err_centre = (back[:, :3].double() - ref[:, :3]).abs().max().item()
        step = float(np.spacing(np.float32(np.abs(g[:, :2]).max()))) if dtype == torch.float32 else 0.0
        bound = max(1e-5 if dtype == torch.float32 else 1e-12, step)
        assert err_centre <= bound, (name, err_centre, bound)
        if name == "150m" and dtype == torch.float32:
            assert err_centre < 1e-3  # the required bound: below 1 mm at the far end of the range
        size_err = (back[:, 3:6].double() - ref[:, 3:6]).abs()
        if name == "zero_size":
            torch.testing.assert_close(back[:, 3:6].double(), torch.full_like(size_err, coder.min_size))
        else:
            assert (size_err <= 4 * eps * ref[:, 3:6]).all(), (name, float((size_err / ref[:, 3:6]).max()))
        dh = normalize_heading((back[:, 6].double() - ref[:, 6]).numpy())
        assert np.abs(dh).max() <= (1e-6 if dtype == torch.float32 else 1e-12), (name, np.abs(dh).max())


# ---------------------------------------------------------------- points in boxes
def _surface_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N, M) long-double distance of each point outside each box's surface (<= 0: inside or on it)."""
    p = points[:, None, :3].astype(np.longdouble)
    b = boxes[None].astype(np.longdouble)
    rx, ry = p[..., 0] - b[..., 0], p[..., 1] - b[..., 1]
    c, s = np.cos(b[..., 6]), np.sin(b[..., 6])
    u, v = rx * c + ry * s, -rx * s + ry * c
    return np.maximum.reduce([np.abs(u) - b[..., 3] / 2, np.abs(v) - b[..., 4] / 2,
                              np.abs(p[..., 2] - b[..., 2]) - b[..., 5] / 2]).astype(np.float64)


def _boxes_and_face_points(rng, centre, size, n_boxes=12, n_points=3000):
    """Boxes at `centre` (headings include +-pi) and points crowded around their faces (1e-9 .. 1e-2 of a size
    inside or outside), plus points exactly on faces of axis-aligned boxes."""
    size = np.asarray(size, float)
    boxes = np.c_[centre[0] + rng.uniform(-3, 3, n_boxes) * size[0], centre[1] + rng.uniform(-3, 3, n_boxes) * size[1],
                  rng.uniform(0, 2, n_boxes), np.tile(size, (n_boxes, 1)),
                  np.resize((*HEADINGS_PI, 0.0, 0.7, -2.2), n_boxes)]
    j = rng.integers(0, n_boxes, n_points)
    local = rng.uniform(-0.5, 0.5, (n_points, 3))
    axis = rng.integers(0, 3, n_points)
    local[np.arange(n_points), axis] = rng.choice([-0.5, 0.5], n_points) * (
        1 + rng.choice([-1, 1], n_points) * 10.0 ** rng.uniform(-9, -2, n_points))
    local *= boxes[j, 3:6]
    c, s = np.cos(boxes[j, 6]), np.sin(boxes[j, 6])
    pts = np.c_[boxes[j, 0] + local[:, 0] * c - local[:, 1] * s, boxes[j, 1] + local[:, 0] * s + local[:, 1] * c,
                boxes[j, 2] + local[:, 2], np.zeros(n_points)]
    return boxes, pts


@pytest.mark.parametrize("case, centre, size", [
    ("150m", (150.0, 5.0), (4.5, 1.9, 1.6)), ("1e4m", (FAR, -FAR), (4.5, 1.9, 1.6)),
    ("1cm", (150.0, 5.0), (0.01, 0.01, 0.01)), ("1cm_1e4m", (FAR, FAR), (0.01, 0.01, 0.01)),
    ("truck_100m", (100.0, 0.0), (100.0, 2.5, 4.0)), ("truck_1e4m", (FAR, FAR), (100.0, 2.5, 4.0)),
])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_points_in_boxes_at_the_extremes(case, centre, size, dtype):
    boxes, pts = _boxes_and_face_points(np.random.default_rng(11), centre, size)
    P, B = pts.astype(dtype), boxes.astype(dtype)
    dist = _surface_distance(P.astype(np.float64), B.astype(np.float64))
    # points within this distance of a face may go either way: 4 steps of the dtype at the box-frame coordinates
    radius = np.linalg.norm(np.asarray(size)) / 2 + 1.0
    margin = 4 * np.finfo(dtype).eps * radius * (1.0 if dtype == np.float32 else 64.0)
    decided = np.abs(dist) > margin
    assert decided.mean() > 0.5 and (dist[decided] <= 0).sum() > 100  # many points inside and near faces
    want = dist <= 0
    tp, tb = torch.from_numpy(P), torch.from_numpy(B)
    for path, mask in (("numba", points_in_boxes_mask(P, B)),
                       ("numba_torch_cpu", points_in_boxes_mask(tp, tb).numpy()),
                       ("device", _points_in_boxes_mask_torch(tp, tb, 0.0).numpy())):
        wrong = (mask != want) & decided
        assert not wrong.any(), (case, path, int(wrong.sum()), float(np.abs(dist[wrong]).max()))
    # counts and first-box indices agree with the membership matrix
    counts, idx = points_in_boxes(P, B)
    mask = points_in_boxes_mask(P, B)
    assert np.array_equal(counts, mask.sum(0)) and np.array_equal(idx, np.where(mask.any(1), mask.argmax(1), -1))
    dc, di = _points_in_boxes_torch(tp, tb, 0.0)
    dmask = _points_in_boxes_mask_torch(tp, tb, 0.0)
    assert torch.equal(dc, dmask.sum(0)) and torch.equal(di, torch.where(dmask.any(1), dmask.int().argmax(1), -1))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_points_in_zero_size_identical_and_touching_boxes(dtype):
    car = [FAR, -FAR, 0.8, 4.5, 1.9, 1.6, math.pi]
    boxes = np.array([car, car,                                   # identical: a point counts in both
                      [FAR - 4.5, -FAR, 0.8, 4.5, 1.9, 1.6, 0.0],  # touches the first at the face x = FAR - 2.25
                      [FAR, -FAR, 0.8, 0.0, 0.0, 0.0, 0.3]], dtype=dtype)  # zero size at the first one's centre
    pts = np.array([[FAR, -FAR, 0.8, 0.0],            # the centre: in 0, 1 and the zero-size box 3
                    [FAR - 2.25, -FAR + 0.5, 0.8, 0.0],  # on the shared face: in 0, 1 and 2 (faces are inclusive)
                    [FAR + 1.0, -FAR, 0.8, 0.0]], dtype=dtype)
    want = np.array([[1, 1, 0, 1], [1, 1, 1, 0], [1, 1, 0, 0]], dtype=bool)
    tp, tb = torch.from_numpy(pts), torch.from_numpy(boxes)
    for path, mask in (("numba", points_in_boxes_mask(pts, boxes)),
                       ("device", _points_in_boxes_mask_torch(tp, tb, 0.0).numpy())):
        assert np.array_equal(mask, want), (path, mask)
    counts, idx = points_in_boxes(pts, boxes)
    assert counts.tolist() == [3, 3, 1, 1] and idx.tolist() == [0, 0, 0]
