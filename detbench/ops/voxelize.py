"""Points to voxels: hard voxelization, dynamic voxelization and scatter reductions.

Conventions (OpenPCDet / spconv):
- ``point_cloud_range`` = [x_min, y_min, z_min, x_max, y_max, z_max] in metres, ego frame;
  ``voxel_size`` = [vx, vy, vz] in metres.
- The grid has ``round((max - min) / size)`` voxels per axis (`voxel_grid_size`, ordered
  (X, Y, Z)); a point belongs to voxel ``floor((p - min) / size)`` (computed in float64) and
  is kept when that index is inside the grid. Points outside are dropped.
- Voxel coordinates are int32 ``(z, y, x)`` (with a leading batch column for batches), the
  order `detbench.sparse.SparseConvTensor` wants; its ``spatial_shape`` is the grid reversed,
  (Z, Y, X).
- NaN anywhere in the points raises ValueError (never silently a voxel).

numpy input runs numba kernels on the CPU; torch input runs torch ops on the tensor's device
(CPU or CUDA). Both give identical results: hard voxelization keeps voxels in the order their
first point appears in the input and, per voxel, the first ``max_points_per_voxel`` points in
input order; the first ``max_voxels`` voxels so ordered are kept.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from numba import njit, prange


class HardVoxels(NamedTuple):
    """Result of hard voxelization.

    voxels: (V, P, C) points per voxel (same dtype as the input points), zero-padded.
    coords: (V, 3) int32 (z, y, x) voxel indices, or (V, 4) (batch, z, y, x) from `voxelize_batch`.
    num_points: (V,) int32 points stored per voxel, in [1, P].
    """

    voxels: np.ndarray | torch.Tensor
    coords: np.ndarray | torch.Tensor
    num_points: np.ndarray | torch.Tensor


# ----------------------------------------------------------------------------- checks
def _geometry(voxel_size: Sequence[float],
              point_cloud_range: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated (lo (3,) float64, size (3,) float64, grid (3,) int64 as X, Y, Z)."""
    vs = np.asarray(voxel_size, dtype=np.float64).reshape(-1)
    pcr = np.asarray(point_cloud_range, dtype=np.float64).reshape(-1)
    if vs.shape != (3,) or pcr.shape != (6,):
        raise ValueError(f"voxel_size must be 3 numbers [vx, vy, vz] and point_cloud_range 6 numbers "
                         f"[x_min, y_min, z_min, x_max, y_max, z_max] (metres); got {list(vs)} and {list(pcr)}")
    if not (np.all(np.isfinite(vs)) and np.all(vs > 0)):
        raise ValueError(f"voxel_size must be positive metres, got {list(vs)}")
    if not (np.all(np.isfinite(pcr)) and np.all(pcr[3:] > pcr[:3])):
        raise ValueError(f"point_cloud_range needs finite x_min < x_max, y_min < y_max, z_min < z_max; got {list(pcr)}")
    grid = np.round((pcr[3:] - pcr[:3]) / vs).astype(np.int64)
    if np.any(grid < 1):
        raise ValueError(f"point_cloud_range {list(pcr)} is smaller than one voxel of size {list(vs)}")
    if np.any(grid > np.iinfo(np.int32).max) or float(np.prod(grid.astype(np.float64))) >= 2.0**62:
        raise ValueError(f"grid {list(grid)} (X, Y, Z) from range {list(pcr)} and voxel size {list(vs)} is too large "
                         "for int32 voxel coordinates / int64 keys; use larger voxels or a smaller range")
    return pcr[:3].copy(), vs, grid


def voxel_grid_size(voxel_size: Sequence[float], point_cloud_range: Sequence[float]) -> tuple[int, int, int]:
    """Voxels per axis (X, Y, Z) = round((max - min) / voxel_size); the sparse spatial_shape is this reversed."""
    return tuple(int(g) for g in _geometry(voxel_size, point_cloud_range)[2])


