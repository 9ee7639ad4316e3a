"""The point operations of detbench.ops (sampling, grouping, interpolate, roi_pool) against brute-force numpy
references; numba vs torch path parity; the empty-slot rule of every op that has empty slots."""
from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch

from detbench.ops import (
    EMPTY_INDEX,
    ball_query,
    cylinder_query,
    farthest_point_sample,
    from_canonical,
    group_linear,
    group_neighbours,
    group_points,
    grouping,
    interpolate,
    points_in_boxes,
    roi_point_pool,
    roi_pool,
    sampling,
    three_interpolate,
    three_nn,
    three_nn_interpolate,
    to_canonical,
)
import tools.bench_points

BACKENDS = ["numba", "torch"]


def offsets(counts):
    return np.concatenate([[0], np.cumsum(counts)]).astype(int)


def clouds(seed, counts, spread=3.0):
    """Concatenated float32 (N, 3) points of len(counts) frames, clumped so balls hold many points."""
    rng = np.random.default_rng(seed)
    parts = []
    for n in counts:
        centres = rng.uniform(-spread, spread, (4, 3))
        parts.append(centres[rng.integers(0, 4, n)] + rng.normal(0, 0.6, (n, 3)))
    return torch.from_numpy(np.concatenate(parts or [np.zeros((0, 3))]).astype(np.float32))


def d2_to(p, c):
    """float64 squared distances of rows p (n, 3) to one point c, in the ops' order of operations."""
    p, c = np.asarray(p, np.float64), np.asarray(c, np.float64)
    dx, dy, dz = p[:, 0] - c[0], p[:, 1] - c[1], p[:, 2] - c[2]
    return dx * dx + dy * dy + dz * dz


# ---------------------------------------------------------------------------- references
def ref_fps(xyz, counts, samples):
    p, out = xyz.numpy().astype(np.float64), []
    for b, (s, n) in enumerate(zip(offsets(counts)[:-1], counts)):
        m = samples[b]
        if m == 0:
            continue
        temp, sel = np.full(n, np.inf), [0]
        for _ in range(1, min(n, m)):
            temp = np.minimum(temp, d2_to(p[s:s + n], p[s + sel[-1]]))
            sel.append(int(np.argmax(temp)))  # first index of the maximum
        out += [s + sel[k % len(sel)] for k in range(m)]
    return np.array(out, dtype=np.int64)


def ref_ball(xyz, centres, pc, qc, r, ns):
    p, q = xyz.numpy(), centres.numpy()
    po, qo = offsets(pc), offsets(qc)
    idx = np.full((len(q), ns), -1)
    for b in range(len(pc)):
        for c in range(qo[b], qo[b + 1]):
            hits = po[b] + np.flatnonzero(d2_to(p[po[b]:po[b + 1]], q[c]) <= r * r)[:ns]
            if hits.size:
                idx[c] = np.concatenate([hits, np.full(ns - hits.size, hits[0])])
    return idx


def ref_three_nn(t, s, tc, sc):
    t, s = t.numpy(), s.numpy()
    to, so = offsets(tc), offsets(sc)
    dist, idx = np.full((len(t), 3), np.inf), np.full((len(t), 3), -1)
    for b in range(len(tc)):
        for i in range(to[b], to[b + 1]):
            d2 = d2_to(s[so[b]:so[b + 1]], t[i])
            order = np.argsort(d2, kind="stable")[:3]  # ties: lower index first
            dist[i, :len(order)], idx[i, :len(order)] = np.sqrt(d2[order]), so[b] + order
    return dist, idx


