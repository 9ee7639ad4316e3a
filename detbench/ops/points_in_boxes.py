"""Which points lie inside which boxes (rotated in bird's-eye view, upright in z).

A point (x, y, z) is inside box (cx, cy, cz, dx, dy, dz, heading) with bottom lift L when

    |u| <= dx / 2  and  |v| <= dy / 2          (u, v: the point in the box's frame,
                                                u along the heading, v to its left)
    cz - dz/2 + L <= z <= cz + dz/2

All six faces are inclusive: a point exactly on a face counts (up to one rounding step of
float64 arithmetic; points are converted to float64 and taken relative to the box centre
before rotating, so coordinates far from the origin lose no precision). The lift raises
only the bottom face: with L = 0.05 m, a box standing on the road (cz = dz/2) ignores the
road points up to 5 cm, so a point at z = 0.04 m does not count and one at z = 0.06 m does.
A negative lift lowers the bottom; a lift above dz leaves the box empty.

This is the LiDAR-detected rule of the study: a vehicle counts as hit by the LiDAR when
`points_in_boxes(points, boxes, bottom_lift=0.05)[0] >= 1`.

numpy inputs run a numba kernel, parallel over points with a cheap axis-aligned bounding
box rejection before the rotated test; torch inputs run vectorised torch on the inputs'
device (chunked over points to bound memory). CPU tensors take the numba kernel as well
(it is far faster there; DETBENCH_OPS=torch makes them take the torch version,
detbench.ops.backend) and come back as tensors; on other devices the torch version
computes in float32 (float64 if an input is float64), so a point within rounding distance
of a face may be decided differently than by the float64 numba kernel.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from detbench.ops.backend import use_torch
from detbench.ops.box_coder import check_boxes, check_points, float_dtype_torch, is_torch

__all__ = ["points_in_boxes", "points_in_boxes_mask"]

# columns of the per-box parameter table handed to the kernels
_CX, _CY, _COS, _SIN, _HX, _HY, _ZLO, _ZHI, _XMIN, _XMAX, _YMIN, _YMAX = range(12)
_AABB_PAD = 1e-6  # metres; the AABB only rejects points clearly outside, the exact test decides
_TORCH_CHUNK_ELEMS = 1 << 22  # points x boxes handled per torch chunk
# Below this many points the serial kernel runs: with the grid rejection a point costs
# ~10 ns, so 60k points take ~0.6 ms on one core and threads would gain little while
# costing a lot whenever the cores are shared with other work.
PARALLEL_MIN_POINTS = 250_000


def _box_table(boxes: np.ndarray, bottom_lift: float) -> np.ndarray:
    """(M, 12) float64: centre, cos/sin heading, half sizes, z limits, padded BEV AABB."""
    b = np.ascontiguousarray(boxes[:, :7], dtype=np.float64)
    m = b.shape[0]
    t = np.empty((m, 12), dtype=np.float64)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    hx, hy = 0.5 * b[:, 3], 0.5 * b[:, 4]
    t[:, _CX], t[:, _CY] = b[:, 0], b[:, 1]
    t[:, _COS], t[:, _SIN] = c, s
    t[:, _HX], t[:, _HY] = hx, hy
    t[:, _ZLO] = b[:, 2] - 0.5 * b[:, 5] + bottom_lift
    t[:, _ZHI] = b[:, 2] + 0.5 * b[:, 5]
    ex = np.abs(c) * hx + np.abs(s) * hy + _AABB_PAD
    ey = np.abs(s) * hx + np.abs(c) * hy + _AABB_PAD
    t[:, _XMIN], t[:, _XMAX] = b[:, 0] - ex, b[:, 0] + ex
    t[:, _YMIN], t[:, _YMAX] = b[:, 1] - ey, b[:, 1] + ey
    return t


@njit(cache=True, inline="always")
def _inside(x, y, z, t, j):
    if x < t[j, _XMIN] or x > t[j, _XMAX] or y < t[j, _YMIN] or y > t[j, _YMAX]:
        return False
    if z < t[j, _ZLO] or z > t[j, _ZHI]:
        return False
    rx = x - t[j, _CX]
    ry = y - t[j, _CY]
    u = rx * t[j, _COS] + ry * t[j, _SIN]
    v = -rx * t[j, _SIN] + ry * t[j, _COS]
    return abs(u) <= t[j, _HX] and abs(v) <= t[j, _HY]


_GRID_MAX_CELLS = 16384  # upper bound on BEV grid cells per call


def _grid_params(table: np.ndarray):
    """Uniform BEV grid over the union of the boxes' AABBs: (x0, y0, inv_cell, nx, ny).

    The cell side is the mean AABB side (so a box touches about four cells) but no
    smaller than what keeps the grid within about 2 * `_GRID_MAX_CELLS` cells.
    """
    x0, x1 = table[:, _XMIN].min(), table[:, _XMAX].max()
    y0, y1 = table[:, _YMIN].min(), table[:, _YMAX].max()
    side = float(np.mean(np.maximum(table[:, _XMAX] - table[:, _XMIN], table[:, _YMAX] - table[:, _YMIN])))
    span_x, span_y = x1 - x0, y1 - y0
    cell = max(side, np.sqrt(span_x * span_y / _GRID_MAX_CELLS), (span_x + span_y) / _GRID_MAX_CELLS, 1e-6)
    # nx * ny <= span_x * span_y / cell^2 + (span_x + span_y) / cell + 1 <= 2 * _GRID_MAX_CELLS + 1
    nx = int(span_x // cell) + 1
    ny = int(span_y // cell) + 1
    return float(x0), float(y0), 1.0 / cell, nx, ny


@njit(cache=True)
def _build_grid(table, x0, y0, inv_cell, nx, ny):
    """CSR lists (offsets (nx*ny+1,), boxes) of the boxes whose AABB touches each cell,
    each list in ascending box index."""
    m = table.shape[0]
    lo_x = np.empty(m, np.int64)
    hi_x = np.empty(m, np.int64)
    lo_y = np.empty(m, np.int64)
    hi_y = np.empty(m, np.int64)
    ncell = nx * ny
    counts = np.zeros(ncell + 1, np.int64)
    for j in range(m):
        lo_x[j] = min(max(np.int64((table[j, _XMIN] - x0) * inv_cell), 0), nx - 1)
        hi_x[j] = min(max(np.int64((table[j, _XMAX] - x0) * inv_cell), 0), nx - 1)
        lo_y[j] = min(max(np.int64((table[j, _YMIN] - y0) * inv_cell), 0), ny - 1)
        hi_y[j] = min(max(np.int64((table[j, _YMAX] - y0) * inv_cell), 0), ny - 1)
        for ix in range(lo_x[j], hi_x[j] + 1):
            for iy in range(lo_y[j], hi_y[j] + 1):
                counts[ix * ny + iy + 1] += 1
    for k in range(ncell):
        counts[k + 1] += counts[k]
    fill = counts[:-1].copy()
    items = np.empty(counts[ncell], np.int64)
    for j in range(m):
        for ix in range(lo_x[j], hi_x[j] + 1):
            for iy in range(lo_y[j], hi_y[j] + 1):
                c = ix * ny + iy
                items[fill[c]] = j
                fill[c] += 1
    return counts, items


@njit(cache=True)
def _pib_range(points, table, offsets, items, bounds, ny, start, stop, counts, box_index):
    """Points start..stop-1: add to `counts` (M,), write `box_index`.

    Each point looks up its grid cell and tests only the boxes listed there; a point lies
    in exactly one cell, so no box is counted twice for it.
    """
    x0, x1, y0, y1, zlo, zhi, inv_cell = bounds[0], bounds[1], bounds[2], bounds[3], bounds[4], bounds[5], bounds[6]
    nx = (offsets.shape[0] - 1) // ny
    for i in range(start, stop):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        # NaN fails every comparison and is skipped here
        if not (x >= x0 and x <= x1 and y >= y0 and y <= y1 and z >= zlo and z <= zhi):
            continue
        ix = min(np.int64((x - x0) * inv_cell), nx - 1)
        iy = min(np.int64((y - y0) * inv_cell), ny - 1)
        cell = ix * ny + iy
        first = -1
        for k in range(offsets[cell], offsets[cell + 1]):
            j = items[k]
            if _inside(x, y, z, table, j):
                counts[j] += 1
                if first < 0:
                    first = j
        box_index[i] = first


@njit(cache=True)
def _grid_bounds(table, x0, y0, inv_cell, nx, ny):
    zlo = table[0, _ZLO]
    zhi = table[0, _ZHI]
    for j in range(table.shape[0]):
        zlo = min(zlo, table[j, _ZLO])
        zhi = max(zhi, table[j, _ZHI])
    return np.array([x0, x0 + nx / inv_cell, y0, y0 + ny / inv_cell, zlo, zhi, inv_cell])


@njit(cache=True, parallel=True)
def _pib_kernel_parallel(points, table, x0, y0, inv_cell, nx, ny, nchunks):
    """counts (M,), first box index per point (N,) (-1 for none); chunks of points in parallel."""
    n = points.shape[0]
    m = table.shape[0]
    offsets, items = _build_grid(table, x0, y0, inv_cell, nx, ny)
    bounds = _grid_bounds(table, x0, y0, inv_cell, nx, ny)
    box_index = np.full(n, -1, dtype=np.int64)
    local = np.zeros((nchunks, m), dtype=np.int64)
    chunk = (n + nchunks - 1) // nchunks
    for c in prange(nchunks):
        _pib_range(points, table, offsets, items, bounds, ny, c * chunk, min(n, (c + 1) * chunk), local[c], box_index)
    counts = np.zeros(m, dtype=np.int64)
    for c in range(nchunks):
        for j in range(m):
            counts[j] += local[c, j]
    return counts, box_index


@njit(cache=True)
def _pib_kernel_serial(points, table, x0, y0, inv_cell, nx, ny):
    """Serial twin of `_pib_kernel_parallel` for small inputs (no thread start-up)."""
    n = points.shape[0]
    offsets, items = _build_grid(table, x0, y0, inv_cell, nx, ny)
    bounds = _grid_bounds(table, x0, y0, inv_cell, nx, ny)
    box_index = np.full(n, -1, dtype=np.int64)
    counts = np.zeros(table.shape[0], dtype=np.int64)
    _pib_range(points, table, offsets, items, bounds, ny, 0, n, counts, box_index)
    return counts, box_index


@njit(cache=True, parallel=True)
def _pib_mask_kernel(points, table):
    n = points.shape[0]
    m = table.shape[0]
    mask = np.zeros((n, m), dtype=np.bool_)
    for i in prange(n):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        for j in range(m):
            if _inside(x, y, z, table, j):
                mask[i, j] = True
    return mask


def _numpy_points(points: np.ndarray) -> np.ndarray:
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    return np.ascontiguousarray(points)


def _check_lift(bottom_lift, func: str) -> float:
    try:
        lift = float(bottom_lift)
    except (TypeError, ValueError):
        raise ValueError(f"{func}: bottom_lift must be a number of metres, got {bottom_lift!r}") from None
    if not np.isfinite(lift):
        raise ValueError(f"{func}: bottom_lift must be finite (metres), got {bottom_lift!r}")
    return lift


def _to_common(points, boxes):
    """If either input is a tensor, make both tensors on the tensor's device."""
    if is_torch(points) and not is_torch(boxes):
        boxes = torch.as_tensor(np.asarray(boxes), device=points.device)
    elif is_torch(boxes) and not is_torch(points):
        points = torch.as_tensor(np.asarray(points), device=boxes.device)
    elif is_torch(points) and points.device != boxes.device:
        raise ValueError(f"points are on {points.device} but boxes on {boxes.device}; move them to one device")
    return points, boxes


