"""Three-nearest-neighbour feature propagation (PointNet++), numba on CPU and torch elsewhere.

Contents
- `three_nn`: the three nearest sources of each target within its frame.
- `three_interpolate`: the weighted sum of three source rows.
- `three_nn_interpolate`: both, with inverse-distance weights (PointNet++ feature propagation).

Batches, indices, arithmetic and backends follow detbench.ops.point_batch.
"""
from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.grouping import group_points
from detbench.ops.point_batch import (EMPTY_INDEX, TORCH_CHUNK_ELEMS, check_counts, check_same_frames, check_xyz,
                                      frame_offsets, num_chunks, pick_backend, xyz_float64)

__all__ = ["three_nn", "three_interpolate", "three_nn_interpolate"]

# Target points below which the serial numba kernel runs (see PARALLEL_MIN_POINTS in points_in_boxes.py).
PARALLEL_MIN_NN_TARGETS = 100_000
_NN_EPS = 1e-8  # metres, added to distances before inverting (as PointNet++)


def _nn_grid(s: np.ndarray):
    """Grid over one frame's sources (m, 3) float64: (lo (3,), h, dims (3,) int64)."""
    m = s.shape[0]
    lo = s.min(axis=0)
    ext = s.max(axis=0) - lo
    big = float(ext.max())
    if big <= 0.0:
        return lo, 1.0, np.ones(3, dtype=np.int64)
    e = np.maximum(ext, big * 1e-9)
    h = max(float(np.prod(e) / max(m / 2.0, 1.0)) ** (1.0 / 3.0), big * 1e-6)
    while np.prod(np.floor(ext / h) + 1.0) > 2.0 * m + 8:  # cells linear in the sources
        h *= 1.5
    return lo, h, (np.floor(ext / h) + 1).astype(np.int64)


@njit(cache=True)
def _nn_insert(d2, pid, bd, bi, k, need):
    """Insert (d2, pid) into the sorted best list bd/bi holding k entries (<= need); new k."""
    if k == need and (d2 > bd[k - 1] or (d2 == bd[k - 1] and pid > bi[k - 1])):
        return k
    t = k if k < need else need - 1
    while t > 0 and (bd[t - 1] > d2 or (bd[t - 1] == d2 and bi[t - 1] > pid)):
        bd[t] = bd[t - 1]
        bi[t] = bi[t - 1]
        t -= 1
    bd[t] = d2
    bi[t] = pid
    return min(k + 1, need)


@njit(cache=True)
def _nn_cell(t, i, s, sid, cstart, cell, bd, bi, k, need):
    """Offer the sources of one grid cell to target i's best list; new count."""
    for j in range(cstart[cell], cstart[cell + 1]):
        dx = s[j, 0] - t[i, 0]
        dy = s[j, 1] - t[i, 1]
        dz = s[j, 2] - t[i, 2]
        k = _nn_insert(dx * dx + dy * dy + dz * dz, sid[j], bd, bi, k, need)
    return k


