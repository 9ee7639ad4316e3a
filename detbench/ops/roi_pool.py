"""PointRCNN stage-2 RoI point pooling and the canonical RoI frame, numba on CPU and torch elsewhere.

Contents
- `roi_point_pool` -> `RoIPoints`: a fixed number of the points in each enlarged RoI, in the
  RoI's canonical frame, with their features.
- `to_canonical` / `from_canonical`: points into a RoI's canonical frame and back.

Batches, indices, arithmetic and backends follow detbench.ops.point_batch. Departure from
OpenPCDet, on purpose: a crowded RoI is subsampled evenly instead of keeping its first
num_samples points (see `roi_point_pool`).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.grouping import group_points
from detbench.ops.point_batch import (EMPTY_INDEX, TORCH_CHUNK_ELEMS, check_counts, check_same_frames, check_xyz,
                                      frame_offsets, num_chunks, pick_backend, to_tensor, xyz_float64)
from detbench.ops.points_in_boxes import _AABB_PAD, _inside

__all__ = ["RoIPoints", "roi_point_pool", "to_canonical", "from_canonical"]

# Point-in-RoI tests (sum over frames of RoIs x points) below which the serial numba kernel runs
# (see PARALLEL_MIN_POINTS in points_in_boxes.py).
PARALLEL_MIN_ROI_TESTS = 8_000_000


class RoIPoints(NamedTuple):
    """Result of `roi_point_pool`.

    points: (R, S, 3 + C) canonical x, y, z (metres, RoI frame) then the C point features;
        zeros for an empty RoI.
    index: (R, S) int64 rows of the concatenated points; EMPTY_INDEX for an empty RoI.
    count: (R,) int64 points inside the enlarged RoI (before sampling to S).
    empty: (R,) bool, True where the enlarged RoI holds no point.
    """

    points: torch.Tensor
    index: torch.Tensor
    count: torch.Tensor
    empty: torch.Tensor


def _rot(rois, xyz):
    r = rois[..., None, :] if xyz.ndim == rois.ndim + 1 else rois
    if xyz.ndim != r.ndim:
        raise ValueError(f"canonical transform: xyz (..., P, 3) or (..., 3) must pair with rois (..., 7); "
                         f"got shapes {tuple(xyz.shape)} and {tuple(rois.shape)}")
    if isinstance(xyz, torch.Tensor):
        return r, torch.cos(r[..., 6]), torch.sin(r[..., 6]), torch.stack
    return r, np.cos(r[..., 6]), np.sin(r[..., 6]), np.stack


def to_canonical(xyz, rois):
    """Points into each RoI's canonical frame: translate to the box centre, rotate by -heading.

    xyz (R, P, 3) points per RoI, or (R, 3) one point per RoI; rois (R, 7) x, y, z, dx, dy, dz,
    heading (metres, radians; any leading batch shape works the same). In the canonical frame
    the box is axis-aligned at the origin: +x along the heading, +y to its left, +z up.
    numpy or torch (same type out); differentiable in torch.
    """
    r, c, s, stack = _rot(rois, xyz)
    x = xyz[..., 0] - r[..., 0]
    y = xyz[..., 1] - r[..., 1]
    return stack([x * c + y * s, -x * s + y * c, xyz[..., 2] - r[..., 2]], -1)


def from_canonical(xyz, rois):
    """Inverse of `to_canonical`: rotate by +heading, then translate to the box centre."""
    r, c, s, stack = _rot(rois, xyz)
    u, v = xyz[..., 0], xyz[..., 1]
    return stack([u * c - v * s + r[..., 0], u * s + v * c + r[..., 1], xyz[..., 2] + r[..., 2]], -1)


def _roi_table(rois: torch.Tensor, extra: float) -> torch.Tensor:
    """(R, 12) float64 table of the enlarged RoIs in the layout of points_in_boxes._box_table.

    Computed once in torch and handed to both backends, so they test against the same numbers.
    """
    b = rois[:, :7].detach().to(torch.float64)
    c, s = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    hx, hy, hz = 0.5 * (b[:, 3] + 2 * extra), 0.5 * (b[:, 4] + 2 * extra), 0.5 * (b[:, 5] + 2 * extra)
    ex = c.abs() * hx + s.abs() * hy + _AABB_PAD
    ey = s.abs() * hx + c.abs() * hy + _AABB_PAD
    return torch.stack([b[:, 0], b[:, 1], c, s, hx, hy, b[:, 2] - hz, b[:, 2] + hz,
                        b[:, 0] - ex, b[:, 0] + ex, b[:, 1] - ey, b[:, 1] + ey], dim=1)


@njit(cache=True)
def _roi_range(p, table, fstart, fcount, r0, r1, index, count, buf):
    """RoIs r0..r1-1: inside points of the RoI's frame in row order -> S sampled rows."""
    ns = index.shape[1]
    for r in range(r0, r1):
        k = 0
        for i in range(fstart[r], fstart[r] + fcount[r]):
            if _inside(p[i, 0], p[i, 1], p[i, 2], table, r):
                buf[k] = i
                k += 1
        count[r] = k
        for j in range(ns):
            if k == 0:
                index[r, j] = EMPTY_INDEX
            elif k <= ns:
                index[r, j] = buf[j % k]
            else:
                index[r, j] = buf[(j * k) // ns]


@njit(cache=True, parallel=True)
def _roi_parallel(p, table, fstart, fcount, nchunks, index, count, bufsize):
    r = table.shape[0]
    step = (r + nchunks - 1) // nchunks
    for c in prange(nchunks):
        buf = np.empty(bufsize, dtype=np.int64)
        _roi_range(p, table, fstart, fcount, c * step, min(r, (c + 1) * step), index, count, buf)


def _roi_torch(p: torch.Tensor, table: torch.Tensor, pc: np.ndarray, rc: np.ndarray, ns: int):
    """Torch twin of `_roi_range`: per frame, chunks of RoIs x points (bounded memory)."""
    dev = p.device
    nr = table.shape[0]
    index = torch.full((nr, ns), EMPTY_INDEX, dtype=torch.int64, device=dev)
    count = torch.zeros(nr, dtype=torch.int64, device=dev)
    po, ro = frame_offsets(pc), frame_offsets(rc)
    slot = torch.arange(ns, device=dev)
    for b in range(pc.shape[0]):
        n = int(pc[b])
        if rc[b] == 0 or n == 0:
            continue
        x, y, z = (p[po[b]:po[b + 1], a][None] for a in range(3))
        step = max(1, TORCH_CHUNK_ELEMS // n)
        for a in range(int(ro[b]), int(ro[b + 1]), step):
            t = table[a:min(int(ro[b + 1]), a + step), :, None]
            inside = (x >= t[:, 8]) & (x <= t[:, 9]) & (y >= t[:, 10]) & (y <= t[:, 11])
            inside &= (z >= t[:, 6]) & (z <= t[:, 7])
            rx, ry = x - t[:, 0], y - t[:, 1]
            inside &= (((rx * t[:, 2] + ry * t[:, 3]).abs() <= t[:, 4])
                       & ((-rx * t[:, 3] + ry * t[:, 2]).abs() <= t[:, 5]))
            cs = torch.cumsum(inside, dim=1)
            k = cs[:, -1]
            rank = torch.where(k[:, None] > ns, torch.div(slot[None] * k[:, None], ns, rounding_mode="floor"),
                               slot[None] % k.clamp_min(1)[:, None])
            local = torch.searchsorted(cs, rank + 1)  # position of the (rank+1)-th inside point
            e = a + t.shape[0]
            index[a:e] = torch.where(k[:, None] > 0, local + int(po[b]), torch.full_like(local, EMPTY_INDEX))
            count[a:e] = k
    return index, count


def roi_point_pool(xyz, rois, num_samples: int = 512, extra: float = 1.0, features=None,
                   point_counts=None, roi_counts=None, backend: str = "auto") -> RoIPoints:
    """PointRCNN stage-2 RoI point pooling: a fixed number of points per RoI, in its own frame.

    A point belongs to a RoI when it lies inside the box enlarged by `extra` metres on every
    side (dx + 2e, dy + 2e, dz + 2e), with the geometry of `points_in_boxes` (all faces
    inclusive, heading counter-clockwise from +x). The inside points of the RoI's frame are
    taken in ascending row order; with k <= S of them, slot j holds inside point j mod k
    (cyclic repetition); with k > S, slot j holds inside point floor(j * k / S), an even,
    deterministic subsample over the whole list (OpenPCDet takes the first S instead, which on
    a scan-ordered cloud keeps only the first rings). Points are returned in the canonical
    frame of their RoI (`to_canonical`), followed by their features.

    Args:
        xyz: (N, >=3) points of B frames concatenated (metres); only x, y, z are used, pass
            intensity and other columns through `features`.
        rois: (R, 7) x, y, z, dx, dy, dz, heading of B frames concatenated, same device.
        num_samples: S, points per RoI (PointRCNN: 512). extra: metres added on each side (1.0).
        features: optional (N, C) per-point features carried along (intensity, depth, score, ...).
        point_counts, roi_counts: (B,) per-frame counts (None, None for one frame).
        backend: "auto" (numba on CPU, torch elsewhere), "numba" or "torch".

    Returns:
        `RoIPoints` (points (R, S, 3 + C), index (R, S) int64 global rows, count (R,), empty (R,)),
        zero rows / EMPTY_INDEX indices for empty RoIs. Differentiable w.r.t. xyz and features (the
        selection itself is not).
    """
    func = "roi_point_pool"
    p = check_xyz(xyz, func, "xyz")
    b = check_xyz(rois, func, "rois", p.device, cols=7)
    ns = int(num_samples)
    if ns < 1:
        raise ValueError(f"{func}: num_samples must be >= 1, got {num_samples!r}")
    e = float(extra)
    if not math.isfinite(e):
        raise ValueError(f"{func}: extra must be a finite number of metres, got {extra!r}")
    if features is not None:
        features = to_tensor(features, func, "features")
        if features.ndim != 2 or features.shape[0] != p.shape[0] or features.device != p.device:
            raise ValueError(f"{func}: features must be (N, C) with one row per point ({p.shape[0]}) on {p.device}, "
                             f"got {tuple(features.shape)} on {features.device}")
    pc = check_counts(point_counts, p.shape[0], func, "point_counts", "points")
    rc = check_counts(roi_counts, b.shape[0], func, "roi_counts", "rois")
    check_same_frames(pc, rc, func, "point_counts", "roi_counts")
    be = pick_backend(backend, p.device, func)
    table = _roi_table(b, e)
    nr = b.shape[0]
    if be == "torch":
        index, count = _roi_torch(p[:, :3].detach().to(torch.float64), table, pc, rc, ns)
    else:
        po = frame_offsets(pc)
        fid = np.repeat(np.arange(pc.shape[0]), rc)
        fstart, fcount = po[fid].astype(np.int64), pc[fid].astype(np.int64)
        idx = np.full((nr, ns), EMPTY_INDEX, dtype=np.int64)
        cnt = np.zeros(nr, dtype=np.int64)
        args = (xyz_float64(p), np.ascontiguousarray(table.numpy()), fstart, fcount)
        bufsize = int(pc.max()) if pc.size else 0
        if int((pc * rc).sum()) >= PARALLEL_MIN_ROI_TESTS and numba.get_num_threads() > 1:
            _roi_parallel(*args, num_chunks(nr), idx, cnt, bufsize)
        elif nr:
            _roi_range(*args, 0, nr, idx, cnt, np.empty(bufsize, dtype=np.int64))
        index, count = torch.from_numpy(idx).to(p.device), torch.from_numpy(cnt).to(p.device)
    empty = count == 0
    gathered = group_points(p[:, :3], index)  # (R, S, 3), zeros for empty RoIs
    canon = to_canonical(gathered, b[:, :7].to(gathered.dtype))
    canon = torch.where(empty[:, None, None], torch.zeros((), dtype=canon.dtype, device=canon.device), canon)
    if features is None:
        return RoIPoints(canon, index, count, empty)
    dt = torch.promote_types(canon.dtype, features.dtype)
    return RoIPoints(torch.cat([canon.to(dt), group_points(features, index).to(dt)], dim=2), index, count, empty)