def _check_points(points, what: str = "points") -> None:
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"{what} must be (N, C>=3) with x, y, z first, got shape {tuple(points.shape)}")
    if isinstance(points, torch.Tensor):
        if not points.dtype.is_floating_point:
            raise ValueError(f"{what} must be a floating-point tensor, got {points.dtype}")
        bad = torch.isnan(points).any(dim=1)
        if bool(bad.any()):
            row = int(bad.nonzero()[0, 0])
            raise ValueError(f"{what} contain NaN (first at row {row}, {int(bad.sum())} rows in all); "
                             "drop or repair those points before voxelization")
    else:
        if not np.issubdtype(points.dtype, np.floating):
            raise ValueError(f"{what} must be a float array, got {points.dtype}")
        bad = np.isnan(points).any(axis=1)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{what} contain NaN (first at row {row}, {int(bad.sum())} rows in all); "
                             "drop or repair those points before voxelization")


# ----------------------------------------------------------------------------- numba kernels
@njit(cache=True, parallel=True)
def _dynamic_kernel(points, lo, vs, grid, out):
    """out[i] = (z, y, x) voxel of point i, or -1s when it lies outside the grid."""
    n = points.shape[0]
    for i in prange(n):
        cx = np.floor((np.float64(points[i, 0]) - lo[0]) / vs[0])
        cy = np.floor((np.float64(points[i, 1]) - lo[1]) / vs[1])
        cz = np.floor((np.float64(points[i, 2]) - lo[2]) / vs[2])
        if cx >= 0.0 and cx < grid[0] and cy >= 0.0 and cy < grid[1] and cz >= 0.0 and cz < grid[2]:
            out[i, 0] = np.int32(cz)
            out[i, 1] = np.int32(cy)
            out[i, 2] = np.int32(cx)
        else:
            out[i, 0] = -1
            out[i, 1] = -1
            out[i, 2] = -1


@njit(cache=True)
def _hard_kernel(points, lo, vs, grid, max_points, max_voxels, point_vid, point_slot, coords, num_points):
    """Sequential pass in input order with an open-addressing hash of linear voxel keys.

    Writes each point's voxel id and slot (-1 when dropped) and the voxels' coords and
    point counts; returns the number of voxels.
    """
    n = points.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    bits = 0
    while (1 << bits) < cap:
        bits += 1
    table_key = np.full(cap, -1, dtype=np.int64)
    table_val = np.empty(cap, dtype=np.int64)
    mult = np.uint64(11400714819323198485)
    shift = np.uint64(64 - bits)
    mask = cap - 1
    nvox = 0
    for i in range(n):
        point_vid[i] = -1
        point_slot[i] = -1
        cx = np.floor((np.float64(points[i, 0]) - lo[0]) / vs[0])
        cy = np.floor((np.float64(points[i, 1]) - lo[1]) / vs[1])
        cz = np.floor((np.float64(points[i, 2]) - lo[2]) / vs[2])
        if not (cx >= 0.0 and cx < grid[0] and cy >= 0.0 and cy < grid[1] and cz >= 0.0 and cz < grid[2]):
            continue
        ix, iy, iz = np.int64(cx), np.int64(cy), np.int64(cz)
        key = (iz * grid[1] + iy) * grid[0] + ix
        h = np.int64((np.uint64(key) * mult) >> shift)
        vid = -1
        while True:
            tk = table_key[h]
            if tk == key:
                vid = table_val[h]
                break
            if tk == -1:
                break
            h = (h + 1) & mask
        if vid < 0:
            if nvox >= max_voxels:
                continue
            vid = nvox
            nvox += 1
            table_key[h] = key
            table_val[h] = vid
            coords[vid, 0] = iz
            coords[vid, 1] = iy
            coords[vid, 2] = ix
            num_points[vid] = 0
        k = num_points[vid]
        if k < max_points:
            point_vid[i] = vid
            point_slot[i] = k
            num_points[vid] = k + 1
    return nvox


