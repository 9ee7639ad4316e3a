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

from dataclasses import dataclass

import torch
import torch.nn as nn

from detbench.ops import roi_point_pool

from .config import Section, StageConfig, ball_radii, centre_counts, nested_counts
from .pointnet2 import PointLevel, SetAbstraction, SharedMLP
from .two_stage import ProposalConfig, RefineLossWeights, TargetConfig


@dataclass(frozen=True)
class TestSplitConfig(StageConfig):
    """`roi_head.test_split`: the test proposal budget split by range (`select_proposals_by_distance`)."""

    enabled: bool
    distance: float  # m (BEV) from the sensor: proposals within it are near
    near_share: float  # share of the budget that goes to the near proposals

    @classmethod
    def read(cls, s: Section) -> TestSplitConfig:
        return cls(enabled=s.flag("enabled"), distance=s.non_negative("distance", "a distance >= 0 in metres"),
                   near_share=s.fraction("near_share", "a share"))


@dataclass(frozen=True)
class PointRCNNRoIHeadConfig(StageConfig):
    """PointRCNN's `model.roi_head`: RoI point pooling, its PointNet++ and the shared second stage."""

    num_points: int  # pooled points per RoI
    pool_extra_width: float  # m per side the RoI is grown by for pooling
    depth_normalizer: float  # m: depth feature = distance / this - 0.5
    batch_norm: bool  # Linear + BatchNorm + ReLU layers (true) or Linear + ReLU
    scaled_xyz: bool  # also the canonical x, y, z divided by the RoI's half-size
    roi_size: bool  # the RoI's log l, w, h appended to its pooled feature
    detach_features: bool  # the refinement's gradients stop at the backbone's point features
    test_split: TestSplitConfig
    xyz_up: tuple[int, ...]  # widths lifting the pooled point's coordinates to a feature
    sa_npoints: tuple[int | None, ...]  # centres of each set-abstraction level (None: every point)
    sa_radii: tuple[float, ...]  # m, ball radius of each level
    sa_nsamples: tuple[int, ...]  # points per ball of each level
    sa_mlps: tuple[tuple[int, ...], ...]  # layer widths of each level
    fc: tuple[int, ...]  # hidden widths of the confidence and box branches
    dropout: float  # dropout probability in those branches
    proposals: ProposalConfig
    targets: TargetConfig
    loss_weights: RefineLossWeights

    @classmethod
    def read(cls, s: Section) -> PointRCNNRoIHeadConfig:
        return cls(num_points=s.count("num_points"),
                   pool_extra_width=s.non_negative("pool_extra_width", "a number of metres >= 0"),
                   depth_normalizer=s.positive("depth_normalizer", "a positive distance in metres"),
                   batch_norm=s.flag("batch_norm"), scaled_xyz=s.flag("scaled_xyz"), roi_size=s.flag("roi_size"),
                   detach_features=s.flag("detach_features"), test_split=s.section("test_split", TestSplitConfig),
                   xyz_up=s.counts("xyz_up"), sa_npoints=centre_counts(s, "sa_npoints"),
                   sa_radii=ball_radii(s, "sa_radii", depth=1), sa_nsamples=nested_counts(s, "sa_nsamples", 1),
                   sa_mlps=nested_counts(s, "sa_mlps", 2), fc=s.counts("fc", empty=True),
                   dropout=s.fraction("dropout", "a probability"), proposals=s.section("proposals", ProposalConfig),
                   targets=s.section("targets", TargetConfig),
                   loss_weights=s.section("loss_weights", RefineLossWeights))


class PointRCNNRoIHead(nn.Module):
    """RoI point pooling and PointNet++ inside each RoI, set up by `cfg`, on the backbone's point
    features of width `point_channels`."""

    def __init__(self, point_channels: int, cfg: PointRCNNRoIHeadConfig):
        super().__init__()
        self.num_points, self.pool_extra_width = cfg.num_points, cfg.pool_extra_width
        self.depth_normalizer = cfg.depth_normalizer
        self.scaled_xyz, self.roi_size, self.detach_features = cfg.scaled_xyz, cfg.roi_size, cfg.detach_features
        batch_norm, xyz_up = cfg.batch_norm, cfg.xyz_up
        width = int(xyz_up[-1])
        self.xyz_up = SharedMLP([8 if self.scaled_xyz else 5, *xyz_up], batch_norm)
        self.merge_down = SharedMLP([width + point_channels, width], batch_norm)
        self.sa = nn.ModuleList()
        c = width
        for npoint, r, ns, mlp in zip(cfg.sa_npoints, cfg.sa_radii, cfg.sa_nsamples, cfg.sa_mlps):
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
