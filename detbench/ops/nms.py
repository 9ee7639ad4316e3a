"""Rotated non-maximum suppression in bird's-eye view.

Greedy NMS: boxes are visited by decreasing score (ties keep the input order, i.e. a
stable sort); a box is kept unless a box kept before it overlaps it with BEV IoU strictly
greater than `iou_threshold`. The BEV IoU is the exact rotated IoU of `detbench.ops.iou`.

numpy inputs (and torch tensors on the CPU) run one numba kernel; torch tensors on other
devices loop over the kept boxes in Python and compute each IoU row with vectorised torch
on the device, so the result never leaves the device except for one scalar per kept box.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit

from detbench.ops.box_coder import check_boxes, is_torch
from detbench.ops.iou import MODE_IOU_BEV, _CAP, _box_aux, _pair_at, _torch_pair_values

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


def _nms_torch(boxes: torch.Tensor, scores: torch.Tensor, thr: float, mk: int) -> torch.Tensor:
    """Device-side greedy NMS: one vectorised IoU row per kept box."""
    dev = boxes.device
    if boxes.shape[0] == 0 or mk == 0:
        return torch.zeros(0, dtype=torch.int64, device=dev)
    dt = torch.float64 if boxes.dtype == torch.float64 else torch.float32
    order = torch.sort(scores.detach(), descending=True, stable=True).indices
    b = boxes.detach()[order, :7].to(dt)
    remaining = torch.arange(b.shape[0], device=dev)
    keep = []
    while remaining.numel() > 0 and len(keep) < mk:
        i = remaining[:1]
        keep.append(i)
        rest = remaining[1:]
        if rest.numel() == 0:
            break
        iou = _torch_pair_values(b[i].expand(rest.numel(), 7), b[rest], MODE_IOU_BEV)
        remaining = rest[iou <= thr]
    return order[torch.cat(keep)]


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
        if boxes.device.type == "cpu":
            kept = _nms_numpy(boxes.detach().to(torch.float64).numpy(), scores.detach().to(torch.float64).numpy(),
                              thr, mk)
            return torch.from_numpy(kept)
        return _nms_torch(boxes, scores, thr, mk)
    return _nms_numpy(boxes, scores, thr, mk)
