"""PointNet++ / PointRCNN point operations in plain torch + numba (no compiled extensions).

Contents
- `farthest_point_sample`: deterministic farthest point sampling per frame.
- `ball_query` -> `BallQuery`: the first `nsample` points within a radius of each centre.
- `group_points`, `group_neighbours`: gather (M, nsample, C) by ball-query indices; zero rows for
  empty balls; differentiable w.r.t. the features.
- `three_nn`, `three_interpolate`, `three_nn_interpolate`: feature propagation by inverse-distance
  weights of the three nearest source points of the same frame.
- `roi_point_pool` -> `RoIPoints`: PointRCNN stage-2 pooling of the points in enlarged RoIs, in each
  RoI's canonical frame; `to_canonical` / `from_canonical` are the transform and its inverse.

Batches. The points of B frames are concatenated along the first axis, with a per-frame count
vector (`counts`, `xyz_counts`, ..., (B,) non-negative integers summing to the row count; None
means one frame holding every row). Centres, targets and RoIs are batched the same way, each
with its own counts and the same B. Every op works within a frame only.

Indices. All returned point indices are int64 rows of the concatenated array (so `xyz[index]`
gathers directly); -1 means "no point" (an empty ball, a missing neighbour, an empty RoI). Frame
b's rows are offsets[b]:offsets[b + 1] with offsets = [0, cumsum(counts)]; subtract offsets[b]
for per-frame indices.

Units and arithmetic. Coordinates in metres (the ego ground frame of docs/architecture.md),
headings in radians. Distances are computed in float64 in both backends, in the same order of
operations (dx*dx + dy*dy + dz*dz with d = point - reference), so the two backends agree bit
for bit on one device (`three_nn` takes its square root with torch.sqrt on the output device).

Backends. `backend="auto"` runs the numba kernels for CPU tensors (via .numpy(), outputs come
back as tensors) and vectorised torch for tensors on other devices (CUDA), memory linear in the
points (chunked where a pairwise step is needed). `backend="torch"` forces the torch path on
any device (the tests run it on CPU against the numba path); `backend="numba"` needs CPU tensors.
numpy arrays are accepted wherever a tensor is and are taken as CPU tensors.

Departures from the OpenPCDet kernels, on purpose: the ball test is inclusive (d^2 <= r^2,
OpenPCDet: d^2 < r^2); farthest point sampling does not skip points near the origin
(pointnet2_batch skips |p|^2 <= 1e-3); RoI pooling subsamples crowded RoIs evenly instead of
taking the first num_samples points (see `roi_point_pool`).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.points_in_boxes import _AABB_PAD, _inside

__all__ = [
    "BallQuery",
    "RoIPoints",
    "farthest_point_sample",
    "ball_query",
    "group_points",
    "group_neighbours",
    "three_nn",
    "three_interpolate",
    "three_nn_interpolate",
    "roi_point_pool",
    "to_canonical",
    "from_canonical",
]

# Work sizes below which the serial numba kernel runs (thread start-up and a shared 2-core
# machine make threads a loss for small calls; see PARALLEL_MIN_POINTS in points_in_boxes.py).
PARALLEL_MIN_FPS_WORK = 20_000_000  # sum over frames of points x samples (one frame never splits)
PARALLEL_MIN_BALL_CANDIDATES = 2_000_000  # estimated candidate pairs: centres x 27 x mean points per cell
PARALLEL_MIN_NN_TARGETS = 100_000  # target points of three_nn
PARALLEL_MIN_ROI_TESTS = 8_000_000  # sum over frames of RoIs x points
_TORCH_CHUNK_ELEMS = 1 << 22  # pairwise elements per torch chunk (memory bound of the torch paths)
_FPS_BLOCK = 64  # spatially sorted points per block of the FPS kernel (bounding box + running maximum)
_BALL_CELL_MARGIN = 1.0 + 1e-6  # ball-query cells are radius * this, so a hit is never > 1 cell away
_NN_EPS = 1e-8  # metres, added to distances before inverting (as PointNet++)


class BallQuery(NamedTuple):
    """Result of `ball_query`.

    index: (M, nsample) int64 rows of the concatenated points: the first hits in index order,
        the row padded by repeating its first hit; all -1 for an empty ball.
    count: (M,) int64 distinct points in the row, min(hits, nsample); 0 for an empty ball.
    empty: (M,) bool, True where no point lies within the radius.
    """

    index: torch.Tensor
    count: torch.Tensor
    empty: torch.Tensor


class RoIPoints(NamedTuple):
    """Result of `roi_point_pool`.

    points: (R, S, 3 + C) canonical x, y, z (metres, RoI frame) then the C point features;
        zeros for an empty RoI.
    index: (R, S) int64 rows of the concatenated points; -1 for an empty RoI.
    count: (R,) int64 points inside the enlarged RoI (before sampling to S).
    empty: (R,) bool, True where the enlarged RoI holds no point.
    """

    points: torch.Tensor
    index: torch.Tensor
    count: torch.Tensor
    empty: torch.Tensor


# ============================================================================ input checks
def _tensor(x, func: str, name: str) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    a = np.asarray(x)
    if a.dtype == object or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{func}: `{name}` must be a numeric tensor or array, got dtype {a.dtype}")
    return torch.from_numpy(np.ascontiguousarray(a))


def _xyz(x, func: str, name: str, device: torch.device | None = None, cols: int = 3) -> torch.Tensor:
    """(N, >=cols) finite float tensor on `device` (a numpy array is taken as a CPU tensor)."""
    t = _tensor(x, func, name)
    if t.ndim == 1 and t.shape[0] == 0:
        t = t.reshape(0, cols)
    if t.ndim != 2 or t.shape[1] < cols:
        what = "x, y, z" if cols == 3 else "x, y, z, dx, dy, dz, heading"
        raise ValueError(f"{func}: `{name}` must have shape (N, {cols}) with columns {what} (metres"
                         f"{', radians' if cols == 7 else ''}); got shape {tuple(t.shape)}. "
                         f"Concatenate the frames along the first axis and pass their counts.")
    if not t.dtype.is_floating_point:
        t = t.to(torch.float64)
    if device is not None and t.device != device:
        raise ValueError(f"{func}: `{name}` is on {t.device} but the points are on {device}; move them to one device")
    if t.device.type == "cpu":  # numpy: one thread, no wake-up of torch's pool for a check
        bad = np.flatnonzero(~np.isfinite(t.detach().numpy()[:, :cols]).all(axis=1))
    else:
        bad = (~torch.isfinite(t[:, :cols]).all(dim=1)).nonzero()[:, 0].cpu().numpy()
    if bad.size:
        raise ValueError(f"{func}: `{name}` contain NaN or infinite values (first at row {int(bad[0])}, "
                         f"{bad.size} rows in all); drop or repair those rows first")
    return t


def _counts(counts, total: int, func: str, name: str, rows: str) -> np.ndarray:
    """(B,) int64 numpy per-frame counts summing to `total` (None: one frame of all rows)."""
    if counts is None:
        return np.array([total], dtype=np.int64)
    c = counts.detach().cpu().numpy() if isinstance(counts, torch.Tensor) else np.asarray(counts)
    if c.ndim == 0:
        c = c.reshape(1)
    if c.ndim != 1 or (c.size and not np.issubdtype(c.dtype, np.integer)):
        raise ValueError(f"{func}: `{name}` must be a 1-D sequence of per-frame integer counts, "
                         f"got shape {c.shape} dtype {c.dtype}")
    c = c.astype(np.int64)
    if (c < 0).any() or int(c.sum()) != total:
        raise ValueError(f"{func}: `{name}` must be non-negative and sum to the number of {rows} ({total}); "
                         f"got {c.tolist()[:8]}{'...' if c.size > 8 else ''} summing to {int(c.sum())}")
    return c


def _same_frames(a: np.ndarray, b: np.ndarray, func: str, na: str, nb: str) -> None:
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{func}: `{na}` has {a.shape[0]} frames but `{nb}` has {b.shape[0]}; give one count "
                         "per frame for both (or None for both when there is one frame)")


def _backend(backend: str, device: torch.device, func: str) -> str:
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"{func}: backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    if backend == "auto":
        return "numba" if device.type == "cpu" else "torch"
    if backend == "numba" and device.type != "cpu":
        raise ValueError(f"{func}: backend='numba' needs CPU tensors, got {device}; use backend='auto' or 'torch'")
    return backend


def _offsets(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def _np64(t: torch.Tensor) -> np.ndarray:
    """C-contiguous float64 (N, 3) numpy copy of the x, y, z columns of a CPU tensor."""
    return np.ascontiguousarray(t.detach().numpy()[:, :3], dtype=np.float64)


def _nchunks(n: int) -> int:
    return int(max(1, min(numba.get_num_threads() * 4, n)))


# ============================================================================ farthest point sampling
_SPREAD3 = np.zeros(1024, dtype=np.int64)  # bit i of v moved to bit 3i (Morton interleave of 10 bits)
for _bit in range(10):
    _SPREAD3 |= ((np.arange(1024, dtype=np.int64) >> _bit) & 1) << (3 * _bit)


def _morton_order(p: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Rows sorted by (frame, Morton code of x, y, z quantised to 10 bits over the batch's box).

    Consecutive rows of the result are close in space, so a block of them has a small box.
    """
    n = p.shape[0]
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    q = np.minimum(((p - lo) / span * 1024.0).astype(np.int64), 1023)
    code = _SPREAD3[q[:, 0]] | (_SPREAD3[q[:, 1]] << 1) | (_SPREAD3[q[:, 2]] << 2)
    frame = np.repeat(np.arange(counts.shape[0], dtype=np.int64), counts)
    return np.argsort((frame << 30) | code, kind="stable")


