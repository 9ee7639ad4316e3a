"""Voxel feature encoders: points of a batch -> one feature vector per occupied voxel."""
from __future__ import annotations

import torch
import torch.nn as nn

from detbench.ops.voxelize import dynamic_voxelize, scatter_mean, unique_voxels
from detbench.sparse import SparseConvTensor

from .grid import VoxelGrid


class MeanVFE(nn.Module):
    """SECOND's mean voxel feature: the mean (x, y, z, intensity) of the points in a voxel.

    Dynamic voxelization (every point of a voxel takes part; no cap of points per voxel
    and no cap of voxels), so the result does not depend on point order.
    Input: batch points (P, 5) [batch_index, x, y, z, intensity]. Output: a SparseConvTensor
    with (V, 4) features and (V, 4) int32 (batch, z, y, x) sites on `grid.spatial_shape`.
    """

    def __init__(self, grid: VoxelGrid, num_point_features: int = 4):
        super().__init__()
        self.grid = grid
        self.out_channels = num_point_features

    def forward(self, points: torch.Tensor, batch_size: int) -> SparseConvTensor:
        coords = dynamic_voxelize(points[:, 1:4].contiguous(), self.grid.voxel_size, self.grid.point_cloud_range)
        bcoords = torch.cat([points[:, :1].to(torch.int32), coords], dim=1)
        bcoords[(coords < 0).any(dim=1)] = -1
        sites, inverse = unique_voxels(bcoords)
        feats = scatter_mean(points[:, 1:1 + self.out_channels], inverse, sites.shape[0])
        return SparseConvTensor(feats, sites, list(self.grid.spatial_shape), batch_size)
