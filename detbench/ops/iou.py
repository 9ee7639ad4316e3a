"""Exact IoU of rotated boxes: bird's-eye view (BEV) and 3-D.

Boxes are (x, y, z, dx, dy, dz, heading): centre, length along the heading, width, height
(metres), heading in radians (any value; angles are periodic, so +-pi and values outside
[-pi, pi) are fine).

Method (both the numba and the torch path)
1. Work in box a's frame: take b's centre relative to a's centre, rotate it by -heading_a,
   and give b the heading difference. All later arithmetic involves coordinates of the
   size of the boxes, never of their position, so boxes at x = 1e4 m lose no precision
   (no cancellation of large numbers) and identical boxes map onto each other exactly.
2. In that frame a is the axis-aligned rectangle [-dx_a/2, dx_a/2] x [-dy_a/2, dy_a/2].
   Clip b's rectangle (4 corners, counter-clockwise) against a's four half-planes
   (Sutherland-Hodgman). A clipped vertex gets the clip line's coordinate exactly.
   Vertices on a border count as inside, so touching boxes give a degenerate polygon of
   area 0 and parallel or coincident edges need no special case.
3. BEV intersection area = shoelace area of the clipped polygon, clamped to
   [0, min(area_a, area_b)]. 3-D intersection = BEV area x the overlap of the z-intervals
   (computed relative to a's centre too).
4. IoU = intersection / (area_a + area_b - intersection) (volumes for 3-D), and 0 when the
   union is 0 (zero-size boxes give 0, never NaN). Results lie in [0, 1].

numpy inputs: computed in float64 by numba kernels, float64 output; rows run in parallel
for large matrices. Negative sizes or NaN/inf values raise a ValueError.
torch inputs: output on the inputs' device in float64 if either input is float64, else
float32. On CUDA (and on the CPU when an input requires grad) a vectorised torch kernel
runs on the device: no Python loop over pairs; pairs whose circumscribed circles are
apart are skipped (one `nonzero`, i.e. one host sync per call), the rest are processed in
chunks to bound memory; it computes in the output dtype and autograd flows through it
(the vertex selection is piecewise constant). CPU tensors without grad take the numba
kernels (float64, then cast), which are much faster on the CPU; DETBENCH_OPS=torch makes CPU tensors
take the torch path (detbench.ops.backend). Negative sizes are
clamped to 0 on the torch paths (no host sync to check them). A NaN or inf box raises the
numpy path's ValueError for CPU tensors too; on the torch path (no host sync) every IoU of
such a box is NaN, never a silent 0.

Numba-callable kernels for other njit code: `iou3d_pair_nb(a, b)`, `iou_bev_pair_nb(a, b)`,
`overlap_bev_pair_nb(a, b)` on 1-D float64 arrays of >= 7 values, and
`iou3d_matrix_nb(a, b)`, `iou_bev_matrix_nb(a, b)` on (N, >=7) / (M, >=7) float64 arrays.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from detbench.ops.backend import use_torch
from detbench.ops.box_coder import check_boxes, float_dtype_torch, is_torch

__all__ = [
    "boxes_iou_bev",
    "boxes_iou3d",
    "boxes_overlap_bev",
    "boxes_iou3d_aligned",
    "boxes_iou_bev_aligned",
    "iou3d_pair_nb",
    "iou_bev_pair_nb",
    "overlap_bev_pair_nb",
    "iou3d_matrix_nb",
    "iou_bev_matrix_nb",
]

MODE_OVERLAP_BEV = 0  # BEV intersection area, m^2
MODE_IOU_BEV = 1
MODE_IOU_3D = 2

_CAP = 16  # vertex buffer size; a rectangle clipped by 4 half-planes has at most 8 vertices
# pairs; smaller matrices run serially: ~1-70 ns a pair, and threads cost ~10 ms when the cores are busy
_PARALLEL_MIN_PAIRS = 1 << 20
_TORCH_CHUNK_PAIRS = 1 << 18  # pairs per torch chunk (about 60 MB of float64 temporaries)


# ----------------------------------------------------------------------------------------
# numba kernels
# ----------------------------------------------------------------------------------------
@njit(cache=True)
def _clip(buf, src, dst, n, axis, sign, h):
    """Clip the polygon in buf[src] (x), buf[src + 1] (y), first n vertices, to
    sign * coord <= h where coord is x (axis 0) or y (axis 1), i.e. one side of a's
    rectangle; the result goes to buf[dst], buf[dst + 1]. Returns its vertex count.

    A vertex on the line counts as inside. A new vertex gets the line's coordinate
    exactly and the other coordinate by interpolation along the crossing edge."""
    k = 0
    cap = buf.shape[1]
    cs, os_ = src + axis, src + 1 - axis  # rows of the clipped and of the other coordinate
    cd, od = dst + axis, dst + 1 - axis
    line = sign * h
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        f0 = sign * buf[cs, i] - h
        f1 = sign * buf[cs, j] - h
        in1 = f1 <= 0.0
        if (f0 <= 0.0) != in1 and k < cap:
            t = f0 / (f0 - f1)  # denominator non-zero: one side <= 0, the other > 0
            o0 = buf[os_, i]
            buf[cd, k] = line
            buf[od, k] = o0 + t * (buf[os_, j] - o0)
            k += 1
        if in1 and k < cap:
            buf[cd, k] = buf[cs, j]
            buf[od, k] = buf[os_, j]
            k += 1
    return k


@njit(cache=True)
def _overlap_local(cx, cy, c, s, hxb, hyb, hxa, hya, buf):
    """BEV intersection area of b (centre (cx, cy), rotation (c, s), half sizes hxb, hyb,
    all in a's frame) with a = [-hxa, hxa] x [-hya, hya]. `buf` is (4, _CAP) float64."""
    # b's axis-aligned extent in a's frame: separated along x or y -> no overlap
    ex = abs(c) * hxb + abs(s) * hyb
    ey = abs(s) * hxb + abs(c) * hyb
    if abs(cx) - ex >= hxa or abs(cy) - ey >= hya:
        return 0.0
    # counter-clockwise corners of b in rows 0 (x) and 1 (y)
    inside = True
    for k in range(4):
        ux = hxb if k == 0 or k == 3 else -hxb
        uy = hyb if k < 2 else -hyb
        x = cx + ux * c - uy * s
        y = cy + ux * s + uy * c
        buf[0, k] = x
        buf[1, k] = y
        inside = inside and abs(x) <= hxa and abs(y) <= hya
    if inside:  # b lies in a
        return 4.0 * hxb * hyb
    n = _clip(buf, 0, 2, 4, 0, 1.0, hxa)
    if n == 0:
        return 0.0
    n = _clip(buf, 2, 0, n, 0, -1.0, hxa)
    if n == 0:
        return 0.0
    n = _clip(buf, 0, 2, n, 1, 1.0, hya)
    if n == 0:
        return 0.0
    n = _clip(buf, 2, 0, n, 1, -1.0, hya)
    if n < 3:
        return 0.0
    area = 0.0
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        area += buf[0, i] * buf[1, j] - buf[0, j] * buf[1, i]
    return abs(0.5 * area)


@njit(cache=True)
def _pair_value(a0, a1, a2, a3, a4, a5, ca, sa, ra, b0, b1, b2, b3, b4, b5, cb, sb, rb, mode, buf):
    """Overlap area / BEV IoU / 3-D IoU of boxes a and b: centre, sizes, cos/sin of the
    heading and the circumscribed radius of each box (the heading difference is taken
    from the products of cos/sin, so no trigonometry runs per pair)."""
    hxa, hya, hza = 0.5 * a3, 0.5 * a4, 0.5 * a5
    hxb, hyb, hzb = 0.5 * b3, 0.5 * b4, 0.5 * b5
    rx = b0 - a0
    ry = b1 - a1
    area_a = a3 * a4
    area_b = b3 * b4
    inter = 0.0
    # cheap reject: circumscribed circles apart
    if rx * rx + ry * ry <= (ra + rb) * (ra + rb) * (1.0 + 1e-12):
        cx = rx * ca + ry * sa
        cy = -rx * sa + ry * ca
        cdh = cb * ca + sb * sa  # cos(hb - ha)
        sdh = sb * ca - cb * sa  # sin(hb - ha)
        inter = _overlap_local(cx, cy, cdh, sdh, hxb, hyb, hxa, hya, buf)
        inter = min(inter, area_a, area_b)
    if mode == MODE_OVERLAP_BEV:
        return inter
    if mode == MODE_IOU_BEV:
        union = area_a + area_b - inter
        return inter / union if union > 0.0 else 0.0
    dz = b2 - a2
    top = min(hza, dz + hzb)
    bottom = max(-hza, dz - hzb)
    ov = top - bottom if top > bottom else 0.0
    inter3 = inter * ov
    union3 = area_a * a5 + area_b * b5 - inter3
    if union3 <= 0.0:
        return 0.0
    return min(inter3 / union3, 1.0)


@njit(cache=True)
def _box_aux(boxes):
    """(N, 3): cos heading, sin heading, circumscribed radius (half the BEV diagonal)."""
    n = boxes.shape[0]
    aux = np.empty((n, 3), dtype=np.float64)
    for i in range(n):
        aux[i, 0] = math.cos(boxes[i, 6])
        aux[i, 1] = math.sin(boxes[i, 6])
        aux[i, 2] = 0.5 * math.sqrt(boxes[i, 3] * boxes[i, 3] + boxes[i, 4] * boxes[i, 4])
    return aux


@njit(cache=True)
def _pair_at(a, i, aa, b, j, ab, mode, buf):
    """Value for rows a[i], b[j] with their precomputed `_box_aux` rows."""
    return _pair_value(a[i, 0], a[i, 1], a[i, 2], a[i, 3], a[i, 4], a[i, 5], aa[i, 0], aa[i, 1], aa[i, 2],
                       b[j, 0], b[j, 1], b[j, 2], b[j, 3], b[j, 4], b[j, 5], ab[j, 0], ab[j, 1], ab[j, 2], mode, buf)


@njit(cache=True)
def _pair_rows(a, b, mode):
    buf = np.empty((4, _CAP), dtype=np.float64)
    ra = 0.5 * math.sqrt(a[3] * a[3] + a[4] * a[4])
    rb = 0.5 * math.sqrt(b[3] * b[3] + b[4] * b[4])
    return _pair_value(a[0], a[1], a[2], a[3], a[4], a[5], math.cos(a[6]), math.sin(a[6]), ra,
                       b[0], b[1], b[2], b[3], b[4], b[5], math.cos(b[6]), math.sin(b[6]), rb, mode, buf)


@njit(cache=True)
def iou3d_pair_nb(a, b):
    """3-D IoU of two boxes, each a 1-D float array (>= 7 values). Numba-callable."""
    return _pair_rows(a, b, MODE_IOU_3D)


@njit(cache=True)
def iou_bev_pair_nb(a, b):
    """BEV IoU of two boxes, each a 1-D float array (>= 7 values). Numba-callable."""
    return _pair_rows(a, b, MODE_IOU_BEV)


@njit(cache=True)
def overlap_bev_pair_nb(a, b):
    """BEV intersection area (m^2) of two boxes, 1-D float arrays (>= 7 values). Numba-callable."""
    return _pair_rows(a, b, MODE_OVERLAP_BEV)


@njit(cache=True)
def _row(a, i, aa, b, ab, mode, buf, out):
    """Fill out[i, :]; pairs whose circumscribed circles are apart stay 0."""
    xi, yi, ri = a[i, 0], a[i, 1], aa[i, 2]
    for j in range(b.shape[0]):
        dx = b[j, 0] - xi
        dy = b[j, 1] - yi
        r = ri + ab[j, 2]
        if dx * dx + dy * dy > r * r * (1.0 + 1e-12):
            continue
        out[i, j] = _pair_at(a, i, aa, b, j, ab, mode, buf)


@njit(cache=True)
def _matrix_serial(a, b, mode):
    out = np.zeros((a.shape[0], b.shape[0]), dtype=np.float64)
    aa, ab = _box_aux(a), _box_aux(b)
    buf = np.empty((4, _CAP), dtype=np.float64)
    for i in range(a.shape[0]):
        _row(a, i, aa, b, ab, mode, buf, out)
    return out


@njit(cache=True, parallel=True)
def _matrix_parallel(a, b, mode):
    out = np.zeros((a.shape[0], b.shape[0]), dtype=np.float64)
    aa, ab = _box_aux(a), _box_aux(b)
    for i in prange(a.shape[0]):
        buf = np.empty((4, _CAP), dtype=np.float64)
        _row(a, i, aa, b, ab, mode, buf, out)
    return out


@njit(cache=True)
def _aligned(a, b, mode):
    n = a.shape[0]
    out = np.zeros(n, dtype=np.float64)
    aa, ab = _box_aux(a), _box_aux(b)
    buf = np.empty((4, _CAP), dtype=np.float64)
    for i in range(n):
        out[i] = _pair_at(a, i, aa, b, i, ab, mode, buf)
    return out


@njit(cache=True)
def iou3d_matrix_nb(a, b):
    """(N, M) 3-D IoU of float64 boxes a (N, >=7) and b (M, >=7), serial. Numba-callable."""
    return _matrix_serial(a, b, MODE_IOU_3D)


@njit(cache=True)
def iou_bev_matrix_nb(a, b):
    """(N, M) BEV IoU of float64 boxes a (N, >=7) and b (M, >=7), serial. Numba-callable."""
    return _matrix_serial(a, b, MODE_IOU_BEV)


# ----------------------------------------------------------------------------------------
# torch path
# ----------------------------------------------------------------------------------------
def _torch_clip(px: torch.Tensor, py: torch.Tensor, axis: int, sign: float, h: torch.Tensor):
    """Clip (P, K) polygons to sign * coord <= h (coord = x if axis == 0 else y).

    Polygons are padded with copies of their first vertex (zero-length edges, no area).
    Returns (P, K + 1) polygons in the same padded form.
    """
    p, k = px.shape
    coord = px if axis == 0 else py
    f0 = sign * coord - h[:, None]
    f1 = torch.roll(f0, -1, dims=1)
    x1, y1 = torch.roll(px, -1, dims=1), torch.roll(py, -1, dims=1)
    in0, in1 = f0 <= 0, f1 <= 0
    cross = in0 != in1
    denom = torch.where(cross, f0 - f1, torch.ones_like(f0))
    t = f0 / denom
    if axis == 0:
        ix = (sign * h)[:, None].expand(p, k)
        iy = py + t * (y1 - py)
    else:
        ix = px + t * (x1 - px)
        iy = (sign * h)[:, None].expand(p, k)
    # per edge (S -> E): [intersection if the edge crosses, E if E is inside]
    cx = torch.stack([ix, x1], dim=2).reshape(p, 2 * k)
    cy = torch.stack([iy, y1], dim=2).reshape(p, 2 * k)
    valid = torch.stack([cross, in1], dim=2).reshape(p, 2 * k)
    kout = k + 1
    pos = torch.cumsum(valid.to(torch.int64), dim=1) - 1
    count = pos[:, -1] + 1
    # invalid candidates go to a dump slot; rounding can (in near-degenerate cases) make
    # more than k + 1 vertices: the surplus shares the last slot, an error at rounding level
    target = torch.where(valid, pos.clamp(max=kout - 1), torch.full_like(pos, kout))
    ox = torch.zeros((p, kout + 1), dtype=px.dtype, device=px.device).scatter(1, target, cx)
    oy = torch.zeros((p, kout + 1), dtype=py.dtype, device=py.device).scatter(1, target, cy)
    ox, oy = ox[:, :kout], oy[:, :kout]
    pad = torch.arange(kout, device=px.device)[None] >= count[:, None]
    ox = torch.where(pad, ox[:, :1], ox)
    oy = torch.where(pad, oy[:, :1], oy)
    return ox, oy, count


def _torch_pair_values(a: torch.Tensor, b: torch.Tensor, mode: int) -> torch.Tensor:
    """Values for aligned rows a (P, 7), b (P, 7) of one float dtype."""
    hxa, hya, hza = 0.5 * a[:, 3].clamp(min=0), 0.5 * a[:, 4].clamp(min=0), 0.5 * a[:, 5].clamp(min=0)
    hxb, hyb, hzb = 0.5 * b[:, 3].clamp(min=0), 0.5 * b[:, 4].clamp(min=0), 0.5 * b[:, 5].clamp(min=0)
    rx, ry = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    ca, sa = torch.cos(a[:, 6]), torch.sin(a[:, 6])
    cx = rx * ca + ry * sa
    cy = ry * ca - rx * sa
    dh = b[:, 6] - a[:, 6]
    c, s = torch.cos(dh)[:, None], torch.sin(dh)[:, None]
    sgn_x = torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=a.dtype, device=a.device)[None]
    sgn_y = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=a.dtype, device=a.device)[None]
    ux, uy = sgn_x * hxb[:, None], sgn_y * hyb[:, None]
    px = cx[:, None] + ux * c - uy * s
    py = cy[:, None] + ux * s + uy * c
    count = None
    for axis, sign, h in ((0, 1.0, hxa), (0, -1.0, hxa), (1, 1.0, hya), (1, -1.0, hya)):
        px, py, count = _torch_clip(px, py, axis, sign, h)
    cross = px * torch.roll(py, -1, dims=1) - torch.roll(px, -1, dims=1) * py
    area_a, area_b = 4.0 * hxa * hya, 4.0 * hxb * hyb
    inter = (0.5 * cross.sum(dim=1)).abs()
    inter = torch.where(count >= 3, inter, torch.zeros_like(inter))
    inter = torch.minimum(inter, torch.minimum(area_a, area_b))
    zero = torch.zeros_like(inter)
    if mode == MODE_OVERLAP_BEV:
        return inter
    if mode == MODE_IOU_BEV:
        union = area_a + area_b - inter
        return torch.where(union > 0, inter / torch.where(union > 0, union, torch.ones_like(union)), zero)
    dz = b[:, 2] - a[:, 2]
    ov = (torch.minimum(hza, dz + hzb) - torch.maximum(-hza, dz - hzb)).clamp(min=0)
    inter3 = inter * ov
    union3 = area_a * 2.0 * hza + area_b * 2.0 * hzb - inter3
    iou = torch.where(union3 > 0, inter3 / torch.where(union3 > 0, union3, torch.ones_like(union3)), zero)
    return iou.clamp(max=1.0)