@njit(cache=True)
def _fps_frame(xs, ys, zs, rows, start, n, first, m, out, out_start, temp):
    """One frame at positions start..start+n-1 of the spatially sorted points xs, ys, zs
    (rows: their global rows; first: the position of the frame's first row). Writes m global
    rows to out[out_start:].

    The positions are cut into blocks of _FPS_BLOCK with a bounding box, a running maximum of
    `temp` and the lowest row holding it. A block whose box is at least its maximum away from
    the new sample cannot change (every distance in it is >= the bound >= every temp; float
    rounding is monotone, so the float bound is <= every float distance) and is skipped; the
    result is exactly the dense loop's, ties going to the lowest row.
    """
    if m == 0:
        return
    k0 = min(n, m)
    nb = (n + _FPS_BLOCK - 1) // _FPS_BLOCK
    box = np.empty((nb, 6))
    bmax = np.full(nb, np.inf)
    brow = np.empty(nb, dtype=np.int64)
    bpos = np.empty(nb, dtype=np.int64)
    for b in range(nb):
        s = start + b * _FPS_BLOCK
        e = min(start + n, s + _FPS_BLOCK)
        box[b, 0], box[b, 1], box[b, 2] = xs[s], ys[s], zs[s]
        box[b, 3], box[b, 4], box[b, 5] = xs[s], ys[s], zs[s]
        for i in range(s, e):
            temp[i] = np.inf
            box[b, 0] = min(box[b, 0], xs[i])
            box[b, 1] = min(box[b, 1], ys[i])
            box[b, 2] = min(box[b, 2], zs[i])
            box[b, 3] = max(box[b, 3], xs[i])
            box[b, 4] = max(box[b, 4], ys[i])
            box[b, 5] = max(box[b, 5], zs[i])
    last = first
    out[out_start] = rows[first]
    for k in range(1, k0):
        lx, ly, lz = xs[last], ys[last], zs[last]
        for b in range(nb):
            gx = max(box[b, 0] - lx, lx - box[b, 3], 0.0)
            gy = max(box[b, 1] - ly, ly - box[b, 4], 0.0)
            gz = max(box[b, 2] - lz, lz - box[b, 5], 0.0)
            if gx * gx + gy * gy + gz * gz >= bmax[b]:
                continue
            s = start + b * _FPS_BLOCK
            bm = -1.0
            br = np.int64(-1)
            bp = s
            for i in range(s, min(start + n, s + _FPS_BLOCK)):
                dx = xs[i] - lx
                dy = ys[i] - ly
                dz = zs[i] - lz
                t = min(temp[i], dx * dx + dy * dy + dz * dz)
                temp[i] = t
                if t > bm or (t == bm and rows[i] < br):
                    bm = t
                    br = rows[i]
                    bp = i
            bmax[b] = bm
            brow[b] = br
            bpos[b] = bp
        bb = 0
        for b in range(1, nb):
            if bmax[b] > bmax[bb] or (bmax[b] == bmax[bb] and brow[b] < brow[bb]):
                bb = b
        last = bpos[bb]
        out[out_start + k] = brow[bb]
    for k in range(k0, m):  # fewer points than samples: repeat the frame's samples cyclically
        out[out_start + k] = out[out_start + k % k0]


