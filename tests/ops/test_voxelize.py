"""detbench.ops.voxelize against plain numpy/Python references; numpy (numba) vs torch parity."""
import numpy as np
import pytest
import torch

from detbench.ops.voxelize import (dynamic_voxelize, scatter_max, scatter_mean, unique_voxels, voxel_grid_size,
                                   voxelize, voxelize_batch)

VS = [0.5, 0.5, 0.25]
PCR = [0.0, -4.0, -1.0, 10.0, 4.0, 2.0]


def clustered_points(n=3000, seed=0):
    """Points in clumps (many share a voxel), some outside the range, 4 columns float32."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-1, -5, -1.5], [11, 5, 2.5], (60, 3))
    xyz = centres[rng.integers(0, 60, n)] + rng.normal(0, 0.3, (n, 3))
    return np.concatenate([xyz, rng.uniform(0, 1, (n, 1))], 1).astype(np.float32)


def reference_hard(points, vs, pcr, max_points, max_voxels):
    """Plain Python: walk points in order, first-come voxels and first-come points."""
    lo, size = np.array(pcr[:3]), np.array(vs)
    grid = np.round((np.array(pcr[3:]) - lo) / size).astype(int)
    table, vox, coords = {}, [], []
    for p in points.astype(np.float64):
        c = np.floor((p[:3] - lo) / size)
        if not np.all((c >= 0) & (c < grid)):
            continue
        key = tuple(int(v) for v in c[::-1])
        if key not in table:
            if len(vox) >= max_voxels:
                continue
            table[key] = len(vox)
            vox.append([])
            coords.append(key)
        lst = vox[table[key]]
        if len(lst) < max_points:
            lst.append(p)
    return coords, vox


@pytest.mark.parametrize("max_points,max_voxels", [(64, 100000), (3, 100000), (5, 40)])
def test_hard_voxelize_matches_reference_numpy_and_torch(max_points, max_voxels):
    pts = clustered_points()
    ref_coords, ref_vox = reference_hard(pts, VS, PCR, max_points, max_voxels)
    out_np = voxelize(pts, VS, PCR, max_points, max_voxels)
    out_t = voxelize(torch.from_numpy(pts), VS, PCR, max_points, max_voxels)
    assert out_np.coords.dtype == np.int32 and out_np.num_points.dtype == np.int32
    assert out_np.voxels.shape == (len(ref_coords), max_points, 4)
    assert [tuple(c) for c in out_np.coords.tolist()] == ref_coords
    assert out_np.num_points.tolist() == [len(v) for v in ref_vox]
    for v, lst in enumerate(ref_vox):
        np.testing.assert_array_equal(out_np.voxels[v, :len(lst)], np.array(lst, dtype=np.float32))
        assert not out_np.voxels[v, len(lst):].any()
    for a, b in zip(out_np, out_t):
        np.testing.assert_array_equal(a, b.numpy())


def test_counts_and_means_against_numpy_groupby():
    pts = clustered_points(seed=1)
    lo, size = np.array(PCR[:3]), np.array(VS)
    grid = np.array(voxel_grid_size(VS, PCR))
    c = np.floor((pts[:, :3].astype(np.float64) - lo) / size).astype(int)
    ok = np.all((c >= 0) & (c < grid), axis=1)
    zyx = c[ok][:, ::-1]
    uniq, inv, counts = np.unique(zyx, axis=0, return_inverse=True, return_counts=True)
    out = voxelize(pts, VS, PCR, max_points_per_voxel=int(counts.max()), max_voxels=10**6)
    means = np.zeros((len(uniq), 4))
    np.add.at(means, inv.reshape(-1), pts[ok].astype(np.float64))
    means /= counts[:, None]
    order = np.lexsort(out.coords.T[::-1])
    np.testing.assert_array_equal(out.coords[order], uniq)
    np.testing.assert_array_equal(out.num_points[order], counts)
    got_means = out.voxels.astype(np.float64).sum(1) / out.num_points[:, None]
    np.testing.assert_allclose(got_means[order], means, rtol=1e-6, atol=1e-6)
    assert out.num_points.sum() == ok.sum()


def test_range_edges_nan_inf_and_empty():
    pts = np.array([[0.0, -4.0, -1.0, 0.1],      # min corner: kept, voxel (0, 0, 0)
                    [10.0, 0.0, 0.0, 0.2],       # x == x_max: outside
                    [9.99, 3.99, 1.99, 0.3],     # last voxel
                    [-0.01, 0.0, 0.0, 0.4],      # below x_min
                    [np.inf, 0.0, 0.0, 0.5],     # inf: outside
                    [5.0, -np.inf, 0.0, 0.6]], dtype=np.float32)
    grid = voxel_grid_size(VS, PCR)
    assert grid == (20, 16, 12)
    for p in (pts, torch.from_numpy(pts)):
        out = voxelize(p, VS, PCR, 4, 100)
        assert np.asarray(out.coords).tolist() == [[0, 0, 0], [11, 15, 19]]
        dyn = np.asarray(dynamic_voxelize(p, VS, PCR))
        assert dyn.tolist() == [[0, 0, 0], [-1, -1, -1], [11, 15, 19], [-1, -1, -1], [-1, -1, -1], [-1, -1, -1]]
    bad = pts.copy()
    bad[2, 1] = np.nan
    for p in (bad, torch.from_numpy(bad)):
        with pytest.raises(ValueError, match="NaN.*row 2"):
            voxelize(p, VS, PCR)
        with pytest.raises(ValueError, match="NaN"):
            dynamic_voxelize(p, VS, PCR)
    with pytest.raises(ValueError, match="point_cloud_range"):
        voxelize(pts, VS, [0, 0, 0, -1, 1, 1])
    with pytest.raises(ValueError, match="voxel_size"):
        voxelize(pts, [0.1, 0.0, 0.1], PCR)
    for p in (np.zeros((0, 4), np.float32), torch.zeros(0, 4)):
        out = voxelize(p, VS, PCR, 5, 10)
        assert tuple(out.voxels.shape) == (0, 5, 4) and tuple(out.coords.shape) == (0, 3)
        assert tuple(dynamic_voxelize(p, VS, PCR).shape) == (0, 3)


def test_deterministic_and_dynamic_parity():
    pts = clustered_points(seed=2)
    a = voxelize(pts, VS, PCR, 4, 500)
    b = voxelize(pts.copy(), VS, PCR, 4, 500)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    d_np = dynamic_voxelize(pts, VS, PCR)
    d_t = dynamic_voxelize(torch.from_numpy(pts), VS, PCR)
    np.testing.assert_array_equal(d_np, d_t.numpy())
    # Dynamic coords of the points of each hard voxel agree with that voxel's coords.
    full = voxelize(pts, VS, PCR, 1, 10**6)
    assert {tuple(r) for r in full.coords.tolist()} == {tuple(r) for r in d_np[d_np[:, 0] >= 0].tolist()}
    pts64 = pts.astype(np.float64)
    np.testing.assert_array_equal(dynamic_voxelize(pts64, VS, PCR), d_np)


def test_voxelize_batch_adds_batch_column():
    clouds = [clustered_points(500, seed=s) for s in range(3)]
    clouds[1] = clouds[1][:0]  # a batch element with no points
    out = voxelize_batch(clouds, VS, PCR, 4, 1000)
    out_t = voxelize_batch([torch.from_numpy(c) for c in clouds], VS, PCR, 4, 1000)
    singles = [voxelize(c, VS, PCR, 4, 1000) for c in clouds]
    assert out.coords.shape[1] == 4
    assert np.bincount(out.coords[:, 0], minlength=3).tolist() == [len(s.coords) for s in singles]
    np.testing.assert_array_equal(out.coords[out.coords[:, 0] == 2, 1:], singles[2].coords)
    for x, y in zip(out, out_t):
        np.testing.assert_array_equal(x, y.numpy())


def test_unique_voxels_and_scatter_against_numpy():
    pts = clustered_points(seed=3)
    dyn = dynamic_voxelize(torch.from_numpy(pts), VS, PCR)
    batch = torch.from_numpy((np.arange(len(pts)) % 2).astype(np.int32)).unsqueeze(1)
    coords = torch.cat([batch, dyn], 1)
    coords[dyn[:, 0] < 0] = -1
    vc, inv = unique_voxels(coords)
    valid = (coords >= 0).all(1)
    assert bool((inv[~valid] == -1).all()) and bool((inv[valid] >= 0).all())
    assert torch.equal(vc[inv[valid]], coords[valid])
    ref_u = np.unique(coords[valid].numpy(), axis=0)
    np.testing.assert_array_equal(vc.numpy(), ref_u)
    feats = torch.from_numpy(pts).double().requires_grad_(True)
    mean = scatter_mean(feats, inv, vc.shape[0])
    mx = scatter_max(feats, inv, vc.shape[0])
    f = pts.astype(np.float64)[valid.numpy()]
    iv = inv[valid].numpy()
    ref_mean = np.zeros((len(vc), 4))
    np.add.at(ref_mean, iv, f)
    ref_mean /= np.bincount(iv)[:, None]
    ref_max = np.full((len(vc), 4), -np.inf)
    np.maximum.at(ref_max, iv, f)
    np.testing.assert_allclose(mean.detach().numpy(), ref_mean, rtol=1e-12)
    np.testing.assert_array_equal(mx.detach().numpy(), ref_max)
    (mean.sum() + mx.sum()).backward()
    assert torch.isfinite(feats.grad).all() and float(feats.grad[~valid].abs().sum()) == 0.0
    vc_np, inv_np = unique_voxels(coords.numpy())
    np.testing.assert_array_equal(vc_np, vc.numpy())
    np.testing.assert_array_equal(inv_np, inv.numpy())
    # Empty segments give 0.
    assert scatter_max(torch.ones(1, 2), torch.tensor([1]), 3)[0].abs().sum() == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_numpy():
    pts = clustered_points(seed=4)
    a = voxelize(pts, VS, PCR, 5, 300)
    b = voxelize(torch.from_numpy(pts).cuda(), VS, PCR, 5, 300)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y.cpu().numpy())
    np.testing.assert_array_equal(dynamic_voxelize(pts, VS, PCR),
                                  dynamic_voxelize(torch.from_numpy(pts).cuda(), VS, PCR).cpu().numpy())
