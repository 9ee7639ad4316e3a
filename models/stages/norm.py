"""Normalisation layers shared by the stages: BatchNorm with the sparse detectors' eps and momentum.

OpenPCDet's voxel and pillar backbones (and the reference code of SECOND and PillarNet)
follow every convolution with BatchNorm(eps=1e-3, momentum=0.01); these helpers are the one
place that setting lives.
"""
from __future__ import annotations

import torch.nn as nn

from detbench.sparse import SafeBatchNorm1d

BN_EPS, BN_MOMENTUM = 1e-3, 0.01


def sparse_bn(channels: int) -> SafeBatchNorm1d:
    """BatchNorm for (N, C) features (a sparse tensor's, or points'); accepts N < 2 while training."""
    return SafeBatchNorm1d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


def dense_bn(channels: int) -> nn.BatchNorm2d:
    """BatchNorm2d for dense (B, C, H, W) maps."""
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


__all__ = ["BN_EPS", "BN_MOMENTUM", "sparse_bn", "dense_bn"]