@njit(cache=True)
def _fps_frames(xs, ys, zs, rows, offsets, firsts, samples, out_offsets, out, temp):
    for f in range(offsets.shape[0] - 1):
        _fps_frame(xs, ys, zs, rows, offsets[f], offsets[f + 1] - offsets[f], firsts[f], samples[f], out,
                   out_offsets[f], temp)


@njit(cache=True, parallel=True)
def _fps_frames_parallel(xs, ys, zs, rows, offsets, firsts, samples, out_offsets, out, temp):
    for f in prange(offsets.shape[0] - 1):
        _fps_frame(xs, ys, zs, rows, offsets[f], offsets[f + 1] - offsets[f], firsts[f], samples[f], out,
                   out_offsets[f], temp)


def _fps_torch(p: torch.Tensor, counts: np.ndarray, samples: np.ndarray) -> torch.Tensor:
    """Vectorised over frames (padded to the largest), one step per sample; p (N, 3) float64."""
    dev = p.device
    total = int(samples.sum())
    live = np.flatnonzero(samples > 0)
    if live.size == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    offs = _offsets(counts)
    n = torch.as_tensor(counts[live], device=dev)
    start = torch.as_tensor(offs[live], device=dev)
    k0 = np.minimum(counts[live], samples[live])
    nmax = int(counts[live].max())
    ar = torch.arange(nmax, device=dev)
    valid = ar[None] < n[:, None]
    rows = torch.where(valid, start[:, None] + ar[None], torch.zeros_like(ar)[None])
    px, py, pz = p[rows, 0], p[rows, 1], p[rows, 2]  # (F, nmax) each
    temp = torch.where(valid, torch.full_like(px, math.inf), torch.full_like(px, -math.inf))
    steps = int(k0.max())
    sel = torch.zeros((live.size, steps), dtype=torch.int64, device=dev)
    frames = torch.arange(live.size, device=dev)
    last = torch.zeros(live.size, dtype=torch.int64, device=dev)
    for k in range(1, steps):
        dx = px - px[frames, last][:, None]
        dy = py - py[frames, last][:, None]
        dz = pz - pz[frames, last][:, None]
        temp = torch.minimum(temp, dx * dx + dy * dy + dz * dz)
        last = temp.argmax(dim=1)  # first index of the maximum
        sel[:, k] = last
    per = torch.as_tensor(samples[live], device=dev)
    fid = torch.repeat_interleave(frames, per)
    first = torch.cumsum(per, 0) - per
    k = torch.arange(total, device=dev) - first[fid]
    return start[fid] + sel[fid, k % torch.as_tensor(k0, device=dev)[fid]]


