"""detbench.ops.cylinder_query (CT3D's points around a proposal): numba and torch give the same indices,
which are those of a brute-force reference, on random clouds and at the extremes; an empty cylinder's
slots are EMPTY_INDEX."""
import math

import numpy as np
import pytest
import torch

from detbench.ops import EMPTY_INDEX, cylinder_query

GOLDEN = 0.6180339887498949


def _golden(n):
    return torch.remainder(torch.arange(n, dtype=torch.float64) * GOLDEN, 1.0).float()


def _reference(xy, keys, centres, radius, k):
    xy, keys, c, r = (np.asarray(t, dtype=np.float32) for t in (xy, keys, centres, radius))
    index, count = np.full((len(c), k), EMPTY_INDEX, np.int64), np.zeros(len(c), np.int64)
    for j in range(len(c)):
        d = c[j, :2] - xy[:, :2]
        with np.errstate(over="ignore"):  # a centre or radius of 1e30 m squares to inf, as in the op
            inside = np.flatnonzero((d * d).sum(1, dtype=np.float32) <= r[j] * r[j])
        count[j] = len(inside)
        if len(inside):
            ordered = inside[np.lexsort((inside, keys[inside]))]
            index[j] = ordered[np.arange(k) % min(k, len(inside))]
    return index, count


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_reference_on_random_clouds(seed):
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(5000, 3, generator=g) * torch.tensor([80.0, 30.0, 3.0]) - torch.tensor([0.0, 15.0, 0.0])
    centres = torch.rand(40, 2, generator=g) * torch.tensor([80.0, 30.0]) - torch.tensor([0.0, 15.0])
    radius = torch.rand(40, generator=g) * 6.0 + 0.5
    centres[-1], radius[-1] = torch.tensor([200.0, 200.0]), 3.0  # an empty cylinder
    keys = torch.rand(5000, generator=g) if seed else _golden(5000)
    ref = _reference(xy, keys, centres, radius, 32)
    for backend in ("numba", "torch"):
        idx, cnt = cylinder_query(xy, keys, centres, radius, 32, backend=backend)
        assert np.array_equal(cnt.numpy(), ref[1]), backend
        assert np.array_equal(idx.numpy(), ref[0]), backend
    assert (ref[1] > 32).any() and (ref[1] < 32).any() and (ref[1] == 0).any()  # every case was exercised


def test_extremes():
    keys = _golden(4)
    xy = torch.tensor([[0.0, 0.0], [3.0, 4.0], [0.0, 0.0], [100.0, 0.0]])
    centres = torch.tensor([[0.0, 0.0], [50.0, 50.0], [1000.0, 0.0]])  # a far padding centre too
    radius = torch.tensor([5.0, 1.0, 1.0])  # (3, 4) lies exactly on the first radius: inside
    for backend in ("numba", "torch"):
        idx, cnt = cylinder_query(xy, keys, centres, radius, 5, backend=backend)
        assert cnt.tolist() == [3, 0, 0]
        order = sorted([0, 1, 2], key=lambda i: float(keys[i]))
        assert idx[0].tolist() == [order[s % 3] for s in range(5)]  # cyclic repetition
        assert idx[1].tolist() == [EMPTY_INDEX] * 5 and idx[2].tolist() == [EMPTY_INDEX] * 5
        # one point, none, no centre
        i1, c1 = cylinder_query(xy[:1], keys[:1], centres[:1], radius[:1], 3, backend=backend)
        assert c1.tolist() == [1] and i1.tolist() == [[0, 0, 0]]
        i0, c0 = cylinder_query(xy[:0], keys[:0], centres, radius, 3, backend=backend)
        assert c0.tolist() == [0, 0, 0] and i0.tolist() == [[EMPTY_INDEX] * 3] * 3
        ie, ce = cylinder_query(xy, keys, centres[:0], radius[:0], 3, backend=backend)
        assert ie.shape == (0, 3) and ce.shape == (0,)


def test_huge_finite_proposals_match_the_reference():
    """An untrained CT3D proposes boxes 1e13 m wide (radius squared 1e27, inf in float32) or centred 1e30 m
    away: finite, so accepted; a huge cylinder holds every point, a far one none, and the grid of the numba
    path stays the size of the point cloud."""
    g = torch.Generator().manual_seed(3)
    xy = torch.rand(2000, 2, generator=g) * torch.tensor([120.0, 40.0]) - torch.tensor([0.0, 20.0])
    keys = torch.rand(2000, generator=g)
    centres = torch.tensor([[10.0, 0.0], [-1.2, -141.0], [1e30, 0.0], [0.0, -1e30], [60.0, 5.0], [-1e25, 1e25]])
    radius = torch.tensor([4.0, 3.7e13, 3.0, 1e20, 2.5, 1e26])
    ref = _reference(xy, keys, centres, radius, 16)
    assert ref[1].tolist()[1:4] == [2000, 0, 2000] and ref[1][-1] == 2000
    for backend in ("numba", "torch"):
        idx, cnt = cylinder_query(xy, keys, centres, radius, 16, backend=backend)
        assert np.array_equal(cnt.numpy(), ref[1]), backend
        assert np.array_equal(idx.numpy(), ref[0]), backend
    # every centre beyond the points: no cell grid at all, every slot empty
    idx, cnt = cylinder_query(xy, keys, torch.tensor([[500.0, 0.0], [0.0, 900.0]]), torch.tensor([3.0, 3.0]), 4,
                              backend="numba")
    assert cnt.tolist() == [0, 0] and idx.tolist() == [[EMPTY_INDEX] * 4] * 2


def test_bad_input_is_named():
    xy, keys = torch.zeros(3, 2), _golden(3)
    with pytest.raises(ValueError, match="num_samples must be >= 1"):
        cylinder_query(xy, keys, torch.zeros(1, 2), torch.ones(1), 0)
    with pytest.raises(ValueError, match="centres and radius must be finite"):
        cylinder_query(xy, keys, torch.tensor([[math.nan, 0.0]]), torch.ones(1), 2)
    with pytest.raises(ValueError, match="keys must be"):
        cylinder_query(xy, keys[:2], torch.zeros(1, 2), torch.ones(1), 2)


def test_equal_keys_keep_index_order_on_the_numba_path():
    """Many equal keys (the k-th smallest key shared by many points): lowest indices first, as the reference."""
    g = torch.Generator().manual_seed(5)
    xy = torch.rand(3000, 2, generator=g) * 20.0
    keys = torch.floor(torch.rand(3000, generator=g) * 4.0) / 4.0  # four distinct values
    centres, radius = torch.rand(25, 2, generator=g) * 20.0, torch.rand(25, generator=g) * 5.0 + 1.0
    idx, cnt = cylinder_query(xy, keys, centres, radius, 48, backend="numba")
    ref = _reference(xy, keys, centres, radius, 48)
    assert np.array_equal(cnt.numpy(), ref[1]) and np.array_equal(idx.numpy(), ref[0])
    assert (ref[1] > 48 * 4).any()  # the k-th key is shared by many points in some cylinder
