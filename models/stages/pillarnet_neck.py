"""PillarNet's neck: spatial-semantic fusion of the 8x and 16x encoder maps into one BEV map at 8x.

The 16x map carries semantics (a large receptive field), the 8x map spatial detail. The
neck refines the 16x map with 3x3 convolutions, up-samples it to 8x with a transposed
convolution, concatenates it with the (densified) 8x map and fuses the two with 3x3
convolutions:

  x16 (B, c16, H/2, W/2) --n_sem x Conv3x3--> (B, s, H/2, W/2) --ConvT 2x2 s2--> (B, u, H, W)
  x8  (B, c8, H, W) ---------------------------------------------------------------+
  cat (B, c8 + u, H, W) --Conv3x3--> (B, o, H, W) --n_fuse x Conv3x3--> (B, o, H, W)

Every convolution is followed by BatchNorm2d (`norm.dense_bn`: eps=1e-3, momentum=0.01) and ReLU.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from .config import Section, StageConfig
from .norm import dense_bn


@dataclass(frozen=True)
class NeckConfig(StageConfig):
    """PillarNet's `model.neck` (see the module docstring for the layers)."""

    semantic_channels: int  # width of the 3x3 convolutions on the 16x map
    semantic_blocks: int  # how many of them (>= 0)
    up_channels: int  # width of the 16x map up-sampled to 8x
    out_channels: int  # width of the fused 8x BEV map
    fuse_blocks: int  # 3x3 convolutions after the first fusing one (>= 0)

    @classmethod
    def read(cls, s: Section) -> NeckConfig:
        return cls(semantic_channels=s.count("semantic_channels"), semantic_blocks=s.count("semantic_blocks", 0),
                   up_channels=s.count("up_channels"), out_channels=s.count("out_channels"),
                   fuse_blocks=s.count("fuse_blocks", 0))


def _cbr(cin: int, cout: int) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, padding=1, bias=False), dense_bn(cout), nn.ReLU()]


class SpatialSemanticNeck(nn.Module):
    """Fuse x8 (B, c8, H, W) and x16 (B, c16, H/2, W/2) into (B, out_channels, H, W).

    Args:
        in_channels8, in_channels16: widths of the encoder's 8x and 16x maps.
        cfg: widths and block counts (`NeckConfig`).
    """

    def __init__(self, in_channels8: int, in_channels16: int, cfg: NeckConfig):
        super().__init__()
        semantic_channels, semantic_blocks, up_channels = cfg.semantic_channels, cfg.semantic_blocks, cfg.up_channels
        out_channels, fuse_blocks = cfg.out_channels, cfg.fuse_blocks
        widths = dict(semantic_channels=semantic_channels, up_channels=up_channels, out_channels=out_channels)
        if min(widths.values()) < 1 or semantic_blocks < 0 or fuse_blocks < 0:
            raise ValueError(f"SpatialSemanticNeck: widths must be >= 1 and block counts >= 0, got {widths}, "
                             f"semantic_blocks={semantic_blocks}, fuse_blocks={fuse_blocks} (model.neck in the config)")
        sem: list[nn.Module] = []
        cin = in_channels16
        for _ in range(semantic_blocks):
            sem += _cbr(cin, semantic_channels)
            cin = semantic_channels
        self.semantic = nn.Sequential(*sem)
        self.up = nn.Sequential(nn.ConvTranspose2d(cin, up_channels, 2, stride=2, bias=False), dense_bn(up_channels),
                                nn.ReLU())
        fuse = _cbr(in_channels8 + up_channels, out_channels)
        for _ in range(fuse_blocks):
            fuse += _cbr(out_channels, out_channels)
        self.fuse = nn.Sequential(*fuse)
        self.out_channels = int(out_channels)

    def forward(self, x8: torch.Tensor, x16: torch.Tensor) -> torch.Tensor:
        """(B, c8, H, W), (B, c16, H/2, W/2) -> (B, out_channels, H, W)."""
        up = self.up(self.semantic(x16))
        if up.shape[-2:] != x8.shape[-2:]:
            raise ValueError(f"SpatialSemanticNeck: the up-sampled 16x map is {tuple(up.shape[-2:])} but the 8x map "
                             f"{tuple(x8.shape[-2:])}; the pillar grid must divide by 16")
        return self.fuse(torch.cat([x8, up], dim=1))
