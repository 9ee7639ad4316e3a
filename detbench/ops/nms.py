"""Rotated non-maximum suppression in bird's-eye view.

Greedy NMS: boxes are visited by decreasing score (ties keep the input order, i.e. a
stable sort); a box is kept unless a box kept before it overlaps it with BEV IoU strictly
greater than `iou_threshold`. The BEV IoU is the exact rotated IoU of `detbench.ops.iou`.

numpy inputs (and torch tensors on the CPU) run one numba kernel. Torch tensors on other devices
(and on the CPU under DETBENCH_OPS=torch, detbench.ops.backend) take the torch path, the same
greedy result in a few hundred tensor operations for 9000 boxes to 512 and a host sync per block
and sweep round, never one per kept box: the sorted boxes are taken in blocks of `_NMS_BLOCK`; a
block's boxes that a box kept in an earlier block suppresses drop out; the IoUs among the rest
give the block's suppression edges (exact IoU, in float64 as the numba kernel, only for pairs
whose axis-aligned bounds leave an IoU above the threshold possible), and a masked sweep over
the edges decides the block (`_greedy_block`); blocks stop once `max_keep` boxes are kept.
Non-finite boxes make the numba path raise; the torch path (no host sync to check them) keeps
such a box and lets it suppress nothing, so callers drop them first, as the models do.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit

from detbench.ops.backend import use_torch
from detbench.ops.box_coder import check_boxes, is_torch
from detbench.ops.iou import _CAP, _TORCH_CHUNK_PAIRS, MODE_IOU_BEV, _box_aux, _pair_at, _torch_pair_values

__all__ = ["nms_bev"]


@njit(cache=True)
def _nms_sorted(b, thr, max_keep):
    """Indices (into the sorted boxes b (N, >=7) float64) kept by greedy BEV NMS."""
    n = b.shape[0]
    suppressed = np.zeros(n, dtype=np.bool_)
    keep = np.empty(n, dtype=np.int64)
    buf = np.empty((4, _CAP), dtype=np.float64)
    aux = _box_aux(b)
    nk = 0
    for i in range(n):
        if suppressed[i]:
            continue
        keep[nk] = i
        nk += 1
        if nk >= max_keep:
            break
        for j in range(i + 1, n):
            if suppressed[j]:
                continue
            iou = _pair_at(b, i, aux, b, j, aux, MODE_IOU_BEV, buf)
            if iou > thr:
                suppressed[j] = True
    return keep[:nk]


def _check_args(boxes, scores, iou_threshold, max_keep, func: str):
    boxes = check_boxes(boxes, func)
    if is_torch(boxes) and not is_torch(scores):
        scores = torch.as_tensor(np.asarray(scores), device=boxes.device)
    elif is_torch(scores) and not is_torch(boxes):
        boxes = torch.as_tensor(np.asarray(boxes), device=scores.device)
    if not is_torch(scores):
        scores = np.asarray(scores)
    if scores.ndim != 1 or scores.shape[0] != boxes.shape[0]:
        raise ValueError(f"{func}: scores must have shape ({boxes.shape[0]},), one per box, "
                         f"got {tuple(scores.shape)}")
    thr = float(iou_threshold)
    if not (0.0 <= thr <= 1.0):
        raise ValueError(f"{func}: iou_threshold must lie in [0, 1], got {iou_threshold!r}")
    if max_keep is None:
        mk = boxes.shape[0]
    else:
        mk = int(max_keep)
        if mk < 0:
            raise ValueError(f"{func}: max_keep must be >= 0 or None, got {max_keep!r}")
    return boxes, scores, thr, mk


def _nms_numpy(boxes: np.ndarray, scores: np.ndarray, thr: float, mk: int) -> np.ndarray:
    b = np.ascontiguousarray(boxes[:, :7], dtype=np.float64)
    s = np.asarray(scores, dtype=np.float64)
    if b.shape[0] == 0 or mk == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.isfinite(b).all() or np.isnan(s).any():
        raise ValueError("nms_bev: boxes or scores contain NaN/inf; filter them before NMS")
    if (b[:, 3:6] < 0).any():
        raise ValueError("nms_bev: a box has a negative size dx, dy or dz; sizes are lengths in metres (>= 0)")
    order = np.argsort(-s, kind="stable")
    kept = _nms_sorted(np.ascontiguousarray(b[order]), thr, mk)
    return order[kept].astype(np.int64)


# Sorted boxes decided per block on the torch path: a block's IoUs with itself and with the boxes kept before it
# are computed at once; the greedy stops after the block in which max_keep boxes are kept.
_NMS_BLOCK = 1024


def _bev_extents(b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """x_min, x_max, y_min, y_max of the boxes' axis-aligned bounding boxes and their BEV areas (sizes clamped at 0)."""
    dx, dy = b[:, 3].clamp(min=0), b[:, 4].clamp(min=0)
    c, s = torch.cos(b[:, 6]).abs(), torch.sin(b[:, 6]).abs()
    ex, ey = 0.5 * (c * dx + s * dy), 0.5 * (s * dx + c * dy)
    return b[:, 0] - ex, b[:, 0] + ex, b[:, 1] - ey, b[:, 1] + ey, dx * dy