def ref_roi(xyz, rois, feats, pc, rc, ns, extra):
    """Independent rule: canonical coordinates by numpy, inclusive faces, sampling rule of the docs."""
    p, b = xyz.numpy().astype(np.float64), rois.numpy().astype(np.float64)
    po, ro = offsets(pc), offsets(rc)
    out = np.zeros((len(b), ns, 3 + feats.shape[1]))
    idx = np.full((len(b), ns), -1)
    for f in range(len(pc)):
        for r in range(ro[f], ro[f + 1]):
            x, y, z, dx, dy, dz, h = b[r]
            rel = p[po[f]:po[f + 1]] - [x, y, z]
            u = rel[:, 0] * math.cos(h) + rel[:, 1] * math.sin(h)
            v = -rel[:, 0] * math.sin(h) + rel[:, 1] * math.cos(h)
            inside = po[f] + np.flatnonzero((np.abs(u) <= dx / 2 + extra) & (np.abs(v) <= dy / 2 + extra)
                                            & (np.abs(rel[:, 2]) <= dz / 2 + extra))
            k = inside.size
            if k == 0:
                continue
            sel = inside[[(j * k) // ns if k > ns else j % k for j in range(ns)]]
            idx[r] = sel
            rel = p[sel] - [x, y, z]
            out[r, :, 0] = rel[:, 0] * math.cos(h) + rel[:, 1] * math.sin(h)
            out[r, :, 1] = -rel[:, 0] * math.sin(h) + rel[:, 1] * math.cos(h)
            out[r, :, 2] = rel[:, 2]
            out[r, :, 3:] = feats.numpy()[sel]
    return out, idx


# ---------------------------------------------------------------------------- farthest point sampling
@pytest.mark.parametrize("backend", BACKENDS)
def test_fps_matches_reference_batched(backend):
    counts, samples = [300, 0, 50, 7, 1], [64, 0, 50, 12, 3]
    xyz = clouds(0, counts)
    got = farthest_point_sample(xyz, samples, counts, backend=backend)
    assert got.dtype == torch.int64 and got.shape == (sum(samples),)
    np.testing.assert_array_equal(got.numpy(), ref_fps(xyz, counts, samples))
    # frame 3 has 7 points for 12 samples: its 7 FPS samples, then the same again cyclically
    f3 = got[114:126].numpy()
    assert sorted(f3[:7]) == list(range(350, 357)) and (f3[7:] == f3[:5]).all()
    assert (got[126:] == 357).all()  # a one-point frame repeats its point


@pytest.mark.parametrize("backend", BACKENDS)
def test_fps_ties_duplicates_and_edges(backend):
    same = torch.ones((10, 3))
    assert farthest_point_sample(same, 4, backend=backend).tolist() == [0, 0, 0, 0]
    assert farthest_point_sample(same, 12, backend=backend).tolist() == [0] * 12
    # the corners of a square: 3 ties at the first step, the lowest index wins
    sq = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0]])
    # row 4 duplicates row 1, so after 0, 3, 1, 2 every distance is 0 and row 0 comes again (reference rule)
    assert farthest_point_sample(sq, 5, backend=backend).tolist() == [0, 3, 1, 2, 0]
    assert farthest_point_sample(torch.zeros((0, 3)), 0, backend=backend).shape == (0,)
    assert farthest_point_sample(torch.zeros((0, 3)), [], counts=[], backend=backend).shape == (0,)
    assert farthest_point_sample(sq, [0, 0], counts=[2, 3], backend=backend).shape == (0,)
    with pytest.raises(ValueError, match="frame 1 has no points"):
        farthest_point_sample(sq, [1, 2], counts=[5, 0], backend=backend)


def test_fps_numba_equals_torch_on_a_larger_cloud():
    xyz = clouds(3, [2000, 1500], spread=20.0)
    a = farthest_point_sample(xyz, [500, 700], [2000, 1500])
    b = farthest_point_sample(xyz, [500, 700], [2000, 1500], backend="torch")
    assert torch.equal(a, b) and a.unique().numel() == 1200


# ---------------------------------------------------------------------------- ball query and grouping
@pytest.mark.parametrize("backend", BACKENDS)
def test_ball_query_matches_reference(backend):
    pc, qc = [400, 0, 120, 60], [50, 5, 30, 0]
    xyz = clouds(1, pc)
    rng = np.random.default_rng(2)
    centres = torch.from_numpy(rng.uniform(-4, 4, (sum(qc), 3)).astype(np.float32))
    for r, ns in ((0.5, 8), (1.3, 32), (5.0, 16)):
        got = ball_query(xyz, centres, r, ns, pc, qc, backend=backend)
        ref = ref_ball(xyz, centres, pc, qc, r, ns)
        np.testing.assert_array_equal(got.index.numpy(), ref)
        np.testing.assert_array_equal(got.empty.numpy(), ref[:, 0] < 0)
        assert got.empty[50:55].all()  # frame 1 has no points
        assert got.count.max() <= ns and (got.count[~got.empty] >= 1).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ball_query_radius_is_inclusive_and_frames_are_separate(backend, dtype):
    r = 0.5
    xyz = torch.tensor([[r, 0, 0], [0, -r, 0], [0, 0, r * (1 + 1e-6)], [0, 0, 0], [0, r, 0]], dtype=dtype)
    bq = ball_query(xyz, torch.zeros((1, 3), dtype=dtype), r, 5, backend=backend)
    # exactly on the sphere counts (d^2 <= r^2); just outside does not
    assert bq.index.tolist() == [[0, 1, 3, 4, 0]] and bq.count.tolist() == [4]
    # split into two frames: frame 1's centre sees only frame 1's points, though frame 0's are as close
    bq2 = ball_query(xyz, torch.zeros((2, 3), dtype=dtype), r, 3, [2, 3], [1, 1], backend=backend)
    assert bq2.index.tolist() == [[0, 1, 0], [3, 4, 3]] and bq2.count.tolist() == [2, 2]


