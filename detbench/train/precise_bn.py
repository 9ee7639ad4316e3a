"""BatchNorm statistics recomputed from training batches at a checkpoint ("precise BN").

A BatchNorm layer normalises with its batch's statistics while training and with its running
averages in eval mode. The detectors' layers average with momentum 0.01 (OpenPCDet's setting), so
the running statistics trail the weights by about a hundred steps: while the learning rate is high
the weights move faster than the averages follow, and a checkpoint evaluated mid-training normalises
with statistics of weights it no longer has (its AP reads near 0 although the model has learned).
`recompute_bn_statistics` resets every BatchNorm's running statistics and averages them anew, with
equal weight, over a fixed number of training batches run through the model in train mode without
gradients, so a checkpoint's eval mode matches its weights. The forward passes leave the weights,
the optimiser and the random streams as they were: training continues exactly as without them.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch import nn

from detbench.train.rng import capture_rng_state, restore_rng_state

__all__ = ["batchnorm_layers", "recompute_bn_statistics"]


def batchnorm_layers(model: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    """The model's BatchNorm layers that keep running statistics."""
    return [m for m in model.modules()
            if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.track_running_stats]


def recompute_bn_statistics(model: nn.Module, batches: Iterable, forward: Callable[[nn.Module, object], object]
                            ) -> int:
    """Replace the running mean and variance of every BatchNorm of `model` by their equal-weight average over
    `batches` (each passed as `forward(model, batch)` in train mode, without gradients). Returns the number of
    batches used; with none (or no BatchNorm layer) the statistics are left as they were."""
    layers = batchnorm_layers(model)
    if not layers:
        return 0
    saved = [(m.running_mean.clone(), m.running_var.clone(), m.num_batches_tracked.clone(), m.momentum)
             for m in layers]
    was_training = model.training
    rng = capture_rng_state()  # a forward may draw random numbers (point sampling, RoI subsets)
    n = 0
    try:
        for m in layers:
            m.reset_running_stats()
            m.momentum = None  # cumulative moving average: every batch weighs the same
        model.train()
        with torch.no_grad():
            for batch in batches:
                forward(model, batch)
                n += 1
    finally:
        for m, (mean, var, count, momentum) in zip(layers, saved):
            m.momentum = momentum
            if n == 0:
                m.running_mean.copy_(mean)
                m.running_var.copy_(var)
                m.num_batches_tracked.copy_(count)
        restore_rng_state(rng)
        model.train(was_training)
    return n