# ----------------------------------------------------------------------------- torch paths
def _coords_torch(points: torch.Tensor, lo, vs, grid) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) int64 (x, y, z) voxel indices (0 where invalid) and (N,) bool inside-grid mask."""
    dev = points.device
    lo_t = torch.as_tensor(lo, dtype=torch.float64, device=dev)
    vs_t = torch.as_tensor(vs, dtype=torch.float64, device=dev)
    grid_t = torch.as_tensor(grid, dtype=torch.float64, device=dev)
    f = torch.floor((points[:, :3].to(torch.float64) - lo_t) / vs_t)
    valid = ((f >= 0) & (f < grid_t)).all(dim=1)
    c = torch.where(valid.unsqueeze(1), f, torch.zeros_like(f)).to(torch.int64)
    return c, valid


def _hard_torch(points: torch.Tensor, lo, vs, grid, max_points: int, max_voxels: int) -> HardVoxels:
    dev = points.device
    n, nch = points.shape
    c, valid = _coords_torch(points, lo, vs, grid)
    idx = valid.nonzero().squeeze(1)  # kept point rows, input order
    if idx.numel() == 0 or max_voxels == 0:
        return HardVoxels(points.new_zeros((0, max_points, nch)), torch.zeros((0, 3), dtype=torch.int32, device=dev),
                          torch.zeros(0, dtype=torch.int32, device=dev))
    c = c[idx]
    keys = (c[:, 2] * int(grid[1]) + c[:, 1]) * int(grid[0]) + c[:, 0]
    _, inv = torch.unique(keys, return_inverse=True)
    nu = int(inv.max()) + 1
    m = idx.shape[0]
    pos = torch.arange(m, device=dev)
    first = torch.full((nu,), m, dtype=torch.int64, device=dev).scatter_reduce(0, inv, pos, "amin")
    vorder = torch.argsort(first)  # voxel ids by first appearance
    rank = torch.empty_like(vorder)
    rank[vorder] = torch.arange(nu, device=dev)
    vid = rank[inv]  # output voxel id of each kept point
    perm = torch.argsort(vid, stable=True)  # grouped by voxel, input order inside a voxel
    vid_s = vid[perm]
    counts = torch.bincount(vid, minlength=nu)
    starts = torch.cumsum(counts, 0) - counts
    slot = pos - starts[vid_s]
    keep = (slot < max_points) & (vid_s < max_voxels)
    nv = min(nu, int(max_voxels))
    voxels = points.new_zeros((nv, max_points, nch))
    voxels[vid_s[keep], slot[keep]] = points[idx[perm[keep]]]
    first_pts = first[vorder[:nv]]
    coords = c[first_pts].flip(1).to(torch.int32)
    num_points = counts[:nv].clamp_max(max_points).to(torch.int32)
    return HardVoxels(voxels, coords, num_points)


# ----------------------------------------------------------------------------- public API
def voxelize(points, voxel_size: Sequence[float], point_cloud_range: Sequence[float],
             max_points_per_voxel: int = 32, max_voxels: int = 20000) -> HardVoxels:
    """Hard voxelization of one point cloud.

    Args:
        points: (N, C>=3) float numpy array (numba path) or torch tensor (any device); x, y, z
            in metres first, then any features (e.g. intensity).
        voxel_size: [vx, vy, vz] metres. point_cloud_range: [x_min, y_min, z_min, x_max, y_max, z_max] metres.
        max_points_per_voxel: P, points kept per voxel (the first P in input order).
        max_voxels: most voxels kept (the first by order of their first point).

    Returns:
        `HardVoxels` (voxels (V, P, C), coords (V, 3) int32 (z, y, x), num_points (V,) int32),
        numpy for numpy input, torch on the input's device for torch input.

    Raises:
        ValueError: NaN in the points, bad shapes, or a bad range / voxel size.
    """
    lo, vs, grid = _geometry(voxel_size, point_cloud_range)
    if int(max_points_per_voxel) < 1 or int(max_voxels) < 0:
        raise ValueError(f"need max_points_per_voxel >= 1 and max_voxels >= 0, "
                         f"got {max_points_per_voxel}, {max_voxels}")
    _check_points(points)
    p, mv = int(max_points_per_voxel), int(max_voxels)
    if isinstance(points, torch.Tensor):
        return _hard_torch(points, lo, vs, grid, p, mv)
    pts = np.ascontiguousarray(points)
    n = pts.shape[0]
    cap = min(mv, n)
    coords = np.zeros((cap, 3), dtype=np.int32)
    num = np.zeros(cap, dtype=np.int32)
    vid = np.empty(n, dtype=np.int64)
    slot = np.empty(n, dtype=np.int64)
    nv = _hard_kernel(pts, lo, vs, grid, p, cap, vid, slot, coords, num) if cap else 0
    voxels = np.zeros((nv, p, pts.shape[1]), dtype=pts.dtype)
    if nv:
        keep = vid >= 0
        voxels[vid[keep], slot[keep]] = pts[keep]
    return HardVoxels(voxels, coords[:nv], num[:nv])


def voxelize_batch(points_list: Sequence, voxel_size: Sequence[float], point_cloud_range: Sequence[float],
                   max_points_per_voxel: int = 32, max_voxels: int = 20000) -> HardVoxels:
    """Hard-voxelize each cloud of a batch and concatenate, adding the batch column.

    Args:
        points_list: B clouds (N_b, C), all numpy or all torch (same C, dtype and device).
        voxel_size, point_cloud_range, max_points_per_voxel: as `voxelize`; max_voxels is per cloud.

    Returns:
        `HardVoxels` with coords (V, 4) int32 (batch, z, y, x), voxels of cloud 0 first.
    """
    if len(points_list) == 0:
        raise ValueError("voxelize_batch needs at least one point cloud")
    parts = [voxelize(p, voxel_size, point_cloud_range, max_points_per_voxel, max_voxels) for p in points_list]
    if isinstance(points_list[0], torch.Tensor):
        coords = torch.cat([torch.cat([torch.full_like(r.coords[:, :1], b), r.coords], 1) for b, r in enumerate(parts)])
        return HardVoxels(torch.cat([r.voxels for r in parts]), coords, torch.cat([r.num_points for r in parts]))
    coords = np.concatenate([np.concatenate([np.full((len(r.coords), 1), b, np.int32), r.coords], 1)
                             for b, r in enumerate(parts)])
    return HardVoxels(np.concatenate([r.voxels for r in parts]), coords, np.concatenate([r.num_points for r in parts]))


def dynamic_voxelize(points, voxel_size: Sequence[float], point_cloud_range: Sequence[float]):
    """Voxel coordinate of every point (dynamic voxelization, no caps).

    Args:
        points: (N, C>=3) float numpy (numba) or torch (any device); metres.
        voxel_size, point_cloud_range: as `voxelize`.

    Returns:
        (N, 3) int32 (z, y, x) per point; rows of points outside the range are -1.
        Use `unique_voxels` (with a batch column) and `scatter_mean` / `scatter_max` to pool.
    """
    lo, vs, grid = _geometry(voxel_size, point_cloud_range)
    _check_points(points)
    if isinstance(points, torch.Tensor):
        c, valid = _coords_torch(points, lo, vs, grid)
        out = c.flip(1).to(torch.int32)
        return torch.where(valid.unsqueeze(1), out, torch.full_like(out, -1))
    pts = np.ascontiguousarray(points)
    out = np.empty((pts.shape[0], 3), dtype=np.int32)
    _dynamic_kernel(pts, lo, vs, grid, out)
    return out


def unique_voxels(coords):
    """Unique voxels of per-point coordinates and each point's voxel row.

    Args:
        coords: (N, D) integer coordinates, e.g. (batch, z, y, x); rows with any negative
            entry (points outside the range) are ignored. numpy or torch.

    Returns:
        (voxel_coords (V, D) int32 sorted lexicographically (batch-major), inverse (N,) int64
        with the row of each point in voxel_coords, -1 for ignored points). Same library and
        device as the input.
    """
    is_np = not isinstance(coords, torch.Tensor)
    c = torch.from_numpy(np.asarray(coords)) if is_np else coords
    if c.dim() != 2 or c.dtype.is_floating_point:
        raise ValueError(f"coords must be an (N, D) integer array, got shape {tuple(c.shape)} dtype {c.dtype}")
    c = c.long()
    valid = (c >= 0).all(dim=1)
    inverse = torch.full((c.shape[0],), -1, dtype=torch.int64, device=c.device)
    if not bool(valid.any()):
        vc = torch.zeros((0, c.shape[1]), dtype=torch.int32, device=c.device)
    else:
        cv = c[valid]
        ext = (cv.max(dim=0).values + 1).tolist()
        if float(np.prod(np.asarray(ext, dtype=np.float64))) >= 2.0**63:
            raise ValueError(f"coordinate extents {ext} are too large for int64 keys")
        key = cv[:, 0]
        for d in range(1, c.shape[1]):
            key = key * ext[d] + cv[:, d]
        uniq, inv = torch.unique(key, sorted=True, return_inverse=True)
        inverse[valid] = inv
        cols, rest = [], uniq
        for d in range(c.shape[1] - 1, 0, -1):
            cols.append(torch.remainder(rest, ext[d]))
            rest = torch.div(rest, ext[d], rounding_mode="floor")
        cols.append(rest)
        vc = torch.stack(cols[::-1], dim=1).to(torch.int32)
    if is_np:
        return vc.numpy(), inverse.numpy()
    return vc, inverse


def _check_scatter(src: torch.Tensor, index: torch.Tensor, num_segments: int) -> torch.Tensor:
    if src.dim() != 2 or index.dim() != 1 or index.shape[0] != src.shape[0]:
        raise ValueError(f"scatter needs src (N, C) and index (N,), got {tuple(src.shape)} and {tuple(index.shape)}")
    index = index.long()
    if index.numel() and int(index.max()) >= num_segments:
        raise ValueError(f"index has values up to {int(index.max())} but num_segments is {num_segments}")
    return index


def scatter_mean(src: torch.Tensor, index: torch.Tensor, num_segments: int) -> torch.Tensor:
    """Mean of the rows of ``src`` (N, C) per segment ``index`` (N,) (negative = ignore) -> (num_segments, C).

    Empty segments give 0. Differentiable w.r.t. ``src``.
    """
    index = _check_scatter(src, index, num_segments)
    keep = index >= 0
    idx, rows = index[keep], src[keep]
    total = src.new_zeros((num_segments, src.shape[1])).index_add(0, idx, rows)
    count = torch.bincount(idx, minlength=num_segments).clamp_min(1).to(src.dtype)
    return total / count.unsqueeze(1)


def scatter_max(src: torch.Tensor, index: torch.Tensor, num_segments: int) -> torch.Tensor:
    """Channel-wise max of ``src`` (N, C) rows per segment ``index`` (N,) (negative = ignore) -> (num_segments, C).

    Empty segments give 0. Differentiable w.r.t. ``src`` (ties share the gradient).
    """
    index = _check_scatter(src, index, num_segments)
    keep = index >= 0
    idx, rows = index[keep], src[keep]
    out = src.new_zeros((num_segments, src.shape[1]))
    return out.scatter_reduce(0, idx.unsqueeze(1).expand_as(rows), rows, "amax", include_self=False)
