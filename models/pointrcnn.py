"""PointRCNN (Shi, Wang and Li, "PointRCNN: 3D Object Proposal Generation and Detection from
Point Cloud", CVPR 2019): the point-based two-stage detector, in plain torch on detbench.ops' point ops.

The model is the composition of shared stages, read top to bottom:

  points --sample_frame_points (optionally thinned to one point per voxel cell: sampling.voxel_size; then a
     fixed budget per frame, far points first, shuffled: sampling.shuffle)--> (B * N, 4)
  --PointNet2MSG (set abstraction down, feature propagation up)--> a feature per point
  --PointHead--> foreground logit + a box per point (residual coding on the mean vehicle size,
     or the paper's bin-based coding: point_head.box_coding)
  --select_proposals (boxes with non-finite geometry dropped and counted; NMS; train / test budgets;
     at test time optionally split by range: roi_head.test_split)--> RoIs
  --sample_proposal_targets (training: fg / bg ratio, IoU thresholds)--> RoIs with targets
  --PointRCNNRoIHead (RoI point pooling, canonical coordinates + depth + score, optionally the
     coordinates scaled by the RoI's half-size and the RoI's size, set abstraction inside each
     RoI)--> (B, R, C) --RefineHead--> confidence + residual box
  loss: point focal loss + point box smooth-L1 + confidence BCE + residual smooth-L1 + corner loss
  predict: refined boxes scored by the confidence branch (or, with
     `set_output_stage("proposals")`, the first stage's boxes through the same final NMS)

Both stages train jointly end to end (OpenPCDet's way; the paper trained them one after the
other). Configuration: configs/pointrcnn.yaml (`model:` section), read by `PointRCNNConfig`;
`point_head.mean_size: auto` is resolved from the training boxes and stored in the checkpoint's config.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections
from detbench.ops import ResidualBoxCoder

from .stages import PostConfig, Section, StageConfig, read_point_cloud_range
from .stages.point_head import PointHead, PointHeadConfig, PointHeadOutput, point_targets
from .stages.pointnet2 import PointNet2Config, PointNet2MSG, SamplingConfig, sample_frame_points
from .stages.pointrcnn_head import PointRCNNRoIHead, PointRCNNRoIHeadConfig
from .stages.two_stage import (
    OutputStageSwitch, Proposals, RefineHead, RefineOutput, dropped_proposals_part, predict_refined, refine_loss,
    rois_for_refinement,
)

POINT_FEATURES = 1  # a Batch's point columns after x, y, z: the intensity


@dataclass(frozen=True)
class PointRCNNConfig(StageConfig):
    """PointRCNN's `model:` section (configs/pointrcnn.yaml)."""

    point_cloud_range: tuple[float, float, float, float, float, float]  # m: points outside are cropped
    sampling: SamplingConfig
    backbone: PointNet2Config
    point_head: PointHeadConfig
    roi_head: PointRCNNRoIHeadConfig
    post: PostConfig

    @classmethod
    def read(cls, s: Section) -> PointRCNNConfig:
        s.skip("name")  # the registry's key, configs/<name>.yaml
        return cls(point_cloud_range=read_point_cloud_range(s), sampling=s.section("sampling", SamplingConfig),
                   backbone=s.section("backbone", PointNet2Config), point_head=s.section("point_head", PointHeadConfig),
                   roi_head=s.section("roi_head", PointRCNNRoIHeadConfig), post=s.section("post", PostConfig))


class PointRCNNOutput(NamedTuple):
    xyz: torch.Tensor  # (B, N, 3) the sampled points
    valid: torch.Tensor  # (B, N) bool, False for filler points of empty frames
    point: PointHeadOutput  # per-point logits and box residuals
    proposals: Proposals  # after NMS (before target sampling)
    refine: RefineOutput  # the second stage on the RoIs


