"""Rotated IoU (detbench.ops.iou) against an independent exact reference and at the extremes.

The reference clips box b's rectangle by each edge of box a in world coordinates
(Sutherland-Hodgman, general half-planes) in exact rational arithmetic (fractions), so
it shares neither the local frame nor the axis-aligned clipping of the implementation.
A Monte Carlo check guards the reference's own conventions (corner order, heading sign).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from numba import njit

from detbench.ops import (
    boxes_iou3d,
    boxes_iou3d_aligned,
    boxes_iou_bev,
    boxes_iou_bev_aligned,
    boxes_overlap_bev,
    iou3d_matrix_nb,
    iou3d_pair_nb,
    iou_bev_matrix_nb,
    iou_bev_pair_nb,
    overlap_bev_pair_nb,
)
from tests.helpers import ref_iou, ref_overlap_bev


# ----------------------------------------------------------------------------------------
# box makers and the paths of each op (the exact reference: tests/helpers.py)
# ----------------------------------------------------------------------------------------
def random_boxes(rng, n, spread=3.0, size=(0.5, 5.0)):
    return np.c_[
        rng.uniform(-spread, spread, (n, 2)),
        rng.uniform(-1.0, 1.0, n),
        rng.uniform(size[0], size[1], (n, 3)),
        rng.uniform(-2 * math.pi, 2 * math.pi, n),
    ]


def both_paths(func, a, b, dtype=torch.float64):
    """Results as numpy of: numpy (numba), torch on the CPU (numba, cast to `dtype`) and
    the vectorised torch kernel (taken when an input requires grad, as on CUDA)."""
    out_np = func(np.asarray(a), np.asarray(b))
    ta, tb = torch.as_tensor(np.asarray(a), dtype=dtype), torch.as_tensor(np.asarray(b), dtype=dtype)
    out_t = func(ta, tb)
    assert out_t.dtype == dtype
    out_v = func(ta.clone().requires_grad_(True), tb)
    assert out_v.requires_grad and out_v.dtype == dtype
    return out_np, out_t.numpy(), out_v.detach().numpy()


def vectorised(func, a, b, dtype=torch.float64):
    """The vectorised torch kernel's result as numpy."""
    ta = torch.as_tensor(np.asarray(a), dtype=dtype).requires_grad_(True)
    return func(ta, torch.as_tensor(np.asarray(b), dtype=dtype)).detach().numpy()


# ----------------------------------------------------------------------------------------
# against the reference
# ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def random_pairs():
    rng = np.random.default_rng(20240611)
    a = random_boxes(rng, 320)
    b = random_boxes(rng, 320)
    # a third of the pairs share the heading or differ by a right angle (parallel edges)
    b[::3, 6] = a[::3, 6] + rng.integers(-2, 3, len(b[::3])) * (math.pi / 2)
    ref3 = np.array([ref_iou(x, y, "3d") for x, y in zip(a, b)])
    refb = np.array([ref_iou(x, y, "bev") for x, y in zip(a, b)])
    refo = np.array([ref_overlap_bev(x, y) for x, y in zip(a, b)])
    return a, b, ref3, refb, refo


