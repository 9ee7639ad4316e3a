"""PointRCNN's RoI feature step: the points in each enlarged RoI, canonical, through PointNet++.

  roi_point_pool: the points inside each RoI grown by `pool_extra_width` metres per side,
      a fixed number per RoI, in the RoI's canonical frame, carrying (segmentation score,
      normalised depth) and the backbone's point features
  xyz_up: canonical x, y, z + score + depth -> a feature of the backbone's width
  merge_down: [that, the backbone feature] -> one feature per point
  SetAbstraction levels inside each RoI (each RoI is one "frame"), the last grouping all
  -> one vector per RoI (B, R, C)

As the paper: canonical coordinates make the refinement independent of where the RoI is;
depth (distance from the sensor) is given back explicitly because the canonical transform
removes it, and it tells how sparse the RoI's points are; the segmentation score tells
which pooled points are the vehicle.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn as nn

from detbench.ops import roi_point_pool

from .pointnet2 import PointLevel, SetAbstraction, SharedMLP


class PointRCNNRoIHead(nn.Module):
    def __init__(self, point_channels: int, num_points: int = 512, pool_extra_width: float = 1.0,
                 depth_normalizer: float = 70.0, xyz_up: Sequence[int] = (128, 128),
                 sa_npoints: Sequence[int | None] = (128, 32, None), sa_radii: Sequence[float] = (0.2, 0.4, 100.0),
                 sa_nsamples: Sequence[int] = (16, 16, 16),
                 sa_mlps: Sequence[Sequence[int]] = ((128, 128, 128), (128, 128, 256), (256, 256, 512))):
        super().__init__()
        self.num_points, self.pool_extra_width = int(num_points), float(pool_extra_width)
        self.depth_normalizer = float(depth_normalizer)
        width = int(xyz_up[-1])
        self.xyz_up = SharedMLP([5, *xyz_up])
        self.merge_down = SharedMLP([width + point_channels, width])
        self.sa = nn.ModuleList()
        c = width
        for npoint, r, ns, mlp in zip(sa_npoints, sa_radii, sa_nsamples, sa_mlps):
            layer = SetAbstraction(npoint, [r], [ns], [mlp], c)
            self.sa.append(layer)
            c = layer.out_channels
        self.out_channels = c

    def forward(self, xyz: torch.Tensor, point_features: torch.Tensor, seg_scores: torch.Tensor, rois: torch.Tensor,
                points_per_frame: int) -> torch.Tensor:
        """xyz (B * N, 3), point_features (B * N, C), seg_scores (B * N,), rois (B, R, 7) -> (B, R, out)."""
        b, r = rois.shape[:2]
        if b * r == 0:  # no RoI slot (e.g. a zero proposal budget): nothing to pool
            return point_features.new_zeros(b, r, self.out_channels)
        depth = xyz.norm(dim=1) / self.depth_normalizer - 0.5
        extra = torch.stack([seg_scores.detach(), depth.detach()], dim=1)
        pooled = roi_point_pool(xyz.detach(), rois.detach().reshape(-1, 7), self.num_points, self.pool_extra_width,
                                features=torch.cat([extra, point_features], dim=1),
                                point_counts=torch.full((b,), points_per_frame, dtype=torch.int64),
                                roi_counts=torch.full((b,), r, dtype=torch.int64))
        p = pooled.points  # (B * R, S, 3 + 2 + C), zeros for empty RoIs
        local = self.xyz_up(p[..., :5])
        merged = self.merge_down(torch.cat([local, p[..., 5:]], dim=-1))
        s = self.num_points
        level = PointLevel(p[..., :3].reshape(-1, 3).contiguous(), merged.reshape(b * r * s, -1), s)
        for sa in self.sa:
            level = sa(level)
        return level.features.reshape(b, r, -1)