def _torch_mask_chunk(p: torch.Tensor, b: torch.Tensor, lift: float) -> torch.Tensor:
    """(n, M) bool for points p (n, 3) and boxes b (M, 7), same dtype/device."""
    rx = p[:, None, 0] - b[None, :, 0]
    ry = p[:, None, 1] - b[None, :, 1]
    c, s = torch.cos(b[:, 6])[None], torch.sin(b[:, 6])[None]
    u = rx * c + ry * s
    v = ry * c - rx * s
    z = p[:, None, 2]
    inside = (u.abs() <= 0.5 * b[None, :, 3]) & (v.abs() <= 0.5 * b[None, :, 4])
    inside &= z >= (b[None, :, 2] - 0.5 * b[None, :, 5] + lift)
    inside &= z <= (b[None, :, 2] + 0.5 * b[None, :, 5])
    return inside


def _torch_chunks(n: int, m: int):
    step = max(1, _TORCH_CHUNK_ELEMS // max(m, 1))
    for start in range(0, n, step):
        yield start, min(n, start + step)


def points_in_boxes(points, boxes, bottom_lift: float = 0.0):
    """Count the points in each box and give each point the first box that holds it.

    Args:
        points: (N, >=3) x, y, z[, ...] in metres, numpy array or torch tensor.
        boxes: (M, 7) x, y, z, dx, dy, dz, heading (metres, radians), same kind as points
            (a numpy array beside a tensor is moved to the tensor's device).
        bottom_lift: metres by which the bottom face is raised (0.05 for the study's
            LiDAR-detected rule).

    Returns:
        counts: (M,) int64, the number of points inside each box (a box with a negative
            size holds no point). Boxes are counted
            independently: a point inside two overlapping boxes adds to both counts.
        box_index: (N,) int64, the index of the first box (lowest index) holding the point,
            -1 when none does.
        numpy in -> numpy out; torch in -> torch out on the same device.

    Borders are inclusive on all faces (see the module docstring).
    """
    func = "points_in_boxes"
    lift = _check_lift(bottom_lift, func)
    points = check_points(points, func)
    boxes = check_boxes(boxes, func)
    points, boxes = _to_common(points, boxes)
    if is_torch(points) and not use_torch(points.device):
        counts, box_index = _points_in_boxes_numpy(_cpu_points(points), boxes.detach().to(torch.float64).numpy(),
                                                   lift, func)
        return torch.from_numpy(counts), torch.from_numpy(box_index)
    if is_torch(points):
        return _points_in_boxes_torch(points, boxes, lift)
    return _points_in_boxes_numpy(points, boxes, lift, func)


def _cpu_points(points: torch.Tensor) -> np.ndarray:
    p = points.detach()
    if p.dtype not in (torch.float32, torch.float64):
        p = p.to(torch.float64)
    return p.numpy()


def _points_in_boxes_torch(points: torch.Tensor, boxes: torch.Tensor, lift: float):
    """Vectorised torch version (any device), chunked over points."""
    dt = float_dtype_torch(points, boxes)
    p = points[:, :3].to(dt)
    b = boxes[:, :7].to(dt)
    n, m = p.shape[0], b.shape[0]
    counts = torch.zeros(m, dtype=torch.int64, device=p.device)
    box_index = torch.full((n,), -1, dtype=torch.int64, device=p.device)
    if n == 0 or m == 0:
        return counts, box_index
    ar = torch.arange(m, device=p.device)
    for start, stop in _torch_chunks(n, m):
        mask = _torch_mask_chunk(p[start:stop], b, lift)
        counts += mask.sum(0)
        first = torch.where(mask, ar[None], m).amin(dim=1)
        box_index[start:stop] = torch.where(first < m, first, -1)
    return counts, box_index


def _points_in_boxes_numpy(points: np.ndarray, boxes: np.ndarray, lift: float, func: str):
    pts = _numpy_points(points)
    m = boxes.shape[0]
    if pts.shape[0] == 0 or m == 0:
        return np.zeros(m, dtype=np.int64), np.full(pts.shape[0], -1, dtype=np.int64)
    table = _box_table(boxes, lift)
    if not np.isfinite(table).all():
        raise ValueError(f"{func}: boxes contain NaN or infinite values; drop or fix those rows")
    x0, y0, inv_cell, nx, ny = _grid_params(table)
    if pts.shape[0] < PARALLEL_MIN_POINTS or numba.get_num_threads() < 2:
        return _pib_kernel_serial(pts, table, x0, y0, inv_cell, nx, ny)
    nchunks = int(min(numba.get_num_threads() * 4, pts.shape[0]))
    return _pib_kernel_parallel(pts, table, x0, y0, inv_cell, nx, ny, nchunks)


def points_in_boxes_mask(points, boxes, bottom_lift: float = 0.0):
    """Membership matrix (N, M) bool: entry (i, j) is True when point i lies in box j.

    Same inputs, borders and device rules as `points_in_boxes`; numpy in -> numpy out,
    torch in -> torch out. Memory is N x M bytes, so prefer `points_in_boxes` for counts.
    """
    func = "points_in_boxes_mask"
    lift = _check_lift(bottom_lift, func)
    points = check_points(points, func)
    boxes = check_boxes(boxes, func)
    points, boxes = _to_common(points, boxes)
    if is_torch(points) and not use_torch(points.device):
        return torch.from_numpy(points_in_boxes_mask(_cpu_points(points), boxes.detach().to(torch.float64).numpy(),
                                                     lift))
    if is_torch(points):
        return _points_in_boxes_mask_torch(points, boxes, lift)
    pts = _numpy_points(points)
    m = boxes.shape[0]
    if pts.shape[0] == 0 or m == 0:
        return np.zeros((pts.shape[0], m), dtype=np.bool_)
    table = _box_table(boxes, lift)
    if not np.isfinite(table).all():
        raise ValueError(f"{func}: boxes contain NaN or infinite values; drop or fix those rows")
    return _pib_mask_kernel(pts, table)


def _points_in_boxes_mask_torch(points: torch.Tensor, boxes: torch.Tensor, lift: float) -> torch.Tensor:
    """Vectorised torch membership matrix (any device), chunked over points."""
    dt = float_dtype_torch(points, boxes)
    p = points[:, :3].to(dt)
    b = boxes[:, :7].to(dt)
    n, m = p.shape[0], b.shape[0]
    if n == 0 or m == 0:
        return torch.zeros((n, m), dtype=torch.bool, device=p.device)
    return torch.cat([_torch_mask_chunk(p[s:e], b, lift) for s, e in _torch_chunks(n, m)], dim=0)
