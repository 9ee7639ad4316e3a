"""PillarNet's encoder: a 2D sparse ResNet-18-style network on pillars, then a dense 16x stage.

Input: a 2D SparseConvTensor of pillar features, sites (batch, y, x) on the pillar grid
(Y, X). Output: `EncoderFeatures`, the densified 8x map and the dense 16x map that the
neck fuses. Layer by layer (c = channels, n = residual blocks per stage):

  stage 1  SubM 3x3 in -> c0, n1 x SparseBasicBlock(c0)            stride 1   (sparse)
  stage 2  SpConv 3x3 s2 c0 -> c1, n2 x SparseBasicBlock(c1)        stride 2   (sparse)
  stage 3  SpConv 3x3 s2 c1 -> c2, n3 x SparseBasicBlock(c2)        stride 4   (sparse)
  stage 4  SpConv 3x3 s2 c2 -> c3, n4 x SparseBasicBlock(c3)        stride 8   (sparse, then densified)
  stage 5  Conv2d 3x3 s2 c3 -> c4, n5 x BasicBlock(c4)              stride 16  (dense)

A basic block is conv-BN-ReLU-conv-BN plus the identity, then ReLU (He et al. 2016);
the sparse blocks use submanifold convolutions, so the active pillars stay the active
pillars within a stage (the blocks of one stage share one rule book). Every convolution
is followed by BatchNorm (models/stages/norm.py: eps=1e-3, momentum=0.01) as in the sparse
detectors' reference code. The grid (Y, X) must divide by 16 (checked by the model via VoxelGrid.check_divisible).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from detbench.sparse import SparseConv2d, SparseConvTensor, SparseModule, SparseSequential, SubMConv2d

from .norm import dense_bn, sparse_bn


class SparseBasicBlock2d(SparseModule):
    """Residual block on a 2D SparseConvTensor: SubM3x3-BN-ReLU-SubM3x3-BN + identity, ReLU.

    (N, C) features in -> (N, C) features out on the same sites. `indice_key` names the
    stage's shared submanifold rule book.
    """

    def __init__(self, channels: int, indice_key: str):
        super().__init__()
        self.conv1 = SubMConv2d(channels, channels, 3, bias=False, indice_key=indice_key)
        self.bn1 = sparse_bn(channels)
        self.conv2 = SubMConv2d(channels, channels, 3, bias=False, indice_key=indice_key)
        self.bn2 = sparse_bn(channels)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        out = self.conv1(x)
        out = out.replace_feature(F.relu(self.bn1(out.features)))
        out = self.conv2(out)
        return out.replace_feature(F.relu(self.bn2(out.features) + x.features))


class BasicBlock2d(nn.Module):
    """Dense residual block: Conv3x3-BN-ReLU-Conv3x3-BN + identity, ReLU; (B, C, H, W) -> same."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn1 = dense_bn(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = dense_bn(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(out)) + x)


class EncoderFeatures(NamedTuple):
    """The encoder's two outputs for the neck."""

    x8: torch.Tensor  # (B, c3, Y/8, X/8) densified sparse stage 4 (inactive cells are 0)
    x16: torch.Tensor  # (B, c4, Y/16, X/16) dense stage 5


class SparseResNet2d(nn.Module):
    """2D sparse ResNet encoder of PillarNet (see the module docstring for the layers).

    Args:
        in_channels: pillar feature width (the pillar encoder's output).
        spatial_shape: (Y, X) pillar grid; both must divide by 16.
        channels: 5 widths (c0..c4) of the stages at strides 1, 2, 4, 8 and 16.
        blocks: 5 residual block counts (>= 0) per stage.
    """

    stride8, stride16 = 8, 16

    def __init__(self, in_channels: int, spatial_shape: Sequence[int], channels: Sequence[int],
                 blocks: Sequence[int]):
        super().__init__()
        channels, blocks = [int(c) for c in channels], [int(b) for b in blocks]
        if len(channels) != 5 or len(blocks) != 5 or min(channels) < 1 or min(blocks) < 0:
            raise ValueError(f"SparseResNet2d needs 5 channel widths >= 1 and 5 block counts >= 0 "
                             f"(strides 1, 2, 4, 8, 16), got channels={channels} blocks={blocks}; "
                             f"fix model.encoder.channels / model.encoder.blocks in the config")
        shape = tuple(int(s) for s in spatial_shape)
        if len(shape) != 2 or shape[0] % 16 or shape[1] % 16:
            raise ValueError(f"SparseResNet2d: the pillar grid (Y, X) = {list(shape)} must be 2D and divide by 16")
        self.input_shape = shape
        c0, c1, c2, c3, c4 = channels
        stage1 = [SubMConv2d(in_channels, c0, 3, bias=False, indice_key="subm1"), sparse_bn(c0), nn.ReLU()]
        stage1 += [SparseBasicBlock2d(c0, "subm1") for _ in range(blocks[0])]
        stages = [SparseSequential(*stage1)]
        for i, (cin, cout) in enumerate(((c0, c1), (c1, c2), (c2, c3)), start=2):
            layers = [SparseConv2d(cin, cout, 3, stride=2, padding=1, bias=False, indice_key=f"spconv{i}"),
                      sparse_bn(cout), nn.ReLU()]
            layers += [SparseBasicBlock2d(cout, f"subm{i}") for _ in range(blocks[i - 1])]
            stages.append(SparseSequential(*layers))
        self.sparse_stages = nn.ModuleList(stages)
        dense = [nn.Conv2d(c3, c4, 3, stride=2, padding=1, bias=False), dense_bn(c4), nn.ReLU()]
        dense += [BasicBlock2d(c4) for _ in range(blocks[4])]
        self.dense_stage = nn.Sequential(*dense)
        self.channels8, self.channels16 = c3, c4

    def output_shapes(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """((Y/8, X/8), (Y/16, X/16)) map sizes in cells."""
        y, x = self.input_shape
        return (y // 8, x // 8), (y // 16, x // 16)

    def forward(self, x: SparseConvTensor) -> EncoderFeatures:
        """Pillars (N, in_channels) on (Y, X) -> EncoderFeatures (x8, x16)."""
        if x.ndim != 2 or tuple(x.spatial_shape) != self.input_shape:
            raise ValueError(f"SparseResNet2d expects a 2D sparse tensor on the grid {list(self.input_shape)} (Y, X), "
                             f"got spatial_shape {x.spatial_shape}")
        for stage in self.sparse_stages:
            x = stage(x)
        x8 = x.dense()
        return EncoderFeatures(x8, self.dense_stage(x8))
