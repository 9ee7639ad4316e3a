"""Dynamic pillar feature encoding (PillarNet; PointPillars' features without a point cap).

Every point in the range takes part (dynamic pillars: no cap of points per pillar, no cap
of pillars), so the result does not depend on the order of the points. Per point, 9
features (metres):

  x, y, z, intensity,
  x - pillar centre x, y - pillar centre y,
  x - mean x, y - mean y, z - mean z     (mean of the points of the pillar)

then a point-wise MLP (Linear + BatchNorm1d + ReLU per layer) and a channel-wise max over
the points of each pillar. With more than one layer, every layer but the last sees its
input concatenated with its pillar's max of the previous layer (PointPillars' PFN layers),
so later layers know the pillar's context.

Input: batch points (P, 5) [batch_index, x, y, z, intensity]. Output: a 2D SparseConvTensor,
sites (batch, y, x) int32 on the grid (Y, X), features (V, C) with C = the last MLP width.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from detbench.ops.voxelize import dynamic_voxelize, scatter_max, scatter_mean, unique_voxels
from detbench.sparse import SparseConvTensor

from .config import Section, StageConfig
from .grid import VoxelGrid
from .norm import sparse_bn

NUM_POINT_FEATURES = 9


@dataclass(frozen=True)
class PillarEncoderConfig(StageConfig):
    """PillarNet's `model.encoder`: the pillar MLP and the sparse ResNet after it (sparse_resnet2d)."""

    pillar_channels: tuple[int, ...]  # point-wise MLP widths before the max per pillar
    channels: tuple[int, int, int, int, int]  # ResNet stages at strides 1, 2, 4, 8 (sparse) and 16 (dense)
    blocks: tuple[int, int, int, int, int]  # residual blocks per stage

    @classmethod
    def read(cls, s: Section) -> PillarEncoderConfig:
        return cls(pillar_channels=s.counts("pillar_channels"), channels=s.counts("channels", length=5),
                   blocks=s.counts("blocks", low=0, length=5))


class DynamicPillarEncoder(nn.Module):
    """Points -> one feature vector per occupied pillar (see the module docstring).

    Args:
        grid: the pillar grid; its z voxel must span the whole z range (one voxel high).
        mlp_channels: widths of the point-wise layers, e.g. (32,) or (32, 64).
        num_point_features: input columns per point after the batch index (x, y, z, intensity).
    """

    def __init__(self, grid: VoxelGrid, mlp_channels: Sequence[int], num_point_features: int = 4):
        super().__init__()
        if grid.grid_size[2] != 1:
            z0, z1 = grid.point_cloud_range[2], grid.point_cloud_range[5]
            raise ValueError(f"DynamicPillarEncoder: a pillar spans the whole z range, so voxel_size z must be "
                             f"{z1 - z0:g} m (z {z0:g}..{z1:g} m), got {grid.voxel_size[2]:g} m; "
                             f"set model.voxel_size to [vx, vy, {z1 - z0:g}] in the config")
        mlp_channels = [int(c) for c in mlp_channels]
        if not mlp_channels or min(mlp_channels) < 1:
            raise ValueError(f"DynamicPillarEncoder: mlp_channels must list >= 1 positive widths, got {mlp_channels} "
                             f"(model.encoder.pillar_channels in the config)")
        if num_point_features != 4:
            raise ValueError(f"DynamicPillarEncoder expects x, y, z, intensity per point (4 features), "
                             f"got num_point_features={num_point_features}")
        self.grid = grid
        self.num_point_features = int(num_point_features)
        self.linears = nn.ModuleList()
        self.norms = nn.ModuleList()
        cin = NUM_POINT_FEATURES
        for i, c in enumerate(mlp_channels):
            last = i == len(mlp_channels) - 1
            cout = c if last else c // 2  # the concatenated pillar max doubles it back to c
            if cout < 1:
                raise ValueError(f"DynamicPillarEncoder: inner MLP widths must be >= 2 (they are halved before the "
                                 f"pillar max is concatenated), got {mlp_channels}")
            self.linears.append(nn.Linear(cin, cout, bias=False))
            self.norms.append(sparse_bn(cout))
            cin = 2 * cout
        self.out_channels = mlp_channels[-1]
        self.spatial_shape = (grid.spatial_shape[1], grid.spatial_shape[2])  # (Y, X)

    def point_features(self, points: torch.Tensor, inverse: torch.Tensor, sites: torch.Tensor) -> torch.Tensor:
        """(N, 9) per-point features of in-range points (rows with inverse >= 0) -> see module docstring.

        points: (N, 5) [batch, x, y, z, intensity]; inverse: (N,) pillar row of each point;
        sites: (V, 3) (batch, y, x) pillars.
        """
        xyz = points[:, 1:4]
        vx, vy = self.grid.voxel_size[:2]
        x0, y0 = self.grid.point_cloud_range[:2]
        site = sites[inverse].to(points.dtype)  # (N, 3)
        centre_x = x0 + (site[:, 2] + 0.5) * vx
        centre_y = y0 + (site[:, 1] + 0.5) * vy
        mean = scatter_mean(xyz, inverse, sites.shape[0])[inverse]  # (N, 3)
        return torch.cat([xyz, points[:, 4:5], (xyz[:, 0] - centre_x)[:, None], (xyz[:, 1] - centre_y)[:, None],
                          xyz - mean], dim=1)

    def forward(self, points: torch.Tensor, batch_size: int) -> SparseConvTensor:
        """points (P, 5) [batch_index, x, y, z, intensity] (m) -> 2D SparseConvTensor on (Y, X)."""
        if points.dim() != 2 or points.shape[1] != 1 + self.num_point_features:
            raise ValueError(f"DynamicPillarEncoder: points must be (P, 5) [batch_index, x, y, z, intensity], "
                             f"got shape {tuple(points.shape)}")
        points = points.float()
        coords = dynamic_voxelize(points[:, 1:4].contiguous(), self.grid.voxel_size, self.grid.point_cloud_range)
        bcoords = torch.stack([points[:, 0].to(torch.int32), coords[:, 1], coords[:, 2]], dim=1)  # (b, y, x)
        inside = (coords >= 0).all(dim=1)
        points, bcoords = points[inside], bcoords[inside]
        sites, inverse = unique_voxels(bcoords)
        if sites.shape[0] == 0:
            feats = points.new_zeros((0, self.out_channels))
            return SparseConvTensor(feats, sites.reshape(0, 3), list(self.spatial_shape), batch_size)
        x = self.point_features(points, inverse, sites)
        num = sites.shape[0]
        for i, (linear, norm) in enumerate(zip(self.linears, self.norms)):
            x = F.relu(norm(linear(x)))
            pooled = scatter_max(x, inverse, num)
            if i < len(self.linears) - 1:
                x = torch.cat([x, pooled[inverse]], dim=1)
        return SparseConvTensor(pooled, sites, list(self.spatial_shape), batch_size)