@pytest.mark.parametrize("backend", BACKENDS)
def test_ball_query_extremes(backend):
    same = torch.full((6, 3), 2.0)
    bq = ball_query(same, torch.tensor([[2.0, 2, 2], [9, 9, 9], [1e9, -1e9, 0]]), 0.1, 4, backend=backend)
    assert bq.index.tolist() == [[0, 1, 2, 3], [-1] * 4, [-1] * 4]
    assert bq.empty.tolist() == [False, True, True] and bq.count.tolist() == [4, 0, 0]
    one = ball_query(torch.tensor([[0.0, 0, 0]]), torch.tensor([[0.05, 0, 0]]), 0.1, 3, backend=backend)
    assert one.index.tolist() == [[0, 0, 0]] and one.count.tolist() == [1]
    none = ball_query(torch.zeros((0, 3)), torch.zeros((2, 3)), 1.0, 3, backend=backend)
    assert none.index.tolist() == [[-1] * 3] * 2 and none.empty.all()
    batch0 = ball_query(torch.zeros((0, 3)), torch.zeros((0, 3)), 1.0, 3, [], [], backend=backend)
    assert batch0.index.shape == (0, 3) and batch0.empty.shape == (0,)


def test_grouping_zero_for_empty_and_relative_coordinates():
    xyz = torch.tensor([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]])
    feats = torch.tensor([[1.0, 2], [3, 4], [5, 6]])
    centres = torch.tensor([[0.5, 0, 0], [-9.0, 0, 0]])
    bq = ball_query(xyz, centres, 0.6, 3)
    g = group_neighbours(xyz, centres, bq.index, feats)
    assert g.shape == (2, 3, 5)
    assert g[0].tolist() == [[-0.5, 0, 0, 1, 2], [0.5, 0, 0, 3, 4], [-0.5, 0, 0, 1, 2]]
    assert not g[1].any() and bq.empty.tolist() == [False, True]
    assert group_neighbours(xyz, centres, bq.index).shape == (2, 3, 3)
    assert group_neighbours(xyz, centres, bq.index, feats, use_xyz=False).shape == (2, 3, 2)
    assert group_points(torch.zeros((0, 4)), torch.full((2, 3), -1)).shape == (2, 3, 4)
    with pytest.raises(ValueError, match="group_points: index holds row 7"):
        group_points(feats, torch.tensor([[7]]))


def test_grouping_gradcheck_float64():
    xyz = clouds(4, [40]).double()
    centres = xyz[:6].clone()
    centres[5] += 100.0  # one empty ball
    bq = ball_query(xyz, centres, 1.0, 5)
    assert bq.empty[5] and not bq.empty[:5].any()
    feats = torch.randn(40, 3, dtype=torch.float64, requires_grad=True)
    pts = xyz.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: group_points(f, bq.index), (feats,))
    assert torch.autograd.gradcheck(lambda p, f: group_neighbours(p, centres, bq.index, f), (pts, feats))
    group_points(feats, bq.index)[5].sum().backward()
    assert not feats.grad.any()  # an empty ball sends no gradient anywhere


@pytest.mark.parametrize("with_features,with_bias", [(True, True), (True, False), (False, True)])
def test_group_linear_equals_linear_of_grouped(with_features, with_bias):
    xyz = clouds(7, [60, 25])
    centres = torch.cat([xyz[:5], xyz[60:63], torch.tensor([[200.0, 0, 0]])])  # the last ball is empty
    bq = ball_query(xyz, centres, 1.0, 6, xyz_counts=[60, 25], centre_counts=[5, 4])
    assert bq.empty[-1] and ((bq.count > 0) & (bq.count < 6)).any()  # partly filled balls (slots repeat) too
    index = bq.index.clone()
    index[0, 5] = -1  # one empty slot in a filled ball: zero input, as group_neighbours has it
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(85, 4, generator=gen) if with_features else None
    weight = torch.randn(8, 3 + (4 if with_features else 0), generator=gen)
    bias = torch.randn(8, generator=gen) if with_bias else None
    want = torch.nn.functional.linear(group_neighbours(xyz, centres, index, feats), weight, bias)
    got = group_linear(xyz, centres, index, feats, weight, bias)
    assert got.shape == want.shape == (9, 6, 8)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    empty = bias if with_bias else torch.zeros(8)
    assert torch.equal(got[-1], empty.expand(6, 8)) and torch.equal(got[0, 5], empty)  # as a zero input row