def _torch_matrix(a: torch.Tensor, b: torch.Tensor, mode: int) -> torch.Tensor:
    """(N, M) values by the vectorised torch kernel, only for pairs whose circumscribed
    circles meet (the others are 0); chunked to bound memory."""
    dt = float_dtype_torch(a, b)
    a = a[:, :7].to(dt)
    b = b[:, :7].to(dt)
    n, m = a.shape[0], b.shape[0]
    out = torch.zeros((n, m), dtype=dt, device=a.device)
    if n == 0 or m == 0:
        return out
    ra = 0.5 * torch.hypot(a[:, 3], a[:, 4]).detach()
    rb = 0.5 * torch.hypot(b[:, 3], b[:, 4]).detach()
    ad, bd = a.detach(), b.detach()
    rows = max(1, _TORCH_CHUNK_PAIRS // m)
    pairs = []
    for start in range(0, n, rows):
        d2 = ((ad[start:start + rows, None, 0] - bd[None, :, 0]) ** 2
              + (ad[start:start + rows, None, 1] - bd[None, :, 1]) ** 2)
        near = d2 <= ((ra[start:start + rows, None] + rb[None, :]) ** 2) * (1.0 + 1e-6)
        idx = near.nonzero()
        idx[:, 0] += start
        pairs.append(idx)
    idx = torch.cat(pairs, dim=0)
    if idx.shape[0] == 0:
        return out
    values = [_torch_pair_values(a[idx[s:s + _TORCH_CHUNK_PAIRS, 0]], b[idx[s:s + _TORCH_CHUNK_PAIRS, 1]], mode)
              for s in range(0, idx.shape[0], _TORCH_CHUNK_PAIRS)]
    return out.index_put((idx[:, 0], idx[:, 1]), torch.cat(values))


def _numba_for_torch(a: torch.Tensor, b: torch.Tensor) -> bool:
    """CPU tensors that need no gradient take the (faster, float64) numba kernels."""
    return not use_torch(a.device) and not (a.requires_grad or b.requires_grad)


def _cpu_boxes(t: torch.Tensor) -> np.ndarray:
    """float64 numpy copy of tensor boxes with sizes clamped at 0 (the torch-path rule)."""
    arr = t[:, :7].detach().to(torch.float64).numpy().copy()
    np.maximum(arr[:, 3:6], 0.0, out=arr[:, 3:6])
    return arr


# ----------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------
def _nonfinite_error(func: str, name: str, row: int, box) -> ValueError:
    return ValueError(f"{func}: `{name}` row {row} contains NaN or inf ({box.tolist()}); "
                      f"drop or fix non-finite boxes first")


def _check_finite_tensor(t: torch.Tensor, func: str, name: str) -> None:
    """The numpy path's ValueError for a CPU tensor holding a non-finite box (checking costs no sync there);
    the torch path (CUDA, or DETBENCH_OPS=torch) gives NaN instead, as on the GPU."""
    if use_torch(t.device):
        return
    bad = ~torch.isfinite(t[:, :7]).all(dim=1)
    if bool(bad.any()):
        row = int(bad.nonzero()[0, 0])
        raise _nonfinite_error(func, name, row, t[row].detach())


def _nan_where_nonfinite(values: torch.Tensor, a: torch.Tensor, b: torch.Tensor, pairwise: bool) -> torch.Tensor:
    """`values` with NaN wherever box a or b is not finite (the device-side rule: no host sync)."""
    bad_a = ~torch.isfinite(a[:, :7]).all(dim=1)
    bad_b = ~torch.isfinite(b[:, :7]).all(dim=1)
    bad = bad_a[:, None] | bad_b[None, :] if pairwise else bad_a | bad_b
    return values.masked_fill(bad, float("nan"))


def _numpy_boxes(boxes: np.ndarray, func: str, name: str) -> np.ndarray:
    b = np.ascontiguousarray(boxes[:, :7], dtype=np.float64)
    if b.size and not np.isfinite(b).all():
        bad = int(np.nonzero(~np.isfinite(b).all(axis=1))[0][0])
        raise _nonfinite_error(func, name, bad, boxes[bad])
    if b.size and (b[:, 3:6] < 0).any():
        bad = int(np.nonzero((b[:, 3:6] < 0).any(axis=1))[0][0])
        raise ValueError(f"{func}: `{name}` row {bad} has a negative size dx, dy or dz "
                         f"({boxes[bad].tolist()}); sizes are lengths in metres (>= 0)")
    return b


def _prepare(a, b, func: str):
    a = check_boxes(a, func, "a")
    b = check_boxes(b, func, "b")
    if is_torch(a) or is_torch(b):
        if not is_torch(a):
            a = torch.as_tensor(np.asarray(a), device=b.device)
        if not is_torch(b):
            b = torch.as_tensor(np.asarray(b), device=a.device)
        if a.device != b.device:
            raise ValueError(f"{func}: a is on {a.device} but b on {b.device}; move them to one device")
        _check_finite_tensor(a, func, "a")
        _check_finite_tensor(b, func, "b")
        return a, b, True
    return _numpy_boxes(a, func, "a"), _numpy_boxes(b, func, "b"), False


def _matrix(a, b, mode: int, func: str):
    a, b, torch_path = _prepare(a, b, func)
    if torch_path:
        if not _numba_for_torch(a, b):
            return _nan_where_nonfinite(_torch_matrix(a, b, mode), a, b, pairwise=True)
        dt = float_dtype_torch(a, b)
        return torch.from_numpy(_numpy_matrix(_cpu_boxes(a), _cpu_boxes(b), mode)).to(dt)
    return _numpy_matrix(a, b, mode)


def _numpy_matrix(a: np.ndarray, b: np.ndarray, mode: int) -> np.ndarray:
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros((a.shape[0], b.shape[0]), dtype=np.float64)
    if a.shape[0] * b.shape[0] >= _PARALLEL_MIN_PAIRS and a.shape[0] > 1:
        return _matrix_parallel(a, b, mode)
    return _matrix_serial(a, b, mode)


def boxes_iou3d(a, b):
    """Pairwise 3-D IoU of rotated boxes.

    Args:
        a: (N, 7) boxes x, y, z, dx, dy, dz, heading (metres, radians).
        b: (M, 7) boxes, same layout. numpy or torch (a numpy array beside a tensor is
            moved to the tensor's device).
    Returns:
        (N, M) IoU in [0, 1]: numpy float64 for numpy inputs; for torch inputs a tensor on
        the inputs' device (float64 if either is float64, else float32).
    """
    return _matrix(a, b, MODE_IOU_3D, "boxes_iou3d")


def boxes_iou_bev(a, b):
    """Pairwise bird's-eye-view IoU of rotated boxes (z and dz ignored).

    Args / returns as `boxes_iou3d`: a (N, 7), b (M, 7) -> (N, M) in [0, 1].
    """
    return _matrix(a, b, MODE_IOU_BEV, "boxes_iou_bev")


def boxes_overlap_bev(a, b):
    """Pairwise bird's-eye-view intersection area (m^2) of rotated boxes.

    Args / returns as `boxes_iou3d`: a (N, 7), b (M, 7) -> (N, M) areas >= 0.
    """
    return _matrix(a, b, MODE_OVERLAP_BEV, "boxes_overlap_bev")


def _aligned_values(a, b, mode: int, func: str):
    a, b, torch_path = _prepare(a, b, func)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{func}: a and b need the same number of rows (one pair per row), "
                         f"got {a.shape[0]} and {b.shape[0]}")
    if torch_path:
        dt = float_dtype_torch(a, b)
        if a.shape[0] == 0:
            return torch.zeros(0, dtype=dt, device=a.device)
        if _numba_for_torch(a, b):
            return torch.from_numpy(_aligned(_cpu_boxes(a), _cpu_boxes(b), mode)).to(dt)
        out = [_torch_pair_values(a[s:s + _TORCH_CHUNK_PAIRS, :7].to(dt), b[s:s + _TORCH_CHUNK_PAIRS, :7].to(dt), mode)
               for s in range(0, a.shape[0], _TORCH_CHUNK_PAIRS)]
        return _nan_where_nonfinite(torch.cat(out), a, b, pairwise=False)
    return _aligned(a, b, mode)


def boxes_iou3d_aligned(a, b):
    """3-D IoU of matching rows: a (N, 7), b (N, 7) -> (N,) in [0, 1] (e.g. for IoU targets).

    numpy -> float64 numpy, torch -> torch on the inputs' device (differentiable).
    """
    return _aligned_values(a, b, MODE_IOU_3D, "boxes_iou3d_aligned")


def boxes_iou_bev_aligned(a, b):
    """BEV IoU of matching rows: a (N, 7), b (N, 7) -> (N,) in [0, 1]; types as `boxes_iou3d_aligned`."""
    return _aligned_values(a, b, MODE_IOU_BEV, "boxes_iou_bev_aligned")