class PointRCNN(OutputStageSwitch, nn.Module):
    CONFIG = PointRCNNConfig  # reads and checks the `model:` section
    STAGES = {"backbone": ["backbone"], "point_head": ["point_head"], "roi_head": ["roi_head", "refine"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = c = PointRCNNConfig.from_config(cfg, source="configs/pointrcnn.yaml")
        bb, rh = c.backbone, c.roi_head
        self.backbone = PointNet2MSG(POINT_FEATURES, bb.npoints, bb.radii, bb.nsamples, bb.mlps, bb.fp_mlps)
        self.point_head = PointHead(self.backbone.out_channels, c.point_head)
        self.roi_head = PointRCNNRoIHead(self.backbone.out_channels, rh)
        split = rh.test_split
        self.test_split = (split.distance, split.near_share) if split.enabled else None
        self.refine = RefineHead(self.roi_head.out_channels, rh.fc, rh.dropout)
        self.coder = ResidualBoxCoder()
        self.loss_weights = rh.loss_weights

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """Resolve `point_head.mean_size: auto` to the mean (length, width, height) of the training boxes (m)."""
        cfg = copy.deepcopy(model_cfg)
        if cfg["point_head"]["mean_size"] != "auto":
            return cfg
        sizes = np.asarray(train_boxes, dtype=np.float64).reshape(-1, 7)[:, 3:6]
        if len(sizes) == 0:
            raise ValueError("PointRCNN: point_head.mean_size is 'auto' but the training split has no LiDAR-detected "
                             "vehicles to size it from; give point_head.mean_size explicitly")
        cfg["point_head"]["mean_size"] = [round(float(v), 3) for v in sizes.mean(axis=0)]
        return cfg

    def forward(self, batch: Batch) -> PointRCNNOutput:
        b, sampling = batch.batch_size, self.cfg.sampling
        n = sampling.num_points
        gen = None if self.training else torch.Generator().manual_seed(0)  # evaluation: the same points every time
        sp = sample_frame_points(batch.points, b, n, sampling.far_threshold, generator=gen, shuffle=sampling.shuffle,
                                voxel_size=sampling.voxel_size)
        xyz = sp.points[:, :3].contiguous()
        feats = self.backbone(xyz, sp.points[:, 3:4].contiguous(), n)
        point = self.point_head(feats, b)
        boxes, scores = self.point_head.decode(point, xyz.reshape(b, n, 3))
        valid = sp.valid.reshape(b, n)
        rh = self.cfg.roi_head
        gt = (batch.gt_boxes, batch.gt_mask) if self.training else None  # evaluation never reads ground truth
        r = rois_for_refinement(boxes, scores, valid, rh.proposals, rh.targets, gt, self.test_split)
        cls, reg = self.refine(self.roi_head(xyz, feats, scores.reshape(-1), r.rois, n))
        return PointRCNNOutput(xyz.reshape(b, n, 3), valid, point, r.proposals,
                               RefineOutput(cls, reg, r.rois, r.mask, r.targets))

    def loss(self, out: PointRCNNOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        t = point_targets(out.xyz, out.valid, batch.gt_boxes, batch.gt_mask, self.point_head.extra_width,
                          bottom_lift=self.point_head.fg_bottom_lift)
        point_total, point_parts = self.point_head.loss(out.point, t, out.xyz)
        rcnn_total, rcnn_parts = refine_loss(out.refine, self.coder, self.loss_weights)
        return point_total + rcnn_total, {**point_parts, **rcnn_parts, **dropped_proposals_part(out.proposals)}

    @torch.no_grad()
    def predict(self, out: PointRCNNOutput, batch: Batch) -> list[Detections]:
        if self.output_stage == "proposals":
            boxes, scores = self.point_head.decode(out.point, out.xyz)
            return [self.cfg.post.select(boxes[i][out.valid[i]], scores[i][out.valid[i]])
                    for i in range(boxes.shape[0])]
        return predict_refined(out.refine, self.coder, self.cfg.post)
