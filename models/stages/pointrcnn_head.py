"""PointRCNN's RoI feature step: the points in each enlarged RoI, canonical, through PointNet++.

  roi_point_pool: the points inside each RoI grown by `pool_extra_width` metres per side,
      a fixed number per RoI, in the RoI's canonical frame, carrying (segmentation score,
      normalised depth) and the backbone's point features
  xyz_up: canonical x, y, z + score + depth (+ with `scaled_xyz` the canonical x, y, z
      divided by the RoI's half-length, half-width and half-height) -> a feature of the
      backbone's width
  merge_down: [that, the backbone feature] -> one feature per point
  SetAbstraction levels inside each RoI (each RoI is one "frame"), the last grouping all
  -> one vector per RoI (B, R, C) (+ with `roi_size` the log of the RoI's l, w, h: C + 3)

As the paper: canonical coordinates make the refinement independent of where the RoI is;
depth (distance from the sensor) is given back explicitly because the canonical transform
removes it, and it tells how sparse the RoI's points are; the segmentation score tells
which pooled points are the vehicle. The canonical coordinates alone are the same for every
RoI on one vehicle that holds the same points, whatever its size; the refinement's size target
and its IoU-guided confidence depend on that size, so `scaled_xyz` and `roi_size` give it.
`batch_norm` False uses plain Linear + ReLU layers (the RoI batch is small and its statistics
change with the proposals); `detach_features` stops the refinement's gradients at the
backbone's point features (the first stage then learns from its own loss only).
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
                 sa_mlps: Sequence[Sequence[int]] = ((128, 128, 128), (128, 128, 256), (256, 256, 512)),
                 *, batch_norm: bool = True, scaled_xyz: bool = False, roi_size: bool = False,
                 detach_features: bool = False):
        super().__init__()
        self.num_points, self.pool_extra_width = int(num_points), float(pool_extra_width)
        self.depth_normalizer = float(depth_normalizer)
        self.scaled_xyz, self.roi_size, self.detach_features = bool(scaled_xyz), bool(roi_size), bool(detach_features)
        width = int(xyz_up[-1])
        self.xyz_up = SharedMLP([8 if self.scaled_xyz else 5, *xyz_up], batch_norm)
        self.merge_down = SharedMLP([width + point_channels, width], batch_norm)
        self.sa = nn.ModuleList()
        c = width
        for npoint, r, ns, mlp in zip(sa_npoints, sa_radii, sa_nsamples, sa_mlps):
            layer = SetAbstraction(npoint, [r], [ns], [mlp], c, batch_norm)
            self.sa.append(layer)
            c = layer.out_channels
        self.out_channels = c + (3 if self.roi_size else 0)

    def forward(self, xyz: torch.Tensor, point_features: torch.Tensor, seg_scores: torch.Tensor, rois: torch.Tensor,
                points_per_frame: int) -> torch.Tensor:
        """xyz (B * N, 3), point_features (B * N, C), seg_scores (B * N,), rois (B, R, 7) -> (B, R, out)."""
        b, r = rois.shape[:2]
        if b * r == 0:  # no RoI slot (e.g. a zero proposal budget): nothing to pool
            return point_features.new_zeros(b, r, self.out_channels)
        depth = xyz.norm(dim=1) / self.depth_normalizer - 0.5
        extra = torch.stack([seg_scores.detach(), depth.detach()], dim=1)
        if self.detach_features:
            point_features = point_features.detach()
        flat = rois.detach().reshape(-1, 7)
        pooled = roi_point_pool(xyz.detach(), flat, self.num_points, self.pool_extra_width,
                                features=torch.cat([extra, point_features], dim=1),
                                point_counts=torch.full((b,), points_per_frame, dtype=torch.int64),
                                roi_counts=torch.full((b,), r, dtype=torch.int64))
        p = pooled.points  # (B * R, S, 3 + 2 + C), zeros for empty RoIs
        inp = p[..., :5]
        if self.scaled_xyz:
            half = (0.5 * flat[:, 3:6]).clamp(min=0.05)[:, None, :]
            inp = torch.cat([inp, p[..., :3] / half], dim=-1)
        local = self.xyz_up(inp)
        merged = self.merge_down(torch.cat([local, p[..., 5:]], dim=-1))
        s = self.num_points
        level = PointLevel(p[..., :3].reshape(-1, 3).contiguous(), merged.reshape(b * r * s, -1), s)
        for sa in self.sa:
            level = sa(level)
        out = level.features.reshape(b, r, -1)
        if self.roi_size:
            out = torch.cat([out, rois.detach()[..., 3:6].clamp(min=0.05).log()], dim=-1)
        return out