def _overlap_edges(a: torch.Tensor, b: torch.Tensor, thr: float, upper: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows of a, rows of b) of the pairs with BEV IoU(a[i], b[j]) > thr, i < j when `upper` (a and b the same
    block); a (n, 7), b (m, 7) float64.

    Only pairs that can pass get an exact IoU: the overlap U of the boxes' axis-aligned bounding boxes (capped at
    the smaller area) bounds their intersection from above, so IoU <= U / (area_a + area_b - U); a pair whose
    bound is below the threshold (with a relative margin of 1e-6 for rounding) cannot be suppressed. The x
    intervals are compared for all pairs, the rest of the bound only for pairs whose x intervals meet."""
    axl, axh, ayl, ayh, area_a = _bev_extents(a)
    bxl, bxh, byl, byh, area_b = _bev_extents(b)
    near = (axl[:, None] <= bxh[None]) & (axh[:, None] >= bxl[None])
    if upper:
        near = near.triu(1)
    i, j = near.nonzero(as_tuple=True)
    ix = (torch.minimum(axh[i], bxh[j]) - torch.maximum(axl[i], bxl[j])).clamp(min=0)
    iy = (torch.minimum(ayh[i], byh[j]) - torch.maximum(ayl[i], byl[j])).clamp(min=0)
    sa, sb = area_a[i], area_b[j]
    u = torch.minimum(ix * iy, torch.minimum(sa, sb))
    can = u * (1.0 + 1e-6) > thr * (sa + sb - u)
    i, j = i[can], j[can]
    if i.numel() == 0:
        return i, j
    iou = torch.cat([_torch_pair_values(a[i[s:s + _TORCH_CHUNK_PAIRS]], b[j[s:s + _TORCH_CHUNK_PAIRS]], MODE_IOU_BEV)
                     for s in range(0, i.numel(), _TORCH_CHUNK_PAIRS)])
    over = iou > thr
    return i[over], j[over]


def _greedy_block(src: torch.Tensor, dst: torch.Tensor, n: int) -> torch.Tensor:
    """The greedy decision among n boxes in score order: (n,) bool kept, for the edges src -> dst (src < dst:
    src suppresses dst when src is kept).

    A masked sweep to a fixed point: a box with a kept predecessor is suppressed; a box whose predecessors are
    all suppressed is kept. Each round decides at least the first undecided box, so the result is exactly the
    sequential sweep's, in as many rounds as the longest chain of boxes each suppressing the next."""
    dev = src.device
    keep = torch.zeros(n, dtype=torch.bool, device=dev)
    undecided = torch.ones(n, dtype=torch.bool, device=dev)
    while True:
        hit = torch.zeros(n, dtype=torch.int32, device=dev).index_add_(0, dst, keep[src].to(torch.int32))
        undecided &= hit == 0
        live = (keep | undecided)[src].to(torch.int32)
        blocked = torch.zeros(n, dtype=torch.int32, device=dev).index_add_(0, dst, live)
        new = undecided & (blocked == 0)
        keep |= new
        undecided &= ~new
        if not bool(undecided.any()):
            return keep


def _nms_torch(boxes: torch.Tensor, scores: torch.Tensor, thr: float, mk: int) -> torch.Tensor:
    """Device-side greedy NMS, block by block of the sorted boxes (float64 IoU, as the numba kernel): the boxes
    of a block that a box kept before it suppresses drop out, the rest are decided by `_greedy_block`."""
    dev = boxes.device
    if boxes.shape[0] == 0 or mk == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    order = torch.sort(scores.detach(), descending=True, stable=True).indices
    b = boxes.detach()[order, :7].to(torch.float64)
    kept = torch.zeros(0, dtype=torch.int64, device=dev)  # positions in the sorted boxes
    for start in range(0, b.shape[0], _NMS_BLOCK):
        pos = torch.arange(start, min(start + _NMS_BLOCK, b.shape[0]), device=dev)
        if kept.numel():
            _, hit = _overlap_edges(b[kept], b[pos], thr, upper=False)
            alive = torch.ones(pos.shape[0], dtype=torch.bool, device=dev)
            alive[hit] = False
            pos = pos[alive]
        blk = b[pos]
        src, dst = _overlap_edges(blk, blk, thr, upper=True)
        kept = torch.cat([kept, pos[_greedy_block(src, dst, pos.shape[0])]])
        if kept.numel() >= mk:
            break
    return order[kept[:mk]]


def nms_bev(boxes, scores, iou_threshold: float, max_keep: int | None = None):
    """Greedy rotated NMS in bird's-eye view.

    Args:
        boxes: (N, 7) x, y, z, dx, dy, dz, heading (metres, radians); numpy or torch.
        scores: (N,) scores, higher is better (same kind as boxes).
        iou_threshold: a box is suppressed when its BEV IoU with an already kept box is
            strictly greater than this value (0..1).
        max_keep: stop after this many kept boxes (None: no limit).
    Returns:
        (K,) int64 indices into `boxes`, highest score first (ties in input order);
        numpy for numpy input, a tensor on the input's device for torch input.
    """
    func = "nms_bev"
    boxes, scores, thr, mk = _check_args(boxes, scores, iou_threshold, max_keep, func)
    if is_torch(boxes):
        if not use_torch(boxes.device):
            kept = _nms_numpy(boxes.detach().to(torch.float64).numpy(), scores.detach().to(torch.float64).numpy(),
                              thr, mk)
            return torch.from_numpy(kept)
        return _nms_torch(boxes, scores, thr, mk)
    return _nms_numpy(boxes, scores, thr, mk)
