"""Ball query and grouping (PointNet++ set abstraction), numba on CPU and torch elsewhere.

Contents
- `ball_query` -> `BallQuery`: the first `nsample` points within a radius of each centre.
- `group_points`, `group_neighbours`: gather (M, nsample, C) by point indices; zero rows for
  empty slots; differentiable w.r.t. the features.
- `group_linear`: a linear layer applied to `group_neighbours`' output, its feature term computed
  per point before the gather (a point shared by several balls is multiplied once).

Batches, indices, arithmetic and backends follow detbench.ops.point_batch. Departure from the
OpenPCDet kernel, on purpose: the ball test is inclusive (d^2 <= r^2, OpenPCDet: d^2 < r^2).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.point_batch import (EMPTY_INDEX, TORCH_CHUNK_ELEMS, check_counts, check_same_frames, check_xyz,
                                      num_chunks, pick_backend, xyz_float64)

__all__ = ["BallQuery", "ball_query", "group_points", "group_neighbours", "group_linear"]

# Estimated candidate pairs (centres x 27 x mean points per cell) below which the serial numba
# kernel runs (see PARALLEL_MIN_POINTS in points_in_boxes.py).
PARALLEL_MIN_BALL_CANDIDATES = 2_000_000
_BALL_CELL_MARGIN = 1.0 + 1e-6  # ball-query cells are radius * this, so a hit is never > 1 cell away


class BallQuery(NamedTuple):
    """Result of `ball_query`.

    index: (M, nsample) int64 rows of the concatenated points: the first hits in index order,
        the row padded by repeating its first hit; all EMPTY_INDEX for an empty ball.
    count: (M,) int64 distinct points in the row, min(hits, nsample); 0 for an empty ball.
    empty: (M,) bool, True where no point lies within the radius.
    """

    index: torch.Tensor
    count: torch.Tensor
    empty: torch.Tensor


_NEIGHBOURS = torch.tensor([(dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])


def _cell_lists(p: torch.Tensor, pc: np.ndarray, q: torch.Tensor, qc: np.ndarray, cell: float, func: str):
    """Points sorted by (frame, cell) and each centre's 27 neighbouring cell ranges.

    p (N, 3), q (M, 3) float64 on one device; pc, qc per-frame counts. Returns
    (perm (N,) point rows in sorted order, start (M, 27), count (M, 27)) int64: the sorted
    positions start..start+count-1 hold the points of one neighbouring cell of the centre's
    frame, in ascending row order (the sort is stable). Memory is linear in N + M.
    """
    dev = p.device
    pb = torch.repeat_interleave(torch.arange(pc.shape[0], device=dev), torch.as_tensor(pc, device=dev))
    qb = torch.repeat_interleave(torch.arange(qc.shape[0], device=dev), torch.as_tensor(qc, device=dev))
    lo = p.min(dim=0).values
    ip = torch.floor((p - lo) / cell).to(torch.int64) + 1  # cells 1..n-2; 0 and n-1 stay free
    ext = (ip.max(dim=0).values + 2).tolist()
    _check_cells(ext, pc.shape[0], cell, func)
    key = ((pb * ext[2] + ip[:, 2]) * ext[1] + ip[:, 1]) * ext[0] + ip[:, 0]
    skey, perm = torch.sort(key, stable=True)
    ukey, ucount = torch.unique_consecutive(skey, return_counts=True)
    ustart = torch.cumsum(ucount, 0) - ucount
    hi = torch.as_tensor(ext, dtype=torch.float64, device=dev)
    fq = torch.floor((q - lo) / cell) + 1
    iq = torch.minimum(torch.maximum(fq, torch.full_like(fq, -2.0)), hi + 1).to(torch.int64)  # far centres stay far
    nc = iq[:, None, :] + _NEIGHBOURS.to(dev)[None]  # (M, 27, 3)
    ok = ((nc >= 0) & (nc < torch.as_tensor(ext, device=dev))).all(dim=2)
    qkey = ((qb[:, None] * ext[2] + nc[..., 2]) * ext[1] + nc[..., 1]) * ext[0] + nc[..., 0]
    pos = torch.searchsorted(ukey, qkey).clamp_max(ukey.shape[0] - 1)  # N > 0, so ukey is not empty
    found = ok & (ukey[pos] == qkey)
    zero = torch.zeros_like(qkey)
    start = torch.where(found, ustart[pos], zero)
    count = torch.where(found, ucount[pos], zero)
    return perm, start, count


def _point_cells_np(p: np.ndarray, pc: np.ndarray, cell: float, func: str):
    """The point half of `_cell_lists` in numpy, for the numba path (same integers).

    Returns (perm, ukey, ustart, ucount, lo, ext): rows sorted by (frame, cell), the occupied
    cell keys ascending with their first sorted position and size, the grid origin and size.
    """
    pb = np.repeat(np.arange(pc.shape[0], dtype=np.int64), pc)
    lo = p.min(axis=0)
    ip = np.floor((p - lo) / cell).astype(np.int64) + 1
    ext = ip.max(axis=0) + 2
    _check_cells(ext, pc.shape[0], cell, func)
    key = ((pb * ext[2] + ip[:, 2]) * ext[1] + ip[:, 1]) * ext[0] + ip[:, 0]
    perm = np.argsort(key, kind="stable")
    skey = key[perm]
    ustart = np.flatnonzero(np.concatenate([[True], skey[1:] != skey[:-1]]))
    ucount = np.diff(np.concatenate([ustart, [skey.shape[0]]]))
    return perm, skey[ustart], ustart, ucount, lo, ext


def _check_cells(ext, frames: int, cell: float, func: str) -> None:
    ext = [int(e) for e in ext]
    if float(frames) * float(np.prod(np.asarray(ext, dtype=np.float64))) >= 2.0 ** 62:
        raise ValueError(f"{func}: radius {cell / _BALL_CELL_MARGIN:g} m is too small for the extent of the points "
                         f"({ext} cells per axis); use a larger radius or split the frames")


@njit(cache=True)
def _ball_range(ps, perm, ukey, ustart, ucount, lo, ext, cell, q, qb, r2, c0, c1, index, found):
    """Centres c0..c1-1: look up the 27 cells around each centre (as `_cell_lists` does), keep
    the nsample smallest rows among the hits (d^2 <= r2), pad the row."""
    ns = index.shape[1]
    nu = ukey.shape[0]
    ic = np.empty(3, dtype=np.int64)
    for c in range(c0, c1):
        for a in range(3):
            f = np.floor((q[c, a] - lo[a]) / cell) + 1.0
            ic[a] = np.int64(min(max(f, -2.0), ext[a] + 1.0))
        row = index[c]
        k = 0
        for oz in range(-1, 2):
            for oy in range(-1, 2):
                for ox in range(-1, 2):
                    cx, cy, cz = ic[0] + ox, ic[1] + oy, ic[2] + oz
                    if cx < 0 or cy < 0 or cz < 0 or cx >= ext[0] or cy >= ext[1] or cz >= ext[2]:
                        continue
                    key = ((qb[c] * ext[2] + cz) * ext[1] + cy) * ext[0] + cx
                    u = np.searchsorted(ukey, key)
                    if u >= nu or ukey[u] != key:
                        continue
                    for pos in range(ustart[u], ustart[u] + ucount[u]):
                        dx = ps[pos, 0] - q[c, 0]
                        dy = ps[pos, 1] - q[c, 1]
                        dz = ps[pos, 2] - q[c, 2]
                        if dx * dx + dy * dy + dz * dz <= r2:
                            pid = perm[pos]
                            if k < ns:
                                t = k
                                k += 1
                            elif pid < row[ns - 1]:
                                t = ns - 1
                            else:
                                continue
                            while t > 0 and row[t - 1] > pid:  # sorted insertion
                                row[t] = row[t - 1]
                                t -= 1
                            row[t] = pid
        found[c] = k
        for t in range(k, ns):
            row[t] = row[0] if k > 0 else EMPTY_INDEX


@njit(cache=True, parallel=True)
def _ball_parallel(ps, perm, ukey, ustart, ucount, lo, ext, cell, q, qb, r2, nchunks, index, found):
    m = q.shape[0]
    step = (m + nchunks - 1) // nchunks
    for c in prange(nchunks):
        _ball_range(ps, perm, ukey, ustart, ucount, lo, ext, cell, q, qb, r2, c * step, min(m, (c + 1) * step),
                    index, found)


def _ball_torch(ps, perm, q, start, count, r2: float, nsample: int):
    """Torch twin of `_ball_range`: candidate pairs expanded in chunks of centres (bounded memory)."""
    dev = q.device
    m, n = q.shape[0], ps.shape[0]
    index = torch.full((m, nsample), EMPTY_INDEX, dtype=torch.int64, device=dev)
    found = torch.zeros(m, dtype=torch.int64, device=dev)
    per = count.sum(dim=1)
    csum = torch.cumsum(per, 0)
    c0 = 0
    while c0 < m:
        base = int(csum[c0 - 1]) if c0 else 0
        c1 = int(torch.searchsorted(csum, torch.tensor(base + TORCH_CHUNK_ELEMS, device=dev), right=True))
        c1 = min(max(c1, c0 + 1), m)
        k = count[c0:c1].reshape(-1)
        s = start[c0:c1].reshape(-1)
        tot = int(k.sum())
        if tot:
            seg = torch.repeat_interleave(torch.arange(k.shape[0], device=dev), k)
            pos = s[seg] + torch.arange(tot, device=dev) - (torch.cumsum(k, 0) - k)[seg]
            cen = c0 + torch.div(seg, start.shape[1], rounding_mode="floor")
            dx = ps[pos, 0] - q[cen, 0]
            dy = ps[pos, 1] - q[cen, 1]
            dz = ps[pos, 2] - q[cen, 2]
            hit = dx * dx + dy * dy + dz * dz <= r2
            pid, cen = perm[pos[hit]], cen[hit]
            order = torch.argsort(cen * n + pid)
            pid, cen = pid[order], cen[order]
            hits = torch.bincount(cen - c0, minlength=c1 - c0)
            rank = torch.arange(pid.shape[0], device=dev) - (torch.cumsum(hits, 0) - hits)[cen - c0]
            keep = rank < nsample
            index[cen[keep], rank[keep]] = pid[keep]
            found[c0:c1] = hits.clamp_max(nsample)
        c0 = c1
    slot = torch.arange(nsample, device=dev)
    index = torch.where(slot[None] < found[:, None], index, index[:, :1])
    return index, found


def ball_query(xyz, centres, radius: float, nsample: int, xyz_counts=None, centre_counts=None,
               backend: str = "auto") -> BallQuery:
    """For each centre, the first `nsample` points of its frame within `radius` (index order).

    A point is within the ball when d^2 <= radius^2 (inclusive, in float64; a point exactly on
    the sphere counts; OpenPCDet's kernel uses d^2 < r^2). Hits are taken in ascending row
    order; a ball with fewer than nsample hits repeats its first hit in the remaining slots;
    an empty ball gives a row of EMPTY_INDEX and `empty` True (`group_points` turns it into zeros).

    The search sorts the points by (frame, cell) with cells of side radius (x (1 + 1e-6)) and
    scans each centre's 27 neighbouring cells: memory is linear in the points and centres.

    Args:
        xyz: (N, >=3) points of B frames concatenated (metres).
        centres: (M, >=3) centres of the same B frames concatenated, on the same device.
        radius: metres, > 0. nsample: slots per centre, >= 1.
        xyz_counts, centre_counts: (B,) per-frame counts (None, None for one frame).
        backend: "auto", "numba" (CPU) or "torch".

    Returns:
        `BallQuery` (index (M, nsample) int64 global rows, count (M,) int64, empty (M,) bool).
    """
    func = "ball_query"
    p = check_xyz(xyz, func, "xyz")
    q = check_xyz(centres, func, "centres", p.device)
    r = float(radius)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"{func}: radius must be a positive number of metres, got {radius!r}")
    if int(nsample) < 1:
        raise ValueError(f"{func}: nsample must be >= 1, got {nsample!r}")
    ns = int(nsample)
    pc = check_counts(xyz_counts, p.shape[0], func, "xyz_counts", "points")
    qc = check_counts(centre_counts, q.shape[0], func, "centre_counts", "centres")
    check_same_frames(pc, qc, func, "xyz_counts", "centre_counts")
    be = pick_backend(backend, p.device, func)
    m = q.shape[0]
    if m == 0 or p.shape[0] == 0:
        index = torch.full((m, ns), EMPTY_INDEX, dtype=torch.int64, device=p.device)
        zero = torch.zeros(m, dtype=torch.int64, device=p.device)
        return BallQuery(index, zero, zero == 0)
    r2 = r * r
    if be == "torch":
        p64, q64 = p[:, :3].detach().to(torch.float64), q[:, :3].detach().to(torch.float64)
        perm, start, count = _cell_lists(p64, pc, q64, qc, r * _BALL_CELL_MARGIN, func)
        index, found = _ball_torch(p64[perm], perm, q64, start, count, r2, ns)
    else:
        p64, q64 = xyz_float64(p), xyz_float64(q)
        cell = r * _BALL_CELL_MARGIN
        perm, ukey, ustart, ucount, lo, ext = _point_cells_np(p64, pc, cell, func)
        qb = np.repeat(np.arange(qc.shape[0], dtype=np.int64), qc)
        args = (np.ascontiguousarray(p64[perm]), perm, ukey, ustart, ucount, lo, ext, cell, q64, qb, r2)
        idx = np.empty((m, ns), dtype=np.int64)
        fnd = np.empty(m, dtype=np.int64)
        # work estimate: the mean cell occupancy times 27 cells per centre
        if 27 * m * p.shape[0] / max(ukey.shape[0], 1) >= PARALLEL_MIN_BALL_CANDIDATES and numba.get_num_threads() > 1:
            _ball_parallel(*args, num_chunks(m), idx, fnd)
        else:
            _ball_range(*args, 0, m, idx, fnd)
        index, found = torch.from_numpy(idx), torch.from_numpy(fnd)
    return BallQuery(index, found, found == 0)


def _gather_index(index, rows: torch.Tensor, func: str, name: str, fix: str) -> torch.Tensor:
    """`index` as int64 on `rows`' device, checked: an integer tensor whose entries are EMPTY_INDEX or
    rows of `rows` (named `name` in the error, with `fix`)."""
    if not isinstance(index, torch.Tensor) or index.dtype.is_floating_point:
        raise ValueError(f"{func}: index must be an integer tensor (e.g. BallQuery.index), got {type(index).__name__}")
    index = index.to(rows.device).long()
    if index.numel() and int(index.max()) >= rows.shape[0]:
        raise ValueError(f"{func}: index holds row {int(index.max())} but {name} has {rows.shape[0]} rows; {fix}")
    return index


def group_points(features: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Gather rows of `features` (N, C) by `index` (M, K) -> (M, K, C); EMPTY_INDEX gives zeros.

    Differentiable w.r.t. `features` (plain torch indexing; gradients of repeated rows add up).
    Use with `BallQuery.index` (empty balls are rows of EMPTY_INDEX) or `three_nn` indices.
    """
    func = "group_points"
    if not isinstance(features, torch.Tensor) or features.ndim != 2:
        raise ValueError(f"{func}: features must be an (N, C) tensor, got "
                         f"{tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__}")
    index = _gather_index(index, features, func, "features",
                          "pass the features of the same concatenated points the indices refer to")
    valid = index >= 0
    if features.shape[0] == 0:
        return features.new_zeros((*index.shape, features.shape[1]))
    g = features[index.clamp_min(0)]
    return torch.where(valid[..., None], g, torch.zeros((), dtype=g.dtype, device=g.device))


def group_neighbours(xyz: torch.Tensor, centres: torch.Tensor, index: torch.Tensor,
                     features: torch.Tensor | None = None, use_xyz: bool = True) -> torch.Tensor:
    """PointNet++ grouping: (M, K, 3 + C) relative coordinates xyz - centre, then features.

    Args:
        xyz: (N, >=3) points (metres); centres: (M, >=3); index: (M, K) from `ball_query`.
        features: optional (N, C) per-point features. use_xyz: put the 3 relative coordinates
            first (needed when features is None).

    Returns:
        (M, K, 3 * use_xyz + C); every entry of an empty ball (EMPTY_INDEX) is zero.
        Differentiable w.r.t. xyz, centres and features.
    """
    if features is None and not use_xyz:
        raise ValueError("group_neighbours: with features=None, use_xyz must be True (nothing to group otherwise)")
    parts = []
    if use_xyz:
        valid = (index >= 0).to(xyz.device)[..., None]
        rel = group_points(xyz[:, :3], index) - centres[:, None, :3]
        parts.append(torch.where(valid, rel, torch.zeros((), dtype=rel.dtype, device=rel.device)))
    if features is not None:
        parts.append(group_points(features, index))
    return torch.cat(parts, dim=2) if len(parts) > 1 else parts[0]


def group_linear(xyz: torch.Tensor, centres: torch.Tensor, index: torch.Tensor, features: torch.Tensor | None,
                 weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """`F.linear(group_neighbours(xyz, centres, index, features), weight, bias)`, computed without
    the (M, K, 3 + C) grouped tensor.

    The layer is linear, so W [x_j - c, f_j] + b = W_xyz (x_j - c) + (W_f f_j + b): the feature term is
    computed once per point (N rows) and gathered, so a point in several balls is multiplied once;
    the relative coordinates are formed as in `group_neighbours` (x_j - c before any product, so far
    points lose no precision). An empty slot (EMPTY_INDEX) gives `bias` (zeros without one), as a
    zero input row does. Equal to the grouped form up to float rounding; differentiable w.r.t. xyz,
    centres, features, weight and bias.

    Args:
        xyz: (N, >=3) points (metres); centres: (M, >=3); index: (M, K) from `ball_query`.
        features: optional (N, C). weight: (O, 3 + C), the relative coordinates' columns first.

    Returns:
        (M, K, O).
    """
    func = "group_linear"
    c = 0 if features is None else features.shape[1]
    if weight.ndim != 2 or weight.shape[1] != 3 + c:
        raise ValueError(f"{func}: weight must be (O, 3 + C) = (O, {3 + c}) for {c} feature channels, got "
                         f"{tuple(weight.shape)}")
    index = _gather_index(index, xyz, func, "xyz", "pass the points the indices refer to")
    out_channels = weight.shape[0]
    if xyz.shape[0] == 0:
        out = xyz.new_zeros((*index.shape, out_channels))
    else:
        safe = index.clamp_min(0)
        rel = xyz[:, :3][safe] - centres[:, None, :3]  # (M, K, 3)
        out = rel @ weight[:, :3].t()
        if features is not None:
            per_point = features @ weight[:, 3:].t() if bias is None else torch.addmm(bias, features, weight[:, 3:].t())
            out = out + per_point[safe]
        elif bias is not None:
            out = out + bias
    empty = torch.zeros((), dtype=out.dtype, device=out.device) if bias is None else bias.to(out.dtype)
    return torch.where((index >= 0)[..., None], out, empty)
