"""PillarNet (Shi, Li and Ma, "PillarNet: Real-Time and High-Performance Pillar-based 3D Object
Detection", 2022).

The model is the composition of shared stages, read top to bottom:

  points (P, 5) --DynamicPillarEncoder--> sparse pillars (Y, X)
  --SparseResNet2d--> densified 8x map + dense 16x map
  --SpatialSemanticNeck--> BEV (B, C, Y/8, X/8)
  --CenterHead--> heat map, offset, z, log size, sin/cos heading, IoU maps --> loss | Detections

Configuration: configs/pillarnet.yaml (`model:` section), read by `PillarNetConfig`. `voxel_size`
is the pillar size (its z is the whole z range); the pillar grid must divide by 16 (the dense
stage's stride).
A frame without a single point in the range gets no detections (there is nothing to see).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections

from .stages import (
    CenterHead, CenterHeadConfig, CenterHeadOutput, CenterPostConfig, DynamicPillarEncoder, NeckConfig,
    PillarEncoderConfig, Section, SpatialSemanticNeck, SparseResNet2d, StageConfig, VoxelGrid,
)

CONFIG_FILE = "configs/pillarnet.yaml"


@dataclass(frozen=True)
class PillarNetConfig(StageConfig):
    """PillarNet's `model:` section (configs/pillarnet.yaml)."""

    grid: VoxelGrid  # point_cloud_range and voxel_size (the pillar size; z = the whole z range)
    encoder: PillarEncoderConfig
    neck: NeckConfig
    head: CenterHeadConfig
    post: CenterPostConfig

    @classmethod
    def read(cls, s: Section) -> PillarNetConfig:
        s.skip("name")  # the registry's key, configs/<name>.yaml
        return cls(grid=VoxelGrid.read(s), encoder=s.section("encoder", PillarEncoderConfig),
                   neck=s.section("neck", NeckConfig), head=s.section("head", CenterHeadConfig),
                   post=s.section("post", CenterPostConfig))


class PillarNetOutput(NamedTuple):
    head: CenterHeadOutput  # raw head maps (B, *, Y/8, X/8)
    pillars_per_frame: torch.Tensor  # (B,) int64 occupied pillars of each frame


class PillarNet(nn.Module):
    """PillarNet for one class (Vehicle). `cfg` is the `model:` section of configs/pillarnet.yaml.

    Contract (`detbench.train.detector.Detector`): `forward(batch) -> PillarNetOutput`,
    `loss(outputs, batch) -> (total, parts)`, `predict(outputs, batch) -> list[Detections]`
    (one per frame, label 0 = Vehicle), `prepare_config` (nothing to derive), `STAGES`.
    Stages: `vfe` (pillar encoder), `backbone` (sparse ResNet), `neck`, `head`.
    """

    CONFIG = PillarNetConfig  # reads and checks the `model:` section
    # top-level children per stage, for tools/benchmark.py's latency split
    STAGES = {"voxelize": ["vfe"], "backbone": ["backbone"], "neck": ["neck"], "head": ["head"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = c = PillarNetConfig.from_config(cfg, source=CONFIG_FILE)
        self.grid = c.grid
        self.grid.check_divisible(SparseResNet2d.stride16, f"PillarNet ({CONFIG_FILE}: model.voxel_size / "
                                                           f"point_cloud_range)")
        self.vfe = DynamicPillarEncoder(self.grid, c.encoder.pillar_channels)
        self.backbone = SparseResNet2d(self.vfe.out_channels, self.vfe.spatial_shape, c.encoder.channels,
                                       c.encoder.blocks)
        self.neck = SpatialSemanticNeck(self.backbone.channels8, self.backbone.channels16, c.neck)
        self.head = CenterHead(self.neck.out_channels, self.grid, SparseResNet2d.stride8, c.head, c.post)

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """A copy of `model_cfg`: PillarNet derives nothing from the training boxes (N, 7)."""
        return copy.deepcopy(model_cfg)

    def forward(self, batch: Batch) -> PillarNetOutput:
        """Batch (points (P, 5) [batch_index, x, y, z, intensity]) -> head maps at 8x and pillars per frame."""
        pillars = self.vfe(batch.points, batch.batch_size)
        feats = self.backbone(pillars)
        bev = self.neck(feats.x8, feats.x16)
        counts = torch.bincount(pillars.indices[:, 0].long(), minlength=batch.batch_size)
        return PillarNetOutput(self.head(bev), counts)

    def loss(self, out: PillarNetOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        """(total scalar, parts {loss_hm, loss_reg, loss_od_iou, loss_iou, mean_iou, num_pos}) against
        batch.gt_boxes (B, M, 7) / gt_mask (B, M); see CenterHead.loss."""
        return self.head.loss(out.head, batch.gt_boxes, batch.gt_mask)

    def predict(self, out: PillarNetOutput, batch: Batch) -> list[Detections]:
        """One `Detections` per frame (boxes (K, 7), scores (K,) in [0, 1], labels 0); none for a frame
        without points in the range."""
        return self.head.predict(out.head, valid=out.pillars_per_frame > 0)