def test_random_pairs_match_exact_reference(random_pairs):
    a, b, ref3, refb, refo = random_pairs
    assert (ref3 > 0).sum() > 100 and (ref3 == 0).sum() > 20  # both regimes are exercised
    for func, ref in ((boxes_iou3d, ref3), (boxes_iou_bev, refb), (boxes_overlap_bev, refo)):
        outs = both_paths(func, a[:80], b[:80])
        assert outs[0].dtype == np.float64 and outs[0].shape == (80, 80)
        for m in outs:
            np.testing.assert_allclose(np.diag(m), ref[:80], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(np.diag(func(a, b)), ref, rtol=1e-9, atol=1e-12)
    for func, ref in ((boxes_iou3d_aligned, ref3), (boxes_iou_bev_aligned, refb)):
        for m in both_paths(func, a, b):
            np.testing.assert_allclose(m, ref, rtol=1e-9, atol=1e-12)


def test_full_matrix_matches_reference_and_is_symmetric(monkeypatch):
    rng = np.random.default_rng(7)
    a, b = random_boxes(rng, 12), random_boxes(rng, 9)
    ref = np.array([[ref_iou(x, y) for y in b] for x in a])
    for m in both_paths(boxes_iou3d, a, b):
        np.testing.assert_allclose(m, ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(boxes_iou3d(b, a), boxes_iou3d(a, b).T, rtol=1e-12, atol=1e-14)
    # the parallel kernel (used for large matrices) gives the values of the pair function
    import importlib

    iou_mod = importlib.import_module("detbench.ops.iou")
    monkeypatch.setattr(iou_mod, "_PARALLEL_MIN_PAIRS", 0)
    big_a, big_b = random_boxes(rng, 80), random_boxes(rng, 70)
    serial = np.array([[iou3d_pair_nb(x, y) for y in big_b] for x in big_a])
    np.testing.assert_allclose(boxes_iou3d(big_a, big_b), serial, rtol=0, atol=1e-15)


def test_float32_torch_close_to_reference(random_pairs):
    a, b, ref3, refb, _ = random_pairs
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    ref32 = np.array([ref_iou(x, y, "3d") for x, y in zip(a32.astype(np.float64), b32.astype(np.float64))])
    for m in both_paths(boxes_iou3d_aligned, a32, b32, torch.float32):
        np.testing.assert_allclose(m, ref32, atol=2e-5)
    # numpy float32 input: computed in float64 on the float32 values
    m = boxes_iou3d(a32[:40], b32[:40])
    assert m.dtype == np.float64
    np.testing.assert_allclose(np.diag(m), ref32[:40], rtol=1e-9, atol=1e-12)


def test_reference_conventions_by_monte_carlo():
    """Monte Carlo in world coordinates: tolerance 5 standard errors of the hit fraction."""
    rng = np.random.default_rng(3)
    n = 200_000
    a, b = random_boxes(rng, 8, spread=1.0), random_boxes(rng, 8, spread=1.0)
    for x, y in zip(a, b):
        # sample uniformly in box a (its own frame), then test membership of b in world frame
        u = rng.uniform(-0.5, 0.5, (n, 2)) * x[3:5]
        c, s = math.cos(x[6]), math.sin(x[6])
        wx, wy = x[0] + u[:, 0] * c - u[:, 1] * s, x[1] + u[:, 0] * s + u[:, 1] * c
        rx, ry = wx - y[0], wy - y[1]
        cb, sb = math.cos(y[6]), math.sin(y[6])
        inside = (np.abs(rx * cb + ry * sb) <= y[3] / 2) & (np.abs(-rx * sb + ry * cb) <= y[4] / 2)
        p = inside.mean()
        est = p * x[3] * x[4]
        tol = 5 * x[3] * x[4] * math.sqrt(max(p * (1 - p), 1.0 / n) / n)
        assert abs(boxes_overlap_bev(x[None], y[None])[0, 0] - est) <= tol
        assert abs(ref_overlap_bev(x, y) - est) <= tol


def test_hand_computed_cases():
    a = np.array([[0, 0, 0, 2, 2, 2, 0.0]])
    b = np.array([
        [1, 0, 0, 2, 2, 2, 0.0],          # half overlap: 2 / 6
        [0, 0, 0, 2, 2, 2, math.pi / 4],  # octagon: 8 (sqrt 2 - 1) over 8 - that
        [0, 0, 1, 2, 2, 2, 0.0],          # half height overlap: 4 / 12
    ])
    octagon = 8 * (math.sqrt(2) - 1)
    np.testing.assert_allclose(boxes_overlap_bev(a, b)[0], [2, octagon, 4], rtol=1e-12)
    np.testing.assert_allclose(boxes_iou3d(a, b)[0], [1 / 3, octagon / (8 - octagon), 1 / 3], rtol=1e-12)
    # a 4 x 2 box turned by 90 degrees is the 2 x 4 box
    np.testing.assert_allclose(boxes_iou3d([[5, 5, 0, 4, 2, 1, math.pi / 2]], [[5, 5, 0, 2, 4, 1, 0.0]]), 1.0,
                               atol=1e-12)
    # heading counter-clockwise: a 4 x 1 box turned +90 deg covers +y, not +x
    bar = [[0, 0, 0, 4, 1, 1, math.pi / 2]]
    assert boxes_overlap_bev(bar, [[0, 1.5, 0, 1, 1, 1, 0.0]])[0, 0] == pytest.approx(1.0)
    assert boxes_overlap_bev(bar, [[1.5, 0, 0, 1, 1, 1, 0.0]])[0, 0] == pytest.approx(0.0, abs=1e-12)


# ----------------------------------------------------------------------------------------
# the extremes, one test each
# ----------------------------------------------------------------------------------------
def test_identical_boxes_give_one():
    rng = np.random.default_rng(11)
    boxes = random_boxes(rng, 50)
    boxes[:10, :2] += 1e4
    boxes[10:20, 3:6] = rng.uniform(0.01, 0.02, (10, 3))
    boxes[20:30, 3:6] = rng.uniform(90, 100, (10, 3))
    for dt in (torch.float64, torch.float32):
        out = boxes_iou3d_aligned(torch.as_tensor(boxes, dtype=dt), torch.as_tensor(boxes, dtype=dt))
        np.testing.assert_allclose(out.numpy(), 1.0, atol=1e-6)
        np.testing.assert_allclose(
            torch.diagonal(boxes_iou_bev(torch.as_tensor(boxes, dtype=dt), torch.as_tensor(boxes, dtype=dt))).numpy(),
            1.0, atol=1e-6)
    np.testing.assert_allclose(np.diag(boxes_iou3d(boxes, boxes)), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.diag(boxes_iou_bev(boxes.astype(np.float32), boxes.astype(np.float32))), 1.0,
                               atol=1e-6)


def test_touching_boxes_give_zero():
    h = 0.7
    c, s = math.cos(h), math.sin(h)
    a = np.array([3.0, -2.0, 0.5, 4.0, 2.0, 1.0, h])
    touching = [
        [4.0, 0, 0, 4, 2, 1, 0.0],                            # axis-aligned, shared edge x = 2
        [0, 2.0, 0, 4, 2, 1, 0.0],                            # shared edge y = 1
        [4.0, 2.0, 0, 4, 2, 1, 0.0],                          # shared corner only
        [0, 0, 2.0, 4, 2, 2, 0.0],                            # stacked: faces touch in z
    ]
    base = np.array([0, 0, 0, 4, 2, 2, 0.0])
    for t in touching:
        for dt in (np.float64, np.float32):
            assert boxes_iou3d(base[None].astype(dt), np.array([t], dtype=dt))[0, 0] == pytest.approx(0, abs=1e-12)
        for dt in (torch.float64, torch.float32):
            assert vectorised(boxes_iou3d, base[None], [t], dt)[0, 0] == pytest.approx(0, abs=1e-12)
    # rotated: b is a moved by its length along its heading, and by its width sideways
    along = a.copy()
    along[:2] += 4.0 * np.array([c, s])
    side = a.copy()
    side[:2] += 2.0 * np.array([-s, c])
    for b in (along, side):
        assert boxes_iou3d(a[None], b[None])[0, 0] == pytest.approx(0, abs=1e-9)
        assert vectorised(boxes_iou_bev, a[None], b[None])[0, 0] == pytest.approx(0, abs=1e-9)
        assert vectorised(boxes_iou_bev, a[None], b[None], torch.float32)[0, 0] == pytest.approx(0, abs=1e-5)


def test_one_box_inside_another():
    big = np.array([[10, 5, 1, 6, 3, 2, 0.4]])
    small = np.array([[10.5, 5.2, 1.1, 1.0, 0.5, 0.4, -1.3]])
    expected = (1.0 * 0.5 * 0.4) / (6 * 3 * 2)
    for m in both_paths(boxes_iou3d, big, small) + both_paths(boxes_iou3d, small, big):
        assert m.reshape(-1)[0] == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(boxes_overlap_bev(big, small), 0.5, rtol=1e-12)
    # same footprint, nested in z
    tall = np.array([[0, 0, 1, 4, 2, 2, 0.3]])
    flat = np.array([[0, 0, 1, 4, 2, 0.5, 0.3]])
    assert boxes_iou3d(tall, flat)[0, 0] == pytest.approx(0.25, rel=1e-12)


@pytest.mark.parametrize("eps", [1e-7, -1e-7, 1e-9, 1e-12])
def test_nearly_parallel_edges(eps):
    h = 0.9
    a = np.array([1.0, 2.0, 0.0, 4.0, 2.0, 1.0, h])
    cases = []
    for shift in (0.0, 1.0, 3.999999):
        b = a.copy()
        b[0] += shift * math.cos(h)
        b[1] += shift * math.sin(h)
        b[6] = h + eps
        cases.append(b)
    # a box turned by 90 deg + eps: edges parallel to the other pair of edges
    b = a.copy()
    b[3], b[4], b[6] = 2.0, 4.0, h + math.pi / 2 + eps
    cases.append(b)
    for b in cases:
        ref = ref_iou(a, b)
        for m in both_paths(boxes_iou3d, a[None], b[None]):
            assert m[0, 0] == pytest.approx(ref, rel=1e-9, abs=1e-12)
    # the IoU is continuous at eps -> 0: shifted by 1 m along the heading gives 3/5
    assert boxes_iou3d(a[None], cases[1][None])[0, 0] == pytest.approx(3.0 / 5.0, abs=1e-6)
    assert boxes_iou3d(a[None], cases[0][None])[0, 0] == pytest.approx(1.0, abs=1e-6)


def test_headings_at_pi_and_outside_range():
    base = np.array([2.0, 1.0, 0.0, 4.5, 1.8, 1.5, 0.0])
    other = np.array([2.5, 1.3, 0.1, 4.0, 2.0, 1.5, 0.6])
    ref = ref_iou(base, other)
    for k in (-3, -1, 1, 2, 50):
        b1, b2 = base.copy(), other.copy()
        b1[6] += 2 * math.pi * k
        b2[6] -= 2 * math.pi * k
        for m in both_paths(boxes_iou3d, b1[None], b2[None]):
            assert m[0, 0] == pytest.approx(ref, rel=1e-9)
    # +pi and -pi are the same heading; a rectangle turned by pi is itself
    p = base.copy()
    p[6] = math.pi
    q = base.copy()
    q[6] = -math.pi
    for m in both_paths(boxes_iou3d, np.stack([p, q, base]), np.stack([q, base, p])):
        np.testing.assert_allclose(np.diag(m), 1.0, atol=1e-9)
    for hp in (math.pi, -math.pi, 3 * math.pi, 7.5):
        x = other.copy()
        x[6] = hp
        assert boxes_iou3d(base[None], x[None])[0, 0] == pytest.approx(ref_iou(base, x), rel=1e-9)


@pytest.mark.parametrize("scale", [0.01, 0.5, 100.0])
def test_tiny_and_huge_boxes(scale):
    """IoU is scale-invariant: 1 cm and 100 m boxes give the same values as 1 m boxes."""
    rng = np.random.default_rng(5)
    a, b = random_boxes(rng, 40, spread=0.7, size=(0.5, 1.5)), random_boxes(rng, 40, spread=0.7, size=(0.5, 1.5))
    b[:, 2] = a[:, 2] + rng.uniform(-0.3, 0.3, 40)
    unit = boxes_iou3d_aligned(a, b)
    sa, sb = a.copy(), b.copy()
    sa[:, :6] *= scale
    sb[:, :6] *= scale
    assert (unit > 0.05).sum() >= 15
    for out in both_paths(boxes_iou3d_aligned, sa, sb):
        np.testing.assert_allclose(out, unit, rtol=1e-9, atol=1e-12)
    for out in both_paths(boxes_iou3d_aligned, sa, sb, torch.float32):
        np.testing.assert_allclose(out, unit, atol=1e-4)
    np.testing.assert_allclose(boxes_overlap_bev(sa[:5], sb[:5]), boxes_overlap_bev(a[:5], b[:5]) * scale**2,
                               rtol=1e-9, atol=1e-15)


def test_far_from_origin_no_cancellation():
    rng = np.random.default_rng(9)
    a, b = random_boxes(rng, 60, spread=1.5), random_boxes(rng, 60, spread=1.5)
    # offsets in multiples of 1/256 m so that the shifted float32 values are exact
    a[:, :3] = np.round(a[:, :3] * 256) / 256
    b[:, :3] = np.round(b[:, :3] * 256) / 256
    near = boxes_iou3d_aligned(a, b)
    shift = np.array([1e4, -1e4, 0.0])
    fa, fb = a.copy(), b.copy()
    fa[:, :3] += shift
    fb[:, :3] += shift
    np.testing.assert_allclose(boxes_iou3d_aligned(fa, fb), near, rtol=0, atol=1e-10)
    for out in both_paths(boxes_iou3d_aligned, fa, fb):
        np.testing.assert_allclose(out, near, atol=1e-10)
    # float32: x = 1e4 has a 1 mm grid, a world-frame computation would be off by ~1e-3
    ta, tb = torch.from_numpy(fa).float(), torch.from_numpy(fb).float()
    assert torch.equal(ta[:, :3].double(), torch.from_numpy(fa[:, :3]))  # inputs are exact
    near32 = vectorised(boxes_iou3d_aligned, a, b, torch.float32)
    ref32 = np.array([ref_iou(x, y) for x, y in zip(ta.double().numpy() - np.r_[shift, 0, 0, 0, 0],
                                                      tb.double().numpy() - np.r_[shift, 0, 0, 0, 0])])
    for out in both_paths(boxes_iou3d_aligned, fa, fb, torch.float32):
        np.testing.assert_allclose(out, ref32, atol=1e-5)
    np.testing.assert_allclose(near32, ref32, atol=1e-5)
    np.testing.assert_allclose(boxes_iou3d(fa.astype(np.float32), fb.astype(np.float32)).diagonal(), ref32, atol=1e-9)


def test_zero_size_boxes_give_zero_not_nan():
    # a point, a zero-width box, a flat box (dz = 0, footprint 2 x 1)
    z = np.array([[0, 0, 0, 0, 0, 0, 0.3], [0, 0, 0, 2, 0, 1, 0.0], [0, 0, 0, 2, 1, 0, 0.0]])
    n = np.array([[0, 0, 0, 2, 2, 2, 0.0], [0, 0, 0, 0, 0, 0, 0.0]])
    expected = {
        boxes_iou3d: (np.zeros((3, 2)), np.zeros((3, 3))),
        boxes_iou_bev: (np.array([[0, 0], [0, 0], [0.5, 0]]), np.diag([0, 0, 1.0])),
        boxes_overlap_bev: (np.array([[0, 0], [0, 0], [2.0, 0]]), np.diag([0, 0, 2.0])),
    }
    for func, (exp_zn, exp_zz) in expected.items():
        for dt in (torch.float64, torch.float32):
            for got, exp in ((both_paths(func, z, n, dt), exp_zn), (both_paths(func, z, z, dt), exp_zz)):
                for m in got:
                    assert np.isfinite(m).all()
                    np.testing.assert_allclose(m, exp, atol=1e-6)


def test_empty_inputs_give_empty_outputs():
    e, two = np.zeros((0, 7)), np.ones((2, 7))
    for func in (boxes_iou3d, boxes_iou_bev, boxes_overlap_bev):
        assert func(e, two).shape == (0, 2) and func(e, two).dtype == np.float64
        assert func(two, e).shape == (2, 0)
        assert func(e, e).shape == (0, 0)
        assert func(np.zeros(0), two).shape == (0, 2)
        for grad in (False, True):
            t = func(torch.zeros((0, 7), requires_grad=grad), torch.ones((3, 7)))
            assert isinstance(t, torch.Tensor) and t.shape == (0, 3) and t.dtype == torch.float32
            t = func(torch.ones((3, 7), dtype=torch.float64, requires_grad=grad), torch.zeros((0, 7)))
            assert t.shape == (3, 0) and t.dtype == torch.float64
        # far apart: the vectorised kernel skips every pair
        assert vectorised(func, two, two + 100).shape == (2, 2) and vectorised(func, two, two + 100).max() == 0
    assert boxes_iou3d_aligned(e, e).shape == (0,)
    assert boxes_iou3d_aligned(torch.zeros((0, 7)), torch.zeros((0, 7))).shape == (0,)
    assert boxes_iou3d_aligned(torch.zeros((0, 7), requires_grad=True), torch.zeros((0, 7))).shape == (0,)


def test_types_devices_and_extra_columns():
    a = np.array([[0, 0, 0, 2, 2, 2, 0.0, 9.0, 9.0]])  # extra columns (velocity) are ignored
    b = torch.tensor([[1, 0, 0, 2, 2, 2, 0.0]], dtype=torch.float32)
    out = boxes_iou3d(a, b)  # numpy beside a tensor: torch path on the tensor's device
    assert isinstance(out, torch.Tensor) and out.device == b.device
    assert out.dtype == torch.float64  # a is float64
    assert out.item() == pytest.approx(1 / 3)
    assert boxes_iou3d(a[0, :7], a[0, :7])[0, 0] == pytest.approx(1.0)  # single 1-D boxes
    out = boxes_iou3d(torch.from_numpy(a).requires_grad_(True), b)
    assert out.dtype == torch.float64 and out.item() == pytest.approx(1 / 3)


def test_errors_name_the_function_and_the_fix():
    good = np.ones((2, 7))
    with pytest.raises(ValueError, match=r"boxes_iou3d.*shape \(M, 7\)"):
        boxes_iou3d(np.ones((2, 6)), good)
    with pytest.raises(ValueError, match=r"boxes_iou_bev.*row 1.*NaN"):
        boxes_iou_bev(good, np.array([[0, 0, 0, 1, 1, 1, 0], [np.nan, 0, 0, 1, 1, 1, 0]]))
    with pytest.raises(ValueError, match="negative size"):
        boxes_iou3d(good, [[0, 0, 0, -1, 1, 1, 0]])
    with pytest.raises(ValueError, match="same number of rows"):
        boxes_iou3d_aligned(good, np.ones((3, 7)))


def test_numba_callable_pair_functions():
    @njit
    def user_kernel(a, b):
        out = np.zeros((a.shape[0], 3))
        for i in range(a.shape[0]):
            out[i, 0] = iou3d_pair_nb(a[i], b[i])
            out[i, 1] = iou_bev_pair_nb(a[i], b[i])
            out[i, 2] = overlap_bev_pair_nb(a[i], b[i])
        return out

    rng = np.random.default_rng(2)
    a, b = random_boxes(rng, 25), random_boxes(rng, 25)
    out = user_kernel(a, b)
    np.testing.assert_allclose(out[:, 0], boxes_iou3d_aligned(a, b), rtol=1e-12, atol=1e-15)

    @njit
    def user_matrix(a, b):
        return iou3d_matrix_nb(a, b), iou_bev_matrix_nb(a, b)

    m3, mb = user_matrix(a, b[:7])
    np.testing.assert_allclose(m3, boxes_iou3d(a, b[:7]), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(mb, boxes_iou_bev(a, b[:7]), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out[:, 1], boxes_iou_bev_aligned(a, b), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out[:, 2], np.diag(boxes_overlap_bev(a, b)), rtol=1e-12, atol=1e-15)


def test_torch_gradient_is_finite_and_correct():
    a = torch.tensor([[0.1, 0.2, 0.0, 4.0, 2.0, 1.5, 0.3]], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([[0.9, -0.3, 0.2, 3.5, 1.8, 1.4, -0.2]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: boxes_iou3d_aligned(x, b), (a,))
    boxes_iou3d(a, b).sum().backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