@njit(cache=True)
def _nn_range(t, s, sid, cstart, lo, h, dims, t0, t1, out_d2, out_idx):
    """Targets t0..t1-1: the 3 nearest sources by (d^2, row), ring search over grid cells.

    s (m, 3) sources sorted by cell, sid their global rows, cstart (ncell + 1,) CSR offsets.
    Ring k holds the cells at Chebyshev distance k from the target's cell (clamped into the
    grid); after rings 0..k every unvisited source is at least k * h away, so the search
    stops once the third distance is below that (strictly, so ties keep the lower row).
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    need = min(3, s.shape[0])
    kmax = max(nx, max(ny, nz))
    bd = np.empty(3)
    bi = np.empty(3, dtype=np.int64)
    c = np.empty(3, dtype=np.int64)
    for i in range(t0, t1):
        for a in range(3):
            f = np.floor((t[i, a] - lo[a]) / h)
            c[a] = np.int64(min(max(f, 0.0), dims[a] - 1.0))
        k = 0
        for ring in range(kmax + 1):
            for iz in range(max(c[2] - ring, 0), min(c[2] + ring, nz - 1) + 1):
                for iy in range(max(c[1] - ring, 0), min(c[1] + ring, ny - 1) + 1):
                    row = (iz * ny + iy) * nx
                    if abs(iz - c[2]) == ring or abs(iy - c[1]) == ring:  # a face of the ring: whole row
                        for ix in range(max(c[0] - ring, 0), min(c[0] + ring, nx - 1) + 1):
                            k = _nn_cell(t, i, s, sid, cstart, row + ix, bd, bi, k, need)
                    else:  # inside rows: only the two end cells belong to the ring
                        if c[0] - ring >= 0:
                            k = _nn_cell(t, i, s, sid, cstart, row + c[0] - ring, bd, bi, k, need)
                        if c[0] + ring < nx:
                            k = _nn_cell(t, i, s, sid, cstart, row + c[0] + ring, bd, bi, k, need)
            if k == need:
                bound = ring * h * (1.0 - 1e-9)
                if bd[k - 1] < bound * bound:
                    break
        for j in range(3):
            if j < k:
                out_d2[i, j] = bd[j]
                out_idx[i, j] = bi[j]
            else:
                out_d2[i, j] = np.inf
                out_idx[i, j] = EMPTY_INDEX


@njit(cache=True, parallel=True)
def _nn_parallel(t, s, sid, cstart, lo, h, dims, nchunks, out_d2, out_idx):
    n = t.shape[0]
    step = (n + nchunks - 1) // nchunks
    for c in prange(nchunks):
        _nn_range(t, s, sid, cstart, lo, h, dims, c * step, min(n, (c + 1) * step), out_d2, out_idx)


def _three_nn_numba(t: np.ndarray, s: np.ndarray, tc: np.ndarray, sc: np.ndarray):
    n = t.shape[0]
    d2 = np.full((n, 3), np.inf)
    idx = np.full((n, 3), EMPTY_INDEX, dtype=np.int64)
    to, so = frame_offsets(tc), frame_offsets(sc)
    parallel = n >= PARALLEL_MIN_NN_TARGETS and numba.get_num_threads() > 1
    for b in range(tc.shape[0]):
        if tc[b] == 0 or sc[b] == 0:
            continue
        src = s[so[b]:so[b + 1]]
        lo, h, dims = _nn_grid(src)
        cell = np.minimum(np.floor((src - lo) / h).astype(np.int64), dims - 1)
        cid = (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
        order = np.argsort(cid, kind="stable")
        cstart = np.concatenate([[0], np.cumsum(np.bincount(cid, minlength=int(np.prod(dims))))]).astype(np.int64)
        args = (np.ascontiguousarray(t[to[b]:to[b + 1]]), np.ascontiguousarray(src[order]),
                (order + so[b]).astype(np.int64), cstart, lo, float(h), dims)
        od, oi = d2[to[b]:to[b + 1]], idx[to[b]:to[b + 1]]
        if parallel and tc[b] >= PARALLEL_MIN_NN_TARGETS // 4:
            _nn_parallel(*args, num_chunks(int(tc[b])), od, oi)
        else:
            _nn_range(*args, 0, int(tc[b]), od, oi)
    return d2, idx


def _three_nn_torch(t: torch.Tensor, s: torch.Tensor, tc: np.ndarray, sc: np.ndarray):
    """Per frame, chunks of targets x all sources (bounded memory), 3 rounds of first-argmin."""
    dev = t.device
    n = t.shape[0]
    d2 = torch.full((n, 3), math.inf, dtype=torch.float64, device=dev)
    idx = torch.full((n, 3), EMPTY_INDEX, dtype=torch.int64, device=dev)
    to, so = frame_offsets(tc), frame_offsets(sc)
    for b in range(tc.shape[0]):
        m = int(sc[b])
        if tc[b] == 0 or m == 0:
            continue
        src = s[so[b]:so[b + 1]]
        step = max(1, TORCH_CHUNK_ELEMS // m)
        for a in range(int(to[b]), int(to[b + 1]), step):
            e = min(int(to[b + 1]), a + step)
            dx = src[None, :, 0] - t[a:e, 0, None]
            dy = src[None, :, 1] - t[a:e, 1, None]
            dz = src[None, :, 2] - t[a:e, 2, None]
            dd = dx * dx + dy * dy + dz * dz
            rows = torch.arange(e - a, device=dev)
            for j in range(min(3, m)):
                k = dd.argmin(dim=1)  # first index of the minimum
                d2[a:e, j] = dd[rows, k]
                idx[a:e, j] = k + int(so[b])
                dd[rows, k] = math.inf
    return d2, idx


def three_nn(targets, sources, target_counts=None, source_counts=None, backend: str = "auto"):
    """The three nearest sources of each target within its frame (ties: lower row first).

    Args:
        targets: (n, >=3) points to interpolate to, B frames concatenated (metres).
        sources: (m, >=3) points that carry features, the same B frames, same device.
        target_counts, source_counts: (B,) per-frame counts (None, None for one frame).
        backend: "auto" (numba grid search on CPU, chunked torch elsewhere), "numba" or "torch".

    Returns:
        dist (n, 3) float64 Euclidean distances (metres, torch.sqrt of the float64 squared
        distance on the input's device), ascending; index (n, 3) int64 global
        source rows. A frame with fewer than 3 sources fills the missing slots with dist inf and
        index EMPTY_INDEX (a frame without sources: all three missing).

    The CPU kernel bins each frame's sources into a grid of about m / 2 cells and searches
    rings of cells outwards, so memory is linear in the points.
    """
    func = "three_nn"
    t = check_xyz(targets, func, "targets")
    s = check_xyz(sources, func, "sources", t.device)
    tc = check_counts(target_counts, t.shape[0], func, "target_counts", "targets")
    sc = check_counts(source_counts, s.shape[0], func, "source_counts", "sources")
    check_same_frames(tc, sc, func, "target_counts", "source_counts")
    if pick_backend(backend, t.device, func) == "torch":
        d2, idx = _three_nn_torch(t[:, :3].detach().to(torch.float64), s[:, :3].detach().to(torch.float64), tc, sc)
    else:
        d2n, idxn = _three_nn_numba(xyz_float64(t), xyz_float64(s), tc, sc)
        d2, idx = torch.from_numpy(d2n), torch.from_numpy(idxn)
    return torch.sqrt(d2), idx


def three_interpolate(features: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Weighted sum of three source rows: out[i] = sum_j weight[i, j] * features[index[i, j]].

    features (m, C), index (n, 3) int64 (EMPTY_INDEX = missing, contributes 0), weight (n, 3) -> (n, C).
    Differentiable w.r.t. features (and weight).
    """
    g = group_points(features, index)  # (n, 3, C)
    return (g * weight.to(g.dtype)[..., None]).sum(dim=1)


def three_nn_interpolate(targets, sources, source_features: torch.Tensor, target_counts=None,
                         source_counts=None, backend: str = "auto") -> torch.Tensor:
    """PointNet++ feature propagation: (n, C) features at the targets from (m, C) at the sources.

    Weights are 1 / (d + 1e-8) over the three nearest sources of the same frame (`three_nn`),
    normalised to sum 1. With fewer than 3 sources in a frame, the existing ones share the
    weight; a frame without sources gives zero features. Differentiable w.r.t. source_features
    (not w.r.t. the coordinates).
    """
    dist, index = three_nn(targets, sources, target_counts, source_counts, backend)
    m = sources.shape[0]
    if not isinstance(source_features, torch.Tensor) or source_features.ndim != 2 or source_features.shape[0] != m:
        raise ValueError(f"three_nn_interpolate: source_features must be an (m, C) tensor with one row per source "
                         f"({m}), got {tuple(getattr(source_features, 'shape', ())) or type(source_features).__name__}")
    w = torch.where(index >= 0, 1.0 / (dist + _NN_EPS), torch.zeros((), dtype=dist.dtype, device=dist.device))
    norm = w.sum(dim=1, keepdim=True)
    w = torch.where(norm > 0, w / norm.clamp_min(1e-300), w)
    return three_interpolate(source_features, index.to(source_features.device), w.to(source_features.device))
