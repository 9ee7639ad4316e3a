"""The 2D BEV backbone of SECOND (and of PointPillars-style detectors).

Blocks of 3x3 convolutions at decreasing resolution; each block's output is brought back to
a common resolution by a transposed convolution and the results are concatenated. With
`layer_strides=(1, 2)` and `upsample_strides=(1, 2)` the output has the input's resolution
and `sum(num_upsample_filters)` channels. Every convolution is followed by BatchNorm2d
(`norm.dense_bn`) and ReLU.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from .config import Section, StageConfig
from .norm import dense_bn


@dataclass(frozen=True)
class BEVBackboneConfig(StageConfig):
    """`model.backbone2d`: one entry per block, from the finest resolution to the coarsest."""

    layer_nums: tuple[int, ...]  # 3x3 convolutions per block after its first (strided) one
    layer_strides: tuple[int, ...]  # stride of each block's first convolution
    num_filters: tuple[int, ...]  # channels of each block
    upsample_strides: tuple[int, ...]  # up-sampling back to the input resolution (the cumulative stride)
    num_upsample_filters: tuple[int, ...]  # channels of each block's up-sampled output

    @classmethod
    def read(cls, s: Section) -> BEVBackboneConfig:
        return cls(layer_nums=s.counts("layer_nums", low=0), layer_strides=s.counts("layer_strides"),
                   num_filters=s.counts("num_filters"), upsample_strides=s.counts("upsample_strides"),
                   num_upsample_filters=s.counts("num_upsample_filters"))


def _cbr(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
            dense_bn(cout), nn.ReLU()]


class BEVBackbone(nn.Module):
    def __init__(self, in_channels: int, cfg: BEVBackboneConfig):
        super().__init__()
        layer_nums, layer_strides, num_filters = cfg.layer_nums, cfg.layer_strides, cfg.num_filters
        upsample_strides, num_upsample_filters = cfg.upsample_strides, cfg.num_upsample_filters
        n = len(layer_nums)
        if not (len(layer_strides) == len(num_filters) == len(upsample_strides) == len(num_upsample_filters) == n):
            raise ValueError("BEVBackbone: layer_nums, layer_strides, num_filters, upsample_strides and "
                             "num_upsample_filters must have the same length")
        total = 1
        for s, u in zip(layer_strides, upsample_strides):
            total *= s
            if total != u:
                raise ValueError(f"BEVBackbone: upsample stride {u} must equal the block's cumulative stride "
                                 f"{total} so all blocks return to the input resolution")
        self.blocks = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        cin = in_channels
        for nl, s, nf, us, nuf in zip(layer_nums, layer_strides, num_filters, upsample_strides, num_upsample_filters):
            layers = _cbr(cin, nf, s)
            for _ in range(nl):
                layers += _cbr(nf, nf)
            self.blocks.append(nn.Sequential(*layers))
            if us == 1:
                de = nn.Conv2d(nf, nuf, 1, bias=False)
            else:
                de = nn.ConvTranspose2d(nf, nuf, us, stride=us, bias=False)
            self.deblocks.append(nn.Sequential(de, dense_bn(nuf), nn.ReLU()))
            cin = nf
        self.out_channels = int(sum(num_upsample_filters))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        return torch.cat(ups, dim=1) if len(ups) > 1 else ups[0]
