"""SECOND's sparse 3D backbone: submanifold blocks and three stride-2 sparse convolutions.

Input: a SparseConvTensor of voxel features on the full grid (Z, Y, X). Output: a
SparseConvTensor at 8x lower resolution in y and x (and ~16x in z), ready for height
compression to a BEV map. Layer by layer (c = channels):

  conv_input  SubM 3x3x3   in -> c0                   stride 1
  stage 1     SubM x n1    c0 -> c0                   stride 1
  stage 2     SpConv s2 c0 -> c1, SubM x (n2-1)        stride 2
  stage 3     SpConv s2 c1 -> c2, SubM x (n3-1)        stride 4
  stage 4     SpConv s2 c2 -> c3 (z padding 0), SubM x (n4-1)   stride 8
  conv_out    SpConv (3,1,1) stride (2,1,1) c3 -> out  (squeezes z)

Each convolution is followed by BatchNorm1d (`norm.sparse_bn`: eps=1e-3, momentum=0.01) and
ReLU, as in the reference implementation. Submanifold layers of one stage share a rule book (indice_key).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch.nn as nn

from detbench.sparse import SparseConv3d, SparseConvTensor, SparseSequential, SubMConv3d, conv_output_shape

from .config import Section, StageConfig
from .norm import sparse_bn


@dataclass(frozen=True)
class SparseBackboneConfig(StageConfig):
    """`model.backbone3d`: SECOND's sparse backbone, four stages."""

    channels: tuple[int, int, int, int]  # widths of the stages at strides 1, 2, 4, 8
    blocks: tuple[int, int, int, int]  # convolutions per stage (the first of stages 2-4 is the strided one)
    out_channels: int  # width of the z-squeezing output convolution

    @classmethod
    def read(cls, s: Section) -> SparseBackboneConfig:
        return cls(channels=s.counts("channels", length=4), blocks=s.counts("blocks", length=4),
                   out_channels=s.count("out_channels"))


def _conv_bn_relu(conv: nn.Module, channels: int) -> SparseSequential:
    return SparseSequential(conv, sparse_bn(channels), nn.ReLU())


class SparseBackbone8x(nn.Module):
    """SECOND-style sparse backbone. `spatial_shape` is the input grid (Z, Y, X)."""

    def __init__(self, in_channels: int, spatial_shape: Sequence[int], cfg: SparseBackboneConfig):
        super().__init__()
        channels, blocks, out_channels = cfg.channels, cfg.blocks, cfg.out_channels
        if len(channels) != 4 or len(blocks) != 4 or min(blocks) < 1:
            raise ValueError(f"SparseBackbone8x needs 4 channel widths and 4 block counts >= 1, "
                             f"got channels={list(channels)} blocks={list(blocks)}")
        c0, c1, c2, c3 = channels
        self.conv_input = _conv_bn_relu(SubMConv3d(in_channels, c0, 3, bias=False, indice_key="subm1"), c0)
        stages = []
        cin = c0
        for i, (cout, n) in enumerate(zip(channels, blocks)):
            layers = []
            if i == 0:
                layers.append(_conv_bn_relu(SubMConv3d(cin, cout, 3, bias=False, indice_key="subm1"), cout))
            else:
                padding = (0, 1, 1) if i == 3 else 1
                layers.append(_conv_bn_relu(SparseConv3d(cin, cout, 3, stride=2, padding=padding, bias=False,
                                                         indice_key=f"spconv{i + 1}"), cout))
            for _ in range(n - 1):
                layers.append(_conv_bn_relu(SubMConv3d(cout, cout, 3, bias=False, indice_key=f"subm{i + 1}"), cout))
            stages.append(SparseSequential(*layers))
            cin = cout
        self.stages = nn.ModuleList(stages)
        self.conv_out = _conv_bn_relu(SparseConv3d(c3, out_channels, (3, 1, 1), stride=(2, 1, 1), padding=0,
                                                   bias=False, indice_key="spconv_down2"), out_channels)
        self.out_channels = out_channels
        self.input_shape = tuple(int(s) for s in spatial_shape)
        shape = self.input_shape
        try:
            for i in range(1, 4):
                shape = conv_output_shape(shape, 3, 2, (0, 1, 1) if i == 3 else 1)
            shape = conv_output_shape(shape, (3, 1, 1), (2, 1, 1), 0)
        except ValueError as e:
            raise ValueError(f"SparseBackbone8x: the input grid {list(self.input_shape)} (Z, Y, X) is too small for "
                             f"three stride-2 convolutions and the z squeeze ({e}); use at least 25 z voxels "
                             f"(a smaller z voxel or a taller z range)") from None
        self.output_shape = tuple(int(s) for s in shape)  # (D, Y/8, X/8)
        self.bev_stride = 8

    @property
    def bev_channels(self) -> int:
        """Channels of the BEV map after height compression: out_channels x output depth."""
        return self.out_channels * self.output_shape[0]

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        x = self.conv_input(x)
        for stage in self.stages:
            x = stage(x)
        return self.conv_out(x)