def farthest_point_sample(xyz, num_samples, counts=None, backend: str = "auto") -> torch.Tensor:
    """Farthest point sampling per frame (PointNet++ / OpenPCDet `furthest_point_sampling` rule).

    Each frame starts at its first point; every next sample is the point with the largest
    running minimum squared distance to the samples so far; on ties the lowest index wins.
    A chosen point has distance 0, so it comes again only when every remaining distance is 0
    (duplicates of chosen points), as in the reference kernel. Distances are float64 (the
    CUDA reference uses float32, so near-ties may resolve differently from OpenPCDet).

    CPU: a numba kernel over the frame sorted along a Morton curve in blocks of 64 points with
    bounding boxes; a block that the new sample cannot bring closer is skipped, with exactly the
    dense loop's result (16384 -> 4096 points of a 1.8 m scan: 13-21 ms on the 2-core test
    machine under a load average of ~5, tools/bench_points.py; the dense loop took ~70 ms). Other
    devices: torch, vectorised over the frames (padded to the largest), one step per sample.

    Args:
        xyz: (N, >=3) points of B frames concatenated, x, y, z first (metres).
        num_samples: samples per frame, an int (all frames) or (B,) ints >= 0.
        counts: (B,) points per frame summing to N; None for one frame.
        backend: "auto" (numba on CPU, torch elsewhere), "numba" or "torch".

    Returns:
        (sum_b num_samples[b],) int64 rows of `xyz` (global indices), frame 0's samples first,
        on the input's device. A frame with n < num_samples points gives its n FPS samples and
        then repeats them cyclically (sample k = sample k mod n), so every frame yields exactly
        num_samples indices; a frame with no points and num_samples > 0 is an error.
    """
    func = "farthest_point_sample"
    p = _xyz(xyz, func, "xyz")
    c = _counts(counts, p.shape[0], func, "counts", "points")
    m = num_samples.detach().cpu().numpy() if isinstance(num_samples, torch.Tensor) else np.asarray(num_samples)
    if m.ndim == 0 and np.issubdtype(m.dtype, np.integer):
        m = np.full(c.shape[0], int(m), dtype=np.int64)
    if m.ndim != 1 or m.shape[0] != c.shape[0] or (m.size and not np.issubdtype(m.dtype, np.integer)):
        raise ValueError(f"{func}: num_samples must be an int or one int per frame ({c.shape[0]} frames), "
                         f"got {num_samples!r}")
    m = m.astype(np.int64)
    if (m < 0).any():
        raise ValueError(f"{func}: num_samples must be >= 0, got {m.tolist()}")
    bad = np.flatnonzero((c == 0) & (m > 0))
    if bad.size:
        raise ValueError(f"{func}: frame {int(bad[0])} has no points but {int(m[bad[0]])} samples are requested; "
                         "drop empty frames or request 0 samples for them")
    if _backend(backend, p.device, func) == "torch":
        return _fps_torch(p[:, :3].to(torch.float64), c, m)
    pts = _np64(p)
    order = _morton_order(pts, c) if pts.shape[0] else np.zeros(0, dtype=np.int64)
    where = np.empty_like(order)
    where[order] = np.arange(order.shape[0])
    offs = _offsets(c)
    firsts = where[np.minimum(offs[:-1], max(pts.shape[0] - 1, 0))] if pts.shape[0] else np.zeros(c.shape[0], np.int64)
    xs, ys, zs = (np.ascontiguousarray(pts[order, i]) for i in range(3))
    out = np.empty(int(m.sum()), dtype=np.int64)
    args = (xs, ys, zs, order, offs, firsts.astype(np.int64), m, _offsets(m), out, np.empty(pts.shape[0]))
    if c.shape[0] > 1 and int((c * m).sum()) >= PARALLEL_MIN_FPS_WORK and numba.get_num_threads() > 1:
        _fps_frames_parallel(*args)
    else:
        _fps_frames(*args)
    return torch.from_numpy(out).to(p.device)