def test_group_linear_gradcheck_and_errors():
    xyz = clouds(8, [30]).double()
    centres = xyz[:4].clone()
    centres[3] += 100.0
    bq = ball_query(xyz, centres, 1.0, 4)
    gen = torch.Generator().manual_seed(1)
    args = [xyz.clone(), centres.clone(), torch.randn(30, 2, dtype=torch.float64, generator=gen),
            torch.randn(5, 5, dtype=torch.float64, generator=gen), torch.randn(5, dtype=torch.float64, generator=gen)]
    args = [a.requires_grad_(True) for a in args]
    assert torch.autograd.gradcheck(lambda p, c, f, w, b: group_linear(p, c, bq.index, f, w, b), args)
    with pytest.raises(ValueError, match=r"group_linear: weight must be \(O, 3 \+ C\) = \(O, 5\)"):
        group_linear(xyz, centres, bq.index, args[2], torch.zeros(5, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match="group_linear: index holds row 30"):
        group_linear(xyz, centres, torch.tensor([[30]]), None, torch.zeros(2, 3, dtype=torch.float64))


# ---------------------------------------------------------------------------- three nearest neighbours
@pytest.mark.parametrize("backend", BACKENDS)
def test_three_nn_matches_reference(backend):
    tc, sc = [300, 40, 10, 5, 0], [80, 2, 1, 0, 4]
    t, s = clouds(5, tc), clouds(6, sc)
    dist, idx = three_nn(t, s, tc, sc, backend=backend)
    rd, ri = ref_three_nn(t, s, tc, sc)
    np.testing.assert_array_equal(idx.numpy(), ri)
    # torch.sqrt on CPU is not always correctly rounded (1 ulp); both backends take it from torch
    np.testing.assert_allclose(dist.numpy(), rd, rtol=1e-15, atol=0)
    assert torch.equal(dist, three_nn(t, s, tc, sc, backend="torch" if backend == "numba" else "numba")[0])
    assert (idx[300:340, 2] == -1).all() and (idx[340:350, 1:] == -1).all() and (idx[350:355] == -1).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_three_nn_ties_flat_and_far_targets(backend):
    s = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 0], [0, 0, 0]])
    t = torch.tensor([[0.0, 0, 0], [0.0, 0, 3.0], [1e6, 0, 0]])
    _, idx = three_nn(t, s, backend=backend)
    assert idx[0].tolist() == [4, 5, 0]  # two at distance 0 (lower row first), then four ties at 1
    assert idx[1].tolist() == [4, 5, 0] and idx[2].tolist() == [0, 4, 5]
    flat = clouds(7, [200]) * torch.tensor([1.0, 1.0, 0.0])  # z == 0: a degenerate grid axis
    tt = clouds(8, [50])
    np.testing.assert_array_equal(three_nn(tt, flat, backend=backend)[1].numpy(),
                                  ref_three_nn(tt, flat, [50], [200])[1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_three_nn_all_sources_identical(backend):
    # every frame's sources coincide (zero extent: the CPU kernel's one-cell grid): frame 0 has five
    # copies of one point, frame 1 two copies of another (fewer than three); targets on the point,
    # near it and 1e6 m away
    s = torch.tensor([[1.0, 2.0, 3.0]] * 5 + [[-4.0, 0.5, 1.0]] * 2, dtype=torch.float64)
    t = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [1e6, -1e6, 5.0], [2.0, 2.0, 2.0], [-4.0, 0.5, 1.0]],
                     dtype=torch.float64)
    tc, sc = [3, 2], [5, 2]
    dist, idx = three_nn(t, s, tc, sc, backend=backend)
    assert idx.tolist() == [[0, 1, 2]] * 3 + [[5, 6, -1]] * 2  # ties: the lowest rows
    np.testing.assert_allclose(dist.numpy(), ref_three_nn(t, s, tc, sc)[0], rtol=1e-15, atol=0)
    other = "torch" if backend == "numba" else "numba"
    assert all(torch.equal(a, b) for a, b in zip((dist, idx), three_nn(t, s, tc, sc, backend=other)))
    # one-hot source features read the weights back: finite, equal between the copies, summing to one
    w = three_nn_interpolate(t, s, torch.eye(7, dtype=torch.float64), tc, sc, backend=backend)
    assert torch.isfinite(w).all()
    np.testing.assert_allclose(w.sum(1).numpy(), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w[:3, :3].numpy(), 1 / 3, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w[3:, 5:].numpy(), 0.5, rtol=0, atol=1e-12)
    # a feature shared by the copies comes back unchanged at every target
    shared = torch.tensor([[0.25, -7.0, 3e3]] * 5 + [[1.5, 0.0, -2.0]] * 2, dtype=torch.float64)
    out = three_nn_interpolate(t, s, shared, tc, sc, backend=backend)
    np.testing.assert_allclose(out.numpy(), shared[[0, 0, 0, 5, 5]].numpy(), rtol=1e-12, atol=0)
    np.testing.assert_allclose(out.numpy(), three_nn_interpolate(t, s, shared, tc, sc, backend=other).numpy(),
                               rtol=1e-15, atol=0)


