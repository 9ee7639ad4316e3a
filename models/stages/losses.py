"""Detection losses as plain functions: tensors in, a scalar (or per-element) tensor out."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from detbench.ops import boxes_to_corners_3d


def sigmoid_focal_loss(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor,
                       alpha: float, gamma: float) -> torch.Tensor:
    """Focal loss (Lin et al. 2017) summed over elements with per-element `weights`.

    logits, targets (0/1 float) and weights share a shape; returns a scalar.
    """
    p = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1 - p) * (1 - targets)
    alpha_t = alpha * targets + (1 - alpha) * (1 - targets)
    return (alpha_t * (1 - p_t).pow(gamma) * ce * weights).sum()


def add_sin_difference(pred: torch.Tensor, target: torch.Tensor, dim: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    """SECOND's heading trick: replace (p, t) at `dim` by (sin p cos t, cos p sin t).

    The smooth-L1 of the pair then penalises sin(p - t), which is 0 for p = t and for
    p = t + pi, so a box regressed backwards is not punished (the direction classifier
    decides which way the box faces).
    """
    p, t = pred[..., dim:dim + 1], target[..., dim:dim + 1]
    pe = torch.sin(p) * torch.cos(t)
    te = torch.cos(p) * torch.sin(t)
    pred = torch.cat([pred[..., :dim], pe, pred[..., dim + 1:]], dim=-1)
    target = torch.cat([target[..., :dim], te, target[..., dim + 1:]], dim=-1)
    return pred, target


def weighted_smooth_l1(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, beta: float = 1.0 / 9.0,
                       code_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Smooth-L1 over (..., C) residuals, each row weighted by `weights` (...); returns a scalar."""
    diff = pred - target
    diff = torch.where(torch.isfinite(diff), diff, torch.zeros_like(diff))
    if code_weights is not None:
        diff = diff * code_weights
    n = diff.abs()
    loss = torch.where(n < beta, 0.5 * n * n / beta, n - 0.5 * beta)
    return (loss.sum(dim=-1) * weights).sum()


def weighted_cross_entropy(logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Cross-entropy over (..., K) logits with integer labels (...) weighted per element; scalar out."""
    ce = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), labels.reshape(-1), reduction="none")
    return (ce * weights.reshape(-1)).sum()


def centernet_focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 2.0,
                         beta: float = 4.0) -> tuple[torch.Tensor, torch.Tensor]:
    """CenterNet's focal loss on a heat map; returns (summed loss (scalar), number of peaks (scalar)).

    logits, target: same shape, target in [0, 1] with exactly 1 at the peaks. Peaks:
    -(1 - p)^alpha log p; elsewhere -(1 - y)^beta p^alpha log(1 - p). log p and log(1 - p)
    come from logsigmoid, so saturated logits stay finite. Divide by max(peaks, 1) to
    normalise as CenterNet does.
    """
    logits, target = logits.float(), target.float()
    pos = target >= 1.0
    p = torch.sigmoid(logits)
    pos_loss = -((1 - p).pow(alpha) * F.logsigmoid(logits))
    neg_loss = -((1 - target).pow(beta) * p.pow(alpha) * F.logsigmoid(-logits))
    loss = torch.where(pos, pos_loss, neg_loss).sum()
    return loss, pos.sum()


def _safe_div(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    """num / den, 0 where den <= 0 (and a finite gradient there)."""
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def od_iou_loss(pred: torch.Tensor, target: torch.Tensor, distance: bool) -> torch.Tensor:
    """Orientation-decoupled IoU loss (PillarNet) of matching rows; (N, 7), (N, 7) -> (N,).

    The IoU is taken between the target and the predicted box turned to the target's
    heading (the predicted heading is ignored: orientation is learnt by the sin/cos L1
    loss alone, so the IoU gradient reaches only centre and size, and a box that is right
    but for its heading is not pushed to shrink). With equal headings the 3D IoU is exact
    and simple: in the target's frame both boxes are axis-aligned. With `distance` the
    DIoU term |centre offset|^2 / |diagonal of the enclosing box|^2 is added, so boxes that
    do not overlap still get a gradient. Loss = 1 - IoU (+ distance term), in [0, 2].
    Finite, with finite gradients, for zero sizes and identical centres.
    """
    if pred.shape != target.shape or pred.dim() != 2 or pred.shape[-1] < 7:
        raise ValueError(f"od_iou_loss: pred and target must both be (N, 7), got {tuple(pred.shape)} and "
                         f"{tuple(target.shape)}")
    pred, target = pred.float(), target.float()
    if pred.shape[0] == 0:
        return pred.new_zeros(0) + 0.0 * pred.sum()
    c, s = torch.cos(target[:, 6]), torch.sin(target[:, 6])
    dx, dy = pred[:, 0] - target[:, 0], pred[:, 1] - target[:, 1]
    local = torch.stack([dx * c + dy * s, -dx * s + dy * c, pred[:, 2] - target[:, 2]], dim=1)  # (N, 3)
    hp, hg = 0.5 * pred[:, 3:6].clamp(min=0), 0.5 * target[:, 3:6].clamp(min=0)
    lo = torch.maximum(local - hp, -hg)
    hi = torch.minimum(local + hp, hg)
    inter = (hi - lo).clamp(min=0).prod(dim=1)
    union = (2 * hp).prod(dim=1) + (2 * hg).prod(dim=1) - inter
    loss = 1.0 - _safe_div(inter, union).clamp(max=1.0)
    if distance:
        enclose = torch.maximum(local + hp, hg) - torch.minimum(local - hp, -hg)
        loss = loss + _safe_div((local * local).sum(dim=1), (enclose * enclose).sum(dim=1))
    return loss


def corner_loss(pred: torch.Tensor, gt: torch.Tensor, delta: float = 1.0) -> torch.Tensor:
    """Per-box corner loss (N,): mean Huber distance of the 8 corners, the smaller of gt and gt turned by pi."""
    if pred.shape[0] == 0:
        return pred.new_zeros(0)
    pc = boxes_to_corners_3d(pred)
    gc = boxes_to_corners_3d(gt)
    flipped = gt.clone()
    flipped[:, 6] = gt[:, 6] + math.pi
    fc = boxes_to_corners_3d(flipped)
    d = torch.minimum((pc - gc).norm(dim=-1), (pc - fc).norm(dim=-1))  # (N, 8)
    return F.huber_loss(d, torch.zeros_like(d), delta=delta, reduction="none").mean(dim=1)
