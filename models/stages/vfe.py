"""Voxel feature encoders: points of a batch -> one feature vector per occupied voxel."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from detbench.ops.voxelize import dynamic_voxelize, scatter_mean, unique_voxels
from detbench.sparse import SparseConvTensor

from .config import Section, StageConfig
from .grid import VoxelGrid

XY_MODES = ("offset", "absolute")


@dataclass(frozen=True)
class VFEConfig(StageConfig):
    """`model.vfe`: how the voxel features give a point's ground position (x, y)."""

    xy: str  # "offset": from the voxel's centre (float16-safe); "absolute": in the ego frame

    @classmethod
    def read(cls, s: Section) -> VFEConfig:
        return cls(xy=s.choice("xy", XY_MODES))


class MeanVFE(nn.Module):
    """SECOND's mean voxel feature: the mean (x, y, z, intensity) of the points in a voxel.

    With `xy="offset"`, x and y are the mean's offsets from the voxel's centre, within half a voxel
    of zero; z (the height above the road, a few metres) and the intensity stay as they are. The
    sparse convolution that takes these features sees where a voxel lies only relative to its
    neighbours, so absolute x and y would tell it the range, and nothing else it cannot see in the
    points; but under float16 autocast an absolute x of 64-128 m is rounded to 0.0625 m and beyond
    128 m to 0.125 m, coarser than the 0.1 m voxel, and the point's place in its voxel is lost. An
    offset keeps it to about a micrometre. (docs/architecture.md, "Voxel features", has the
    argument.) `xy="absolute"` is the ego-frame mean, what checkpoints of earlier versions trained on.

    Dynamic voxelization (every point of a voxel takes part; no cap of points per voxel
    and no cap of voxels), so the result does not depend on point order.
    Input: batch points (P, 5) [batch_index, x, y, z, intensity]. Output: a SparseConvTensor
    with (V, 4) features and (V, 4) int32 (batch, z, y, x) sites on `grid.spatial_shape`.
    """

    def __init__(self, grid: VoxelGrid, cfg: VFEConfig, num_point_features: int = 4):
        super().__init__()
        self.grid = grid
        self.xy = cfg.xy
        self.out_channels = num_point_features

    def forward(self, points: torch.Tensor, batch_size: int) -> SparseConvTensor:
        coords = dynamic_voxelize(points[:, 1:4].contiguous(), self.grid.voxel_size, self.grid.point_cloud_range)
        bcoords = torch.cat([points[:, :1].to(torch.int32), coords], dim=1)
        bcoords[(coords < 0).any(dim=1)] = -1
        sites, inverse = unique_voxels(bcoords)
        feats = scatter_mean(points[:, 1:1 + self.out_channels], inverse, sites.shape[0])
        if self.xy == "offset":
            feats = torch.cat([self.centre_offsets(feats[:, :2], sites), feats[:, 2:]], dim=1)
        return SparseConvTensor(feats, sites, list(self.grid.spatial_shape), batch_size)

    def centre_offsets(self, xy: torch.Tensor, sites: torch.Tensor) -> torch.Tensor:
        """(V, 2) x, y minus the centres of the voxels `sites` (V, 4) (batch, z, y, x), computed in float64."""
        lo = torch.tensor(self.grid.point_cloud_range[:2], dtype=torch.float64, device=xy.device)
        size = torch.tensor(self.grid.voxel_size[:2], dtype=torch.float64, device=xy.device)
        centre = lo + (sites[:, [3, 2]].to(torch.float64) + 0.5) * size
        return (xy.to(torch.float64) - centre).to(xy.dtype)
