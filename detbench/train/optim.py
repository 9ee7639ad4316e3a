"""AdamW with a one-cycle learning-rate schedule (OpenPCDet's `adam_onecycle`, in torch's own classes).

The learning rate rises from lr / div_factor to lr over the first `pct_start` of the steps
(cosine), then anneals to lr / (div_factor * final_div_factor); Adam's beta1 cycles the
other way between the two ends of `momentum_range`. The schedule advances once per
optimizer step.
"""
from __future__ import annotations

from torch import nn
from torch.optim import AdamW
from torch.optim.lr_scheduler import OneCycleLR

__all__ = ["build_optimizer", "build_scheduler"]


def build_optimizer(model: nn.Module, lr: float, weight_decay: float, betas: tuple[float, float] = (0.9, 0.99)
                    ) -> AdamW:
    """AdamW over the trainable parameters; biases and 1-D (normalisation) weights get no weight decay.

    Args:
        lr: peak learning rate (OneCycleLR overwrites the starting value).
        weight_decay: decoupled weight decay for the >= 2-D weights.
        betas: Adam's (beta1, beta2); beta1 is cycled by the scheduler.
    """
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (no_decay if p.ndim <= 1 or name.endswith(".bias") else decay).append(p)
    if not decay and not no_decay:
        raise ValueError("the model has no trainable parameters; nothing to optimise")
    groups = [{"params": decay, "weight_decay": float(weight_decay)},
              {"params": no_decay, "weight_decay": 0.0}]
    return AdamW([g for g in groups if g["params"]], lr=float(lr), betas=(float(betas[0]), float(betas[1])))


def build_scheduler(optimizer: AdamW, lr: float, total_steps: int, pct_start: float = 0.4, div_factor: float = 10.0,
                    final_div_factor: float = 100.0, momentum_range: tuple[float, float] = (0.85, 0.95)
                    ) -> OneCycleLR:
    """One-cycle schedule over `total_steps` optimizer steps (epochs x batches per epoch).

    Args:
        lr: peak learning rate.
        pct_start: share of the steps spent rising, in (0, 1).
        div_factor: start lr = lr / div_factor.
        final_div_factor: end lr = start lr / final_div_factor.
        momentum_range: (low, high) for Adam's beta1: high at the start and end, low at the peak lr.
    """
    if total_steps < 1:
        raise ValueError(f"the one-cycle schedule needs at least one step, got total_steps={total_steps} "
                         f"(is the training set empty?)")
    if not 0.0 < pct_start < 1.0:
        raise ValueError(f"pct_start must be in (0, 1), got {pct_start}")
    lo, hi = momentum_range
    return OneCycleLR(optimizer, max_lr=float(lr), total_steps=int(total_steps), pct_start=float(pct_start),
                      anneal_strategy="cos", cycle_momentum=True, base_momentum=float(lo), max_momentum=float(hi),
                      div_factor=float(div_factor), final_div_factor=float(final_div_factor))
