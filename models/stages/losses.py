"""Detection losses as plain functions: tensors in, a scalar (or per-element) tensor out."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def sigmoid_focal_loss(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor,
                       alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
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
