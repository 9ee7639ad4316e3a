"""CT3D's cylinder query: the points in a vertical cylinder around each proposal, numba on CPU
and torch elsewhere.

Contents
- `cylinder_query`: per centre, a fixed number of the points of one frame within a radius in
  BEV (any z), ordered by a key per point.

Indices, backends and argument checks follow detbench.ops.point_batch; the query takes one
frame per call and compares squared distances in the points' float type.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from detbench.ops.point_batch import EMPTY_INDEX, pick_backend, to_tensor

__all__ = ["cylinder_query"]

_CYL_MAX_CELLS = 1 << 22  # grid cells of the numba path at most (the cell grows past this)


@njit(cache=True)
def _cell_span(c, rr, lo, cell, n):  # pragma: no cover - numba
    """The grid cells [first, last] a cylinder of radius rr around c overlaps, clamped to 0..n-1 while still
    floats (so a centre or radius far outside the grid cannot overflow the int conversion); first > last when
    none."""
    a, b = (c - rr - lo) / cell, (c + rr - lo) / cell
    if not (b >= 0.0) or not (a <= n - 1.0):
        return 1, 0
    return (0 if a <= 0.0 else int(a)), (n - 1 if b >= n - 1.0 else int(b))


@njit(cache=True)
def _cylinder_numba(px, py, keys, cx, cy, r2, k, cell, out_idx, out_cnt):  # pragma: no cover - numba
    n, r = px.shape[0], cx.shape[0]
    rmax = math.sqrt(r2.max())  # r >= 1: the caller returns before for no centre
    # the grid covers the points that can lie in some cylinder: the cylinders' extent cut to the points'
    # (a proposal of an untrained model can be finite yet 1e13 m wide; its extent alone would overflow int64)
    x0, x1 = max(cx.min() - rmax, px.min()) - 1.0, min(cx.max() + rmax, px.max()) + 1.0
    y0, y1 = max(cy.min() - rmax, py.min()) - 1.0, min(cy.max() + rmax, py.max()) + 1.0
    if x1 < x0 or y1 < y0:  # no point near any centre
        for j in range(r):
            out_cnt[j] = 0
            for s in range(k):
                out_idx[j, s] = EMPTY_INDEX
        return
    while ((x1 - x0) / cell + 1.0) * ((y1 - y0) / cell + 1.0) > _CYL_MAX_CELLS:  # in floats: no overflow
        cell *= 2.0
    nx, ny = int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1
    start = np.zeros(nx * ny + 1, np.int64)
    cid = np.full(n, -1, np.int64)
    for i in range(n):  # counting sort of the points that can lie in some cylinder, by cell
        if px[i] >= x0 and px[i] <= x1 and py[i] >= y0 and py[i] <= y1:
            c = int((px[i] - x0) / cell) * ny + int((py[i] - y0) / cell)
            cid[i] = c
            start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(start[-1], np.int64)
    for i in range(n):  # ascending index within a cell
        if cid[i] >= 0:
            order[fill[cid[i]]] = i
            fill[cid[i]] += 1
    buf_idx = np.empty(n, np.int64)
    buf_key = np.empty(n, keys.dtype)
    sel = np.empty(n, np.int64)
    ties = np.empty(n, np.int64)
    for j in range(r):
        rr = math.sqrt(r2[j])
        ix0, ix1 = _cell_span(cx[j], rr, x0, cell, nx)
        iy0, iy1 = _cell_span(cy[j], rr, y0, cell, ny)
        m = 0
        for ix in range(ix0, ix1 + 1):
            for iy in range(iy0, iy1 + 1):
                c = ix * ny + iy
                for t in range(start[c], start[c + 1]):
                    i = order[t]
                    dx, dy = cx[j] - px[i], cy[j] - py[i]
                    if dx * dx + dy * dy <= r2[j]:
                        buf_idx[m] = i
                        m += 1
        out_cnt[j] = m
        if m == 0:
            for s in range(k):
                out_idx[j, s] = EMPTY_INDEX
            continue
        for t in range(m):
            buf_key[t] = keys[buf_idx[t]]
        take = m
        if m > k:  # keep the k smallest keys (ties at the k-th key: lowest index first), O(m)
            thr = np.partition(buf_key[:m], k - 1)[k - 1]
            take = 0
            for t in range(m):
                if buf_key[t] < thr:
                    sel[take] = buf_idx[t]
                    take += 1
            nt = 0
            for t in range(m):
                if buf_key[t] == thr:
                    ties[nt] = buf_idx[t]
                    nt += 1
            ties_sorted = np.sort(ties[:nt])
            for t in range(k - take):
                sel[take + t] = ties_sorted[t]
            take = k
        else:
            for t in range(m):
                sel[t] = buf_idx[t]
        cand = np.sort(sel[:take])  # ascending index, so equal keys keep index order
        for t in range(take):
            buf_key[t] = keys[cand[t]]
        o = np.argsort(buf_key[:take], kind="mergesort")
        for s in range(k):
            out_idx[j, s] = cand[o[s % take]]


def _cylinder_torch(xy: torch.Tensor, keys: torch.Tensor, centres: torch.Tensor, r2: torch.Tensor, k: int,
                    max_pairs: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    r, n = centres.shape[0], xy.shape[0]
    index = torch.zeros(r, k, dtype=torch.int64, device=xy.device)
    count = torch.zeros(r, dtype=torch.int64, device=xy.device)
    step = max(1, max_pairs // max(n, 1))
    for s in range(0, r, step):  # chunks bound the (r, N) memory
        d2 = (centres[s:s + step, None, :] - xy[None, :, :]).pow(2).sum(-1)
        inside = d2 <= r2[s:s + step, None]
        rows = inside.shape[0]
        masked = torch.where(inside, keys.expand(rows, n), torch.full_like(keys, 2.0).expand(rows, n))
        kk = min(k, n)
        _, idx = masked.topk(kk, dim=1, largest=False)  # ascending key: inside points first
        if kk < k:
            idx = torch.cat([idx, idx.new_zeros(rows, k - kk)], dim=1)
        cnt = inside.sum(dim=1)
        slot = torch.arange(k, device=xy.device)[None, :].expand(rows, k)
        index[s:s + step] = torch.gather(idx, 1, torch.remainder(slot, cnt.clamp(min=1)[:, None]))
        count[s:s + step] = cnt
    return torch.where(count[:, None] > 0, index, EMPTY_INDEX), count


def cylinder_query(xy, keys, centres, radius, num_samples: int, backend: str = "auto"
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """CT3D's point selection: per centre, `num_samples` points of one frame within a vertical cylinder.

    A point is inside when its BEV distance to the centre is <= the centre's radius (any z;
    squared distances compared in the points' float type). The inside points are ordered
    by ascending `keys` (equal keys by index); slot j holds inside point j when there are at
    least `num_samples` of them, else inside point j mod count (cyclic repetition).

    Args:
        xy: (N, >=2) points of one frame (only x, y used), metres.
        keys: (N,) floats in [0, 1): the selection order (random keys: a uniform random subset).
        centres: (R, 2) cylinder centres; radius: (R,) radii, metres; both on the points' device.
        num_samples: K >= 1.
        backend: "auto" (numba on CPU: a BEV grid, memory linear in N + R * K; torch elsewhere:
            (R, N) distances in chunks), "numba" or "torch"; both give the same indices.
    Returns:
        (index (R, K) int64 rows of `xy`, EMPTY_INDEX in every slot of an empty cylinder; count (R,)
        int64 points inside).
    """
    func = "cylinder_query"
    p, c = to_tensor(xy, func, "xy"), to_tensor(centres, func, "centres")
    if p.ndim != 2 or p.shape[1] < 2 or c.ndim != 2 or c.shape[1] < 2:
        raise ValueError(f"{func}: xy must be (N, >=2) and centres (R, >=2); got {tuple(p.shape)} and {tuple(c.shape)}")
    kt, rad = to_tensor(keys, func, "keys"), to_tensor(radius, func, "radius")
    if kt.shape != (p.shape[0],) or rad.shape != (c.shape[0],):
        raise ValueError(f"{func}: keys must be ({p.shape[0]},) and radius ({c.shape[0]},); got {tuple(kt.shape)} "
                         f"and {tuple(rad.shape)}")
    k = int(num_samples)
    if k < 1:
        raise ValueError(f"{func}: num_samples must be >= 1, got {num_samples!r}")
    if not bool(torch.isfinite(c[:, :2]).all()) or not bool(torch.isfinite(rad).all()):
        raise ValueError(f"{func}: centres and radius must be finite; drop non-finite proposals first")
    dt = p.dtype if p.dtype.is_floating_point else torch.float32
    xy2, cen = p[:, :2].to(dt), c[:, :2].to(dt)
    r2 = rad.to(dt).pow(2)
    if c.shape[0] == 0 or p.shape[0] == 0:
        return (torch.full((c.shape[0], k), EMPTY_INDEX, dtype=torch.int64, device=p.device),
                torch.zeros(c.shape[0], dtype=torch.int64, device=p.device))
    if pick_backend(backend, p.device, func) == "torch":
        return _cylinder_torch(xy2, kt.to(p.device), cen, r2, k)
    a = xy2.detach().contiguous().numpy()
    b = cen.detach().contiguous().numpy()
    index = np.full((c.shape[0], k), EMPTY_INDEX, np.int64)
    count = np.zeros(c.shape[0], np.int64)
    _cylinder_numba(np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1]),
                    np.ascontiguousarray(kt.detach().cpu().numpy()), np.ascontiguousarray(b[:, 0]),
                    np.ascontiguousarray(b[:, 1]), np.ascontiguousarray(r2.detach().numpy()), k,
                    a.dtype.type(1.0), index, count)
    return torch.from_numpy(index), torch.from_numpy(count)