def test_three_nn_interpolate_values_and_gradcheck():
    tc, sc = [30, 6, 4], [10, 2, 0]
    t, s = clouds(9, tc).double(), clouds(10, sc).double()
    feats = torch.randn(12, 4, dtype=torch.float64, requires_grad=True)
    out = three_nn_interpolate(t, s, feats, tc, sc)
    rd, ri = ref_three_nn(t, s, tc, sc)
    w = np.where(ri >= 0, 1.0 / (rd + 1e-8), 0.0)
    w = w / np.maximum(w.sum(1, keepdims=True), 1e-300)
    ref = (w[..., None] * np.where(ri[..., None] >= 0, feats.detach().numpy()[np.maximum(ri, 0)], 0)).sum(1)
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-12, atol=1e-12)
    assert not out[36:].any()  # frame 2 has no sources: zero features
    assert torch.autograd.gradcheck(lambda f: three_nn_interpolate(t, s, f, tc, sc), (feats,))
    dist, idx = three_nn(t, s, tc, sc)
    wt = torch.rand(40, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda f: three_interpolate(f, idx, wt), (feats,))


# ---------------------------------------------------------------------------- RoI point pooling
def test_canonical_transform_round_trip_and_axes():
    rng = np.random.default_rng(11)
    rois = torch.from_numpy(np.c_[rng.uniform(-50, 50, (5, 3)), rng.uniform(1, 5, (5, 3)), rng.uniform(-3.1, 3.1, 5)])
    pts = torch.from_numpy(rng.uniform(-60, 60, (5, 7, 3)))
    back = from_canonical(to_canonical(pts, rois), rois)
    np.testing.assert_allclose(back.numpy(), pts.numpy(), atol=1e-12)
    np.testing.assert_allclose(to_canonical(pts.numpy(), rois.numpy()), to_canonical(pts, rois).numpy())
    box = torch.tensor([[10.0, 5.0, 1.0, 4.0, 2.0, 1.5, math.pi / 2]], dtype=torch.float64)
    # heading pi/2: the box's +x (forward) is the ego's +y, its left (+y) is the ego's -x
    got = to_canonical(torch.tensor([[10.0, 7.0, 1.5], [9.0, 5.0, 1.0]], dtype=torch.float64), box.expand(2, 7))
    np.testing.assert_allclose(got.numpy(), [[2.0, 0.0, 0.5], [0.0, 1.0, 0.0]], atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_roi_point_pool_matches_reference(backend):
    pc, rc = [600, 0, 200, 150], [5, 2, 3, 0]
    xyz = clouds(12, pc)
    rng = np.random.default_rng(13)
    rois = torch.from_numpy(np.c_[rng.uniform(-3, 3, (10, 3)), rng.uniform(0.3, 3, (10, 3)),
                                  rng.uniform(-3.1, 3.1, 10)].astype(np.float32))
    rois[4, :3] = 50.0  # an empty RoI
    feats = torch.from_numpy(rng.uniform(0, 1, (950, 2)).astype(np.float32))
    out = roi_point_pool(xyz, rois, 16, 0.4, feats, pc, rc, backend=backend)
    ref, ridx = ref_roi(xyz, rois, feats, pc, rc, 16, 0.4)
    np.testing.assert_array_equal(out.index.numpy(), ridx)
    np.testing.assert_allclose(out.points.numpy(), ref, atol=2e-5)
    assert out.points.shape == (10, 16, 5) and out.empty[[4, 5, 6]].all() and not out.points[4].any()
    enlarged = rois.clone()
    enlarged[:, 3:6] += 0.8
    for f, (r0, r1) in enumerate(zip(offsets(rc)[:-1], offsets(rc)[1:])):
        p0, p1 = offsets(pc)[f], offsets(pc)[f + 1]
        if r1 > r0:  # counts agree with points_in_boxes on the enlarged boxes
            np.testing.assert_array_equal(out.count[r0:r1].numpy(),
                                          points_in_boxes(xyz[p0:p1], enlarged[r0:r1])[0].numpy())
    assert (out.count > 16).any() and ((out.count > 0) & (out.count < 16)).any()  # both sampling rules ran


@pytest.mark.parametrize("backend", BACKENDS)
def test_roi_point_pool_faces_cyclic_and_extremes(backend):
    box = torch.tensor([[0.0, 0, 0, 2, 1, 1, math.pi / 2]], dtype=torch.float64)
    # enlarged by 0.5: along the heading (+y) |v| <= 1.5, across (x) |u| <= 1.0, z <= 1.0; faces inclusive
    xyz = torch.tensor([[0.0, 1.5, 0], [1.0, 0, 0], [0, 0, 1.0], [0, 1.5001, 0], [1.0001, 0, 0], [0, 0, -1.0001]],
                       dtype=torch.float64)
    out = roi_point_pool(xyz, box, 5, 0.5, backend=backend)
    assert out.index.tolist() == [[0, 1, 2, 0, 1]] and out.count.tolist() == [3]
    np.testing.assert_allclose(out.points[0, 0].numpy(), [1.5, 0, 0], atol=1e-12)  # canonical: ahead of the box
    one = roi_point_pool(xyz[:1], box, 4, 0.5, torch.tensor([[7.0]]), backend=backend)
    assert one.index.tolist() == [[0] * 4] and (one.points[0, :, 3] == 7).all()
    none = roi_point_pool(torch.zeros((0, 3)), box, 4, 0.5, backend=backend)
    assert none.empty.tolist() == [True] and none.index.tolist() == [[-1] * 4] and not none.points.any()
    batch0 = roi_point_pool(torch.zeros((0, 3)), torch.zeros((0, 7)), 4, 0.5, None, [], [], backend=backend)
    assert batch0.points.shape == (0, 4, 3) and batch0.empty.shape == (0,)


@pytest.mark.parametrize("backend", BACKENDS)
def test_roi_point_pool_identical_points_and_an_empty_roi(backend):
    # rows 0, 2, 3, 5 are one point inside RoI 0 (with distinct features, to tell them apart), row 1 lies
    # outside every RoI, row 4 is the same point again but in frame 1, which also holds rows 5 and 6;
    # RoI 1 (frame 0) and RoI 3 (frame 1) hold no point
    p = [1.0, 0.5, 0.2]
    xyz = torch.tensor([p, [9.0, 9.0, 0.0], p, p, p, p, [-30.0, 0.0, 0.0]], dtype=torch.float64)
    feats = torch.arange(7, dtype=torch.float64)[:, None] * 10 + 1
    rois = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3], [-20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],
                         [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3], [20.0, 5.0, 0.0, 4.0, 2.0, 1.5, 0.0]],
                        dtype=torch.float64)
    pc, rc = [4, 3], [2, 2]
    out = roi_point_pool(xyz, rois, 6, 0.5, feats, pc, rc, backend=backend)
    assert out.empty.tolist() == [False, True, False, True] and out.count.tolist() == [3, 0, 2, 0]
    # three inside points for six slots: rows 0, 2, 3 then again cyclically; frame 1: rows 4, 5 three times
    assert out.index.tolist() == [[0, 2, 3, 0, 2, 3], [-1] * 6, [4, 5] * 3, [-1] * 6]
    canon = to_canonical(torch.tensor([p], dtype=torch.float64), rois[:1])[0]
    for r in (0, 2):
        np.testing.assert_allclose(out.points[r, :, :3].numpy(), canon.expand(6, 3).numpy(), atol=1e-12)
    assert out.points[0, :, 3].tolist() == [1.0, 21.0, 31.0] * 2 and out.points[2, :, 3].tolist() == [41.0, 51.0] * 3
    assert not out.points[[1, 3]].any()  # empty RoIs: zero coordinates and features
    ref, ridx = ref_roi(xyz, rois, feats, pc, rc, 6, 0.5)
    np.testing.assert_array_equal(out.index.numpy(), ridx)
    np.testing.assert_allclose(out.points.numpy(), ref, atol=1e-12)
    # more identical points than slots: the even subsample floor(j * k / S) of the seven copies
    many = roi_point_pool(torch.tensor([p] * 7), rois[:1].float(), 3, 0.5, backend=backend)
    assert many.index.tolist() == [[0, 2, 4]] and many.count.tolist() == [7] and not many.empty.any()