# ============================================================================ ball query
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
            row[t] = row[0] if k > 0 else -1


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
    index = torch.full((m, nsample), -1, dtype=torch.int64, device=dev)
    found = torch.zeros(m, dtype=torch.int64, device=dev)
    per = count.sum(dim=1)
    csum = torch.cumsum(per, 0)
    c0 = 0
    while c0 < m:
        base = int(csum[c0 - 1]) if c0 else 0
        c1 = int(torch.searchsorted(csum, torch.tensor(base + _TORCH_CHUNK_ELEMS, device=dev), right=True))
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
    an empty ball gives a row of -1 and `empty` True (`group_points` turns it into zeros).

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
    p = _xyz(xyz, func, "xyz")
    q = _xyz(centres, func, "centres", p.device)
    r = float(radius)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"{func}: radius must be a positive number of metres, got {radius!r}")
    if int(nsample) < 1:
        raise ValueError(f"{func}: nsample must be >= 1, got {nsample!r}")
    ns = int(nsample)
    pc = _counts(xyz_counts, p.shape[0], func, "xyz_counts", "points")
    qc = _counts(centre_counts, q.shape[0], func, "centre_counts", "centres")
    _same_frames(pc, qc, func, "xyz_counts", "centre_counts")
    be = _backend(backend, p.device, func)
    m = q.shape[0]
    if m == 0 or p.shape[0] == 0:
        index = torch.full((m, ns), -1, dtype=torch.int64, device=p.device)
        zero = torch.zeros(m, dtype=torch.int64, device=p.device)
        return BallQuery(index, zero, zero == 0)
    r2 = r * r
    if be == "torch":
        p64, q64 = p[:, :3].detach().to(torch.float64), q[:, :3].detach().to(torch.float64)
        perm, start, count = _cell_lists(p64, pc, q64, qc, r * _BALL_CELL_MARGIN, func)
        index, found = _ball_torch(p64[perm], perm, q64, start, count, r2, ns)
    else:
        p64, q64 = _np64(p), _np64(q)
        cell = r * _BALL_CELL_MARGIN
        perm, ukey, ustart, ucount, lo, ext = _point_cells_np(p64, pc, cell, func)
        qb = np.repeat(np.arange(qc.shape[0], dtype=np.int64), qc)
        args = (np.ascontiguousarray(p64[perm]), perm, ukey, ustart, ucount, lo, ext, cell, q64, qb, r2)
        idx = np.empty((m, ns), dtype=np.int64)
        fnd = np.empty(m, dtype=np.int64)
        # work estimate: the mean cell occupancy times 27 cells per centre
        if 27 * m * p.shape[0] / max(ukey.shape[0], 1) >= PARALLEL_MIN_BALL_CANDIDATES and numba.get_num_threads() > 1:
            _ball_parallel(*args, _nchunks(m), idx, fnd)
        else:
            _ball_range(*args, 0, m, idx, fnd)
        index, found = torch.from_numpy(idx), torch.from_numpy(fnd)
    return BallQuery(index, found, found == 0)


