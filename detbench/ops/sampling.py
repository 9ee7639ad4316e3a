"""Farthest point sampling (PointNet++ / PointRCNN), numba on CPU and torch elsewhere.

Contents
- `farthest_point_sample`: deterministic farthest point sampling per frame.

Batches, indices, arithmetic and backends follow detbench.ops.point_batch. Departure from the
OpenPCDet kernel, on purpose: points near the origin are not skipped (pointnet2_batch skips
|p|^2 <= 1e-3).
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.point_batch import check_counts, check_xyz, frame_offsets, pick_backend, xyz_float64

__all__ = ["farthest_point_sample"]

# Work below which the serial numba kernel runs (thread start-up and a shared 2-core machine
# make threads a loss for small calls; see PARALLEL_MIN_POINTS in points_in_boxes.py).
PARALLEL_MIN_FPS_WORK = 20_000_000  # sum over frames of points x samples (one frame never splits)
_FPS_BLOCK = 64  # spatially sorted points per block of the FPS kernel (bounding box + running maximum)


_SPREAD3 = np.zeros(1024, dtype=np.int64)  # bit i of v moved to bit 3i (Morton interleave of 10 bits)
for _bit in range(10):
    _SPREAD3 |= ((np.arange(1024, dtype=np.int64) >> _bit) & 1) << (3 * _bit)


def _morton_order(p: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Rows sorted by (frame, Morton code of x, y, z quantised to 10 bits over the batch's box).

    Consecutive rows of the result are close in space, so a block of them has a small box.
    """
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


@contextmanager
def _one_cpu_thread(device: torch.device) -> Iterator[None]:
    """torch on one thread for the block when `device` is the CPU (DETBENCH_OPS=torch): a step's operations
    are too small to share, and waking a second thread for each of them costs more than the step (about 8x
    on the 2-core test machine under load)."""
    if device.type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _fps_torch(p: torch.Tensor, counts: np.ndarray, samples: np.ndarray) -> torch.Tensor:
    """Batched over frames (padded to the largest), one step per sample; p (N, 3) float64.

    A step is seven tensor operations on all frames at once and no host sync: gather the newest samples,
    subtract, square, add the three squared differences in the numba kernel's order, take the running
    minimum and its argmax (the first index of the maximum, the kernel's tie rule)."""
    dev = p.device
    total = int(samples.sum())
    live = np.flatnonzero(samples > 0)
    if live.size == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    offs = frame_offsets(counts)
    f = live.size
    n = torch.as_tensor(counts[live], device=dev)
    start = torch.as_tensor(offs[live], device=dev)
    k0 = np.minimum(counts[live], samples[live])
    nmax = int(counts[live].max())
    ar = torch.arange(nmax, device=dev)
    valid = ar[None] < n[:, None]
    rows = torch.where(valid, start[:, None] + ar[None], torch.zeros_like(ar)[None])
    pts = p[rows].permute(2, 0, 1).contiguous()  # (3, F, nmax): x, y, z planes
    temp = torch.where(valid, torch.full((f, nmax), math.inf, dtype=p.dtype, device=dev),
                       torch.full((f, nmax), -math.inf, dtype=p.dtype, device=dev))  # padding never wins
    diff = torch.empty_like(pts)
    dist = torch.empty_like(temp)
    last = torch.zeros(f, dtype=torch.int64, device=dev)
    picks = [last]
    with _one_cpu_thread(dev):
        for _ in range(1, int(k0.max())):
            centre = pts.gather(2, last.view(1, f, 1).expand(3, f, 1))
            torch.sub(pts, centre, out=diff)
            diff.mul_(diff)
            torch.add(diff[0], diff[1], out=dist)
            dist.add_(diff[2])
            torch.minimum(temp, dist, out=temp)
            last = temp.argmax(dim=1)
            picks.append(last)
    sel = torch.stack(picks, dim=1)  # (F, steps)
    frames = torch.arange(f, device=dev)
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
    devices (and the CPU under DETBENCH_OPS=torch): torch, batched over the frames (padded to the largest),
    one step of seven tensor operations per sample and no host sync.

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
    p = check_xyz(xyz, func, "xyz")
    c = check_counts(counts, p.shape[0], func, "counts", "points")
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
    if pick_backend(backend, p.device, func) == "torch":
        return _fps_torch(p[:, :3].to(torch.float64), c, m)
    pts = xyz_float64(p)
    order = _morton_order(pts, c) if pts.shape[0] else np.zeros(0, dtype=np.int64)
    where = np.empty_like(order)
    where[order] = np.arange(order.shape[0])
    offs = frame_offsets(c)
    firsts = where[np.minimum(offs[:-1], max(pts.shape[0] - 1, 0))] if pts.shape[0] else np.zeros(c.shape[0], np.int64)
    xs, ys, zs = (np.ascontiguousarray(pts[order, i]) for i in range(3))
    out = np.empty(int(m.sum()), dtype=np.int64)
    args = (xs, ys, zs, order, offs, firsts.astype(np.int64), m, frame_offsets(m), out, np.empty(pts.shape[0]))
    if c.shape[0] > 1 and int((c * m).sum()) >= PARALLEL_MIN_FPS_WORK and numba.get_num_threads() > 1:
        _fps_frames_parallel(*args)
    else:
        _fps_frames(*args)
    return torch.from_numpy(out).to(p.device)