def test_roi_point_pool_gradients_flow_to_features():
    xyz = clouds(14, [80]).double()
    feats = torch.randn(80, 2, dtype=torch.float64, requires_grad=True)
    box = torch.tensor([[0.0, 0, 0, 3, 3, 3, 0.4]], dtype=torch.float64)
    assert 8 < roi_point_pool(xyz, box, 8, 0.2).count.item() < 80
    assert torch.autograd.gradcheck(lambda f: roi_point_pool(xyz, box, 8, 0.2, f).points, (feats,))


# ---------------------------------------------------------------------------- shared
def test_parallel_kernels_equal_serial(monkeypatch):
    xyz = clouds(15, [3000, 2500], spread=10.0)
    cnt = [3000, 2500]
    serial = [farthest_point_sample(xyz, [400, 300], cnt), ball_query(xyz, xyz[::7], 1.0, 16, cnt, [429, 357]),
              three_nn(xyz, xyz[::5], cnt, [600, 500]),
              roi_point_pool(xyz, torch.tensor([[0.0, 0, 0, 4, 4, 4, 0.3]] * 6), 32, 1.0, None, cnt, [4, 2])]
    for module, name in ((sampling, "PARALLEL_MIN_FPS_WORK"), (grouping, "PARALLEL_MIN_BALL_CANDIDATES"),
                         (interpolate, "PARALLEL_MIN_NN_TARGETS"), (roi_pool, "PARALLEL_MIN_ROI_TESTS")):
        monkeypatch.setattr(module, name, 0)
    parallel = [farthest_point_sample(xyz, [400, 300], cnt), ball_query(xyz, xyz[::7], 1.0, 16, cnt, [429, 357]),
                three_nn(xyz, xyz[::5], cnt, [600, 500]),
                roi_point_pool(xyz, torch.tensor([[0.0, 0, 0, 4, 4, 4, 0.3]] * 6), 32, 1.0, None, cnt, [4, 2])]
    assert torch.equal(serial[0], parallel[0])
    for a, b in zip(serial[1:], parallel[1:]):
        assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_torch_chunking_gives_same_result(monkeypatch):
    xyz = clouds(16, [500, 300])
    cnt, qc = [500, 300], [100, 60]
    full = [ball_query(xyz, xyz[::5], 1.0, 8, cnt, qc, backend="torch"),
            three_nn(xyz, xyz[::5], cnt, qc, backend="torch"),
            roi_point_pool(xyz, torch.tensor([[0.0, 0, 0, 2, 2, 2, 0.3]] * 5), 16, 0.5, None, cnt, [3, 2],
                           backend="torch")]
    for module in (grouping, interpolate, roi_pool):
        monkeypatch.setattr(module, "TORCH_CHUNK_ELEMS", 64)
    small = [ball_query(xyz, xyz[::5], 1.0, 8, cnt, qc, backend="torch"),
             three_nn(xyz, xyz[::5], cnt, qc, backend="torch"),
             roi_point_pool(xyz, torch.tensor([[0.0, 0, 0, 2, 2, 2, 0.3]] * 5), 16, 0.5, None, cnt, [3, 2],
                            backend="torch")]
    for a, b in zip(full, small):
        assert all(torch.equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_empty_slot_is_EMPTY_INDEX(backend):
    """One rule for every op with empty slots: an empty ball, a missing neighbour, an empty RoI and an
    empty cylinder all read EMPTY_INDEX (-1), with and without any points at all."""
    assert EMPTY_INDEX == -1
    xyz = torch.tensor([[0.0, 0, 0], [1, 0, 0]])
    far = torch.tensor([[50.0, 50, 0]])
    cases = {
        "ball_query": ball_query(xyz, far, 1.0, 4, backend=backend).index,
        "ball_query, no points": ball_query(xyz[:0], far, 1.0, 4, backend=backend).index,
        "three_nn": three_nn(far, xyz, backend=backend)[1][:, 2:],  # two sources: the third is missing
        "three_nn, no sources": three_nn(far, xyz[:0], backend=backend)[1],
        "roi_point_pool": roi_point_pool(xyz, torch.tensor([[50.0, 50, 0, 1, 1, 1, 0]]), 4, 0.5,
                                         backend=backend).index,
        "roi_point_pool, no points": roi_point_pool(xyz[:0], torch.tensor([[50.0, 50, 0, 1, 1, 1, 0]]), 4, 0.5,
                                                    backend=backend).index,
        "cylinder_query": cylinder_query(xyz, torch.tensor([0.1, 0.2]), far[:, :2], torch.ones(1), 4,
                                         backend=backend)[0],
        "cylinder_query, no points": cylinder_query(xyz[:0], torch.zeros(0), far[:, :2], torch.ones(1), 4,
                                                    backend=backend)[0],
    }
    for what, index in cases.items():
        assert index.dtype == torch.int64 and index.numel() and (index == EMPTY_INDEX).all(), what
    # the consumers' side of the rule: gathering from empty slots gives zeros
    assert not group_points(torch.ones(2, 3), cases["ball_query"]).any()
    assert not three_interpolate(torch.ones(2, 3), cases["three_nn, no sources"], torch.ones(1, 3)).any()


def test_numpy_inputs_and_input_errors():
    xyz = clouds(17, [20]).numpy()
    assert farthest_point_sample(xyz, 5).shape == (5,)
    assert ball_query(xyz, xyz[:3], 1.0, 4).index.shape == (3, 4)
    with pytest.raises(ValueError, match=r"farthest_point_sample: `xyz` must have shape \(N, 3\)"):
        farthest_point_sample(xyz[:, :2], 5)
    with pytest.raises(ValueError, match="ball_query: `xyz_counts` must be non-negative and sum to"):
        ball_query(xyz, xyz[:3], 1.0, 4, [10, 9], [2, 1])
    with pytest.raises(ValueError, match="ball_query: `xyz_counts` has 1 frames but `centre_counts` has 2"):
        ball_query(xyz, xyz[:3], 1.0, 4, [20], [2, 1])
    with pytest.raises(ValueError, match="ball_query: radius must be a positive"):
        ball_query(xyz, xyz[:3], 0.0, 4)
    bad = xyz.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="three_nn: `sources` contain NaN or infinite values .first at row 4"):
        three_nn(xyz, bad)
    with pytest.raises(ValueError, match="backend must be 'auto', 'numba' or 'torch'"):
        farthest_point_sample(xyz, 5, backend="cuda")
    with pytest.raises(ValueError, match=r"roi_point_pool: `rois` must have shape \(N, 7\)"):
        roi_point_pool(xyz, np.zeros((2, 6)))
    with pytest.raises(ValueError, match="three_nn_interpolate: source_features must be an"):
        three_nn_interpolate(xyz, xyz[:5], torch.zeros((4, 2)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    xyz = clouds(18, [3000, 2000])
    cnt = [3000, 2000]
    cpu = farthest_point_sample(xyz, [512, 256], cnt)
    assert torch.equal(farthest_point_sample(xyz.cuda(), [512, 256], cnt).cpu(), cpu)
    c = xyz[cpu]
    a, b = ball_query(xyz, c, 0.8, 16, cnt, [512, 256]), ball_query(xyz.cuda(), c.cuda(), 0.8, 16, cnt, [512, 256])
    assert all(torch.equal(x, y.cpu()) for x, y in zip(a, b))
    a, b = three_nn(xyz, c, cnt, [512, 256]), three_nn(xyz.cuda(), c.cuda(), cnt, [512, 256])
    assert all(torch.equal(x, y.cpu()) for x, y in zip(a, b))


def test_bench_points_tool_writes_reports(tmp_path, capsys):
    import json

    mod = tools.bench_points
    threads = (torch.get_num_threads(), numba.get_num_threads())
    try:  # main() sets both thread counts; give them back to the other tests
        assert mod.main(["--out", str(tmp_path), "--points", "600", "--samples", "128", "--rois", "4",
                         "--channels", "8", "--repeats", "1", "--threads", "1", "--frames", "2", "--nms-boxes", "300",
                         "--nms-keep", "40"]) == 0
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])
    report = json.loads((tmp_path / "bench_points.json").read_text())
    assert report["units"].startswith("milliseconds") and report["fps_ms"] > 0
    assert any(r.get("equal_to_numba") is True for r in report["cases"])
    nms = [r for r in report["cases"] if r["case"].startswith("nms_bev 300 -> 40")]
    assert len(nms) == 2 and nms[1]["equal_to_numba"] is True and report["nms_torch_over_numba"] > 0
    md = (tmp_path / "bench_points.md").read_text()
    assert "FPS 600 -> 128" in md and "median ms" in md
    assert "ms per frame" in capsys.readouterr().out