# ============================================================================ grouping
def group_points(features: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Gather rows of `features` (N, C) by `index` (M, K) -> (M, K, C); index -1 gives zeros.

    Differentiable w.r.t. `features` (plain torch indexing; gradients of repeated rows add up).
    Use with `BallQuery.index` (empty balls are rows of -1) or `three_nn` indices.
    """
    func = "group_points"
    if not isinstance(features, torch.Tensor) or features.ndim != 2:
        raise ValueError(f"{func}: features must be an (N, C) tensor, got "
                         f"{tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__}")
    if not isinstance(index, torch.Tensor) or index.dtype.is_floating_point:
        raise ValueError(f"{func}: index must be an integer tensor (e.g. BallQuery.index), got {type(index).__name__}")
    index = index.to(features.device).long()
    valid = index >= 0
    if index.numel() and int(index.max()) >= features.shape[0]:
        raise ValueError(f"{func}: index holds row {int(index.max())} but features has {features.shape[0]} rows; "
                         "pass the features of the same concatenated points the indices refer to")
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
        (M, K, 3 * use_xyz + C); every entry of an empty ball (index -1) is zero.
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


# ============================================================================ three nearest neighbours
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
                out_idx[i, j] = -1


@njit(cache=True, parallel=True)
def _nn_parallel(t, s, sid, cstart, lo, h, dims, nchunks, out_d2, out_idx):
    n = t.shape[0]
    step = (n + nchunks - 1) // nchunks
    for c in prange(nchunks):
        _nn_range(t, s, sid, cstart, lo, h, dims, c * step, min(n, (c + 1) * step), out_d2, out_idx)


def _three_nn_numba(t: np.ndarray, s: np.ndarray, tc: np.ndarray, sc: np.ndarray):
    n = t.shape[0]
    d2 = np.full((n, 3), np.inf)
    idx = np.full((n, 3), -1, dtype=np.int64)
    to, so = _offsets(tc), _offsets(sc)
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
            _nn_parallel(*args, _nchunks(int(tc[b])), od, oi)
        else:
            _nn_range(*args, 0, int(tc[b]), od, oi)
    return d2, idx


def _three_nn_torch(t: torch.Tensor, s: torch.Tensor, tc: np.ndarray, sc: np.ndarray):
    """Per frame, chunks of targets x all sources (bounded memory), 3 rounds of first-argmin."""
    dev = t.device
    n = t.shape[0]
    d2 = torch.full((n, 3), math.inf, dtype=torch.float64, device=dev)
    idx = torch.full((n, 3), -1, dtype=torch.int64, device=dev)
    to, so = _offsets(tc), _offsets(sc)
    for b in range(tc.shape[0]):
        m = int(sc[b])
        if tc[b] == 0 or m == 0:
            continue
        src = s[so[b]:so[b + 1]]
        step = max(1, _TORCH_CHUNK_ELEMS // m)
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
        index -1 (a frame without sources: all three missing).

    The CPU kernel bins each frame's sources into a grid of about m / 2 cells and searches
    rings of cells outwards, so memory is linear in the points.
    """
    func = "three_nn"
    t = _xyz(targets, func, "targets")
    s = _xyz(sources, func, "sources", t.device)
    tc = _counts(target_counts, t.shape[0], func, "target_counts", "targets")
    sc = _counts(source_counts, s.shape[0], func, "source_counts", "sources")
    _same_frames(tc, sc, func, "target_counts", "source_counts")
    if _backend(backend, t.device, func) == "torch":
        d2, idx = _three_nn_torch(t[:, :3].detach().to(torch.float64), s[:, :3].detach().to(torch.float64), tc, sc)
    else:
        d2n, idxn = _three_nn_numba(_np64(t), _np64(s), tc, sc)
        d2, idx = torch.from_numpy(d2n), torch.from_numpy(idxn)
    return torch.sqrt(d2), idx


def three_interpolate(features: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Weighted sum of three source rows: out[i] = sum_j weight[i, j] * features[index[i, j]].

    features (m, C), index (n, 3) int64 (-1 = missing, contributes 0), weight (n, 3) -> (n, C).
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


# ============================================================================ canonical transform
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


# ============================================================================ RoI point pooling
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
                index[r, j] = -1
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
    index = torch.full((nr, ns), -1, dtype=torch.int64, device=dev)
    count = torch.zeros(nr, dtype=torch.int64, device=dev)
    po, ro = _offsets(pc), _offsets(rc)
    slot = torch.arange(ns, device=dev)
    for b in range(pc.shape[0]):
        n = int(pc[b])
        if rc[b] == 0 or n == 0:
            continue
        x, y, z = (p[po[b]:po[b + 1], a][None] for a in range(3))
        step = max(1, _TORCH_CHUNK_ELEMS // n)
        for a in range(int(ro[b]), int(ro[b + 1]), step):
            t = table[a:min(int(ro[b + 1]), a + step), :, None]
            inside = (x >= t[:, 8]) & (x <= t[:, 9]) & (y >= t[:, 10]) & (y <= t[:, 11])
            inside &= (z >= t[:, 6]) & (z <= t[:, 7])
            rx, ry = x - t[:, 0], y - t[:, 1]
            inside &= ((rx * t[:, 2] + ry * t[:, 3]).abs() <= t[:, 4]) & ((-rx * t[:, 3] + ry * t[:, 2]).abs() <= t[:, 5])
            cs = torch.cumsum(inside, dim=1)
            k = cs[:, -1]
            rank = torch.where(k[:, None] > ns, torch.div(slot[None] * k[:, None], ns, rounding_mode="floor"),
                               slot[None] % k.clamp_min(1)[:, None])
            local = torch.searchsorted(cs, rank + 1)  # position of the (rank+1)-th inside point
            e = a + t.shape[0]
            index[a:e] = torch.where(k[:, None] > 0, local + int(po[b]), torch.full_like(local, -1))
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
        zero rows / -1 indices for empty RoIs. Differentiable w.r.t. xyz and features (the
        selection itself is not).
    """
    func = "roi_point_pool"
    p = _xyz(xyz, func, "xyz")
    b = _xyz(rois, func, "rois", p.device, cols=7)
    ns = int(num_samples)
    if ns < 1:
        raise ValueError(f"{func}: num_samples must be >= 1, got {num_samples!r}")
    e = float(extra)
    if not math.isfinite(e):
        raise ValueError(f"{func}: extra must be a finite number of metres, got {extra!r}")
    if features is not None:
        features = _tensor(features, func, "features")
        if features.ndim != 2 or features.shape[0] != p.shape[0] or features.device != p.device:
            raise ValueError(f"{func}: features must be (N, C) with one row per point ({p.shape[0]}) on {p.device}, "
                             f"got {tuple(features.shape)} on {features.device}")
    pc = _counts(point_counts, p.shape[0], func, "point_counts", "points")
    rc = _counts(roi_counts, b.shape[0], func, "roi_counts", "rois")
    _same_frames(pc, rc, func, "point_counts", "roi_counts")
    be = _backend(backend, p.device, func)
    table = _roi_table(b, e)
    nr = b.shape[0]
    if be == "torch":
        index, count = _roi_torch(p[:, :3].detach().to(torch.float64), table, pc, rc, ns)
    else:
        po = _offsets(pc)
        fid = np.repeat(np.arange(pc.shape[0]), rc)
        fstart, fcount = po[fid].astype(np.int64), pc[fid].astype(np.int64)
        idx = np.full((nr, ns), -1, dtype=np.int64)
        cnt = np.zeros(nr, dtype=np.int64)
        args = (_np64(p), np.ascontiguousarray(table.numpy()), fstart, fcount)
        bufsize = int(pc.max()) if pc.size else 0
        if int((pc * rc).sum()) >= PARALLEL_MIN_ROI_TESTS and numba.get_num_threads() > 1:
            _roi_parallel(*args, _nchunks(nr), idx, cnt, bufsize)
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


# ============================================================================ cylinder query (CT3D)
_CYL_MAX_CELLS = 1 << 22  # grid cells of the numba path at most (the cell grows past this)


@njit(cache=True)
def _cylinder_numba(px, py, keys, cx, cy, r2, k, cell, out_idx, out_cnt):  # pragma: no cover - numba
    n, r = px.shape[0], cx.shape[0]
    rmax = np.float32(0.0)
    for j in range(r):
        rmax = max(rmax, np.float32(math.sqrt(r2[j])))
    x0, x1 = cx.min() - rmax - 1.0, cx.max() + rmax + 1.0
    y0, y1 = cy.min() - rmax - 1.0, cy.max() + rmax + 1.0
    while (int((x1 - x0) / cell) + 1) * (int((y1 - y0) / cell) + 1) > _CYL_MAX_CELLS:
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
        ix0, ix1 = max(0, int((cx[j] - rr - x0) / cell)), min(nx - 1, int((cx[j] + rr - x0) / cell))
        iy0, iy1 = max(0, int((cy[j] - rr - y0) / cell)), min(ny - 1, int((cy[j] + rr - y0) / cell))
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
    return index * (count > 0)[:, None], count


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
        (index (R, K) int64 rows of `xy`, 0 for an empty cylinder; count (R,) int64 points inside).
    """
    func = "cylinder_query"
    p, c = _tensor(xy, func, "xy"), _tensor(centres, func, "centres")
    if p.ndim != 2 or p.shape[1] < 2 or c.ndim != 2 or c.shape[1] < 2:
        raise ValueError(f"{func}: xy must be (N, >=2) and centres (R, >=2); got {tuple(p.shape)} and {tuple(c.shape)}")
    kt, rad = _tensor(keys, func, "keys"), _tensor(radius, func, "radius")
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
        return (torch.zeros(c.shape[0], k, dtype=torch.int64, device=p.device),
                torch.zeros(c.shape[0], dtype=torch.int64, device=p.device))
    if _backend(backend, p.device, func) == "torch":
        return _cylinder_torch(xy2, kt.to(p.device), cen, r2, k)
    a = xy2.detach().contiguous().numpy()
    b = cen.detach().contiguous().numpy()
    index = np.zeros((c.shape[0], k), np.int64)
    count = np.zeros(c.shape[0], np.int64)
    _cylinder_numba(np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1]),
                    np.ascontiguousarray(kt.detach().cpu().numpy()), np.ascontiguousarray(b[:, 0]),
                    np.ascontiguousarray(b[:, 1]), np.ascontiguousarray(r2.detach().numpy()), k,
                    a.dtype.type(1.0), index, count)
    return torch.from_numpy(index), torch.from_numpy(count)
