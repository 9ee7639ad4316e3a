"""PointRCNN (Shi, Wang and Li, "PointRCNN: 3D Object Proposal Generation and Detection from
Point Cloud", CVPR 2019): the point-based two-stage detector, in plain torch on detbench.ops' point ops.

The model is the composition of shared stages, read top to bottom:

  points --sample_frame_points (fixed budget per frame, far points first, shuffled: sampling.shuffle)--> (B * N, 4)
  --PointNet2MSG (set abstraction down, feature propagation up)--> a feature per point
  --PointHead--> foreground logit + a box per point (residual coding on the mean vehicle size,
     or the paper's bin-based coding: point_head.box_coding)
  --select_proposals (NMS; train / test budgets; at test time optionally split by range:
     roi_head.test_split)--> RoIs
  --sample_proposal_targets (training: fg / bg ratio, IoU thresholds)--> RoIs with targets
  --PointRCNNRoIHead (RoI point pooling, canonical coordinates + depth + score, optionally the
     coordinates scaled by the RoI's half-size and the RoI's size, set abstraction inside each
     RoI)--> (B, R, C) --RefineHead--> confidence + residual box
  loss: point focal loss + point box smooth-L1 + confidence BCE + residual smooth-L1 + corner loss
  predict: refined boxes scored by the confidence branch (or, with
     `set_output_stage("proposals")`, the first stage's boxes through the same final NMS)

Both stages train jointly end to end (OpenPCDet's way; the paper trained them one after the
other). Configuration: configs/pointrcnn.yaml (`model:` section); `point_head.mean_size:
auto` is resolved from the training boxes and stored in the checkpoint's config.
"""
from __future__ import annotations

import copy
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections
from detbench.ops import ResidualBoxCoder

from .stages.point_head import PointHead, PointHeadOutput, point_targets
from .stages.pointnet2 import PointNet2MSG, sample_frame_points
from .stages.pointrcnn_head import PointRCNNRoIHead
from .stages.postprocess import select_detections
from .stages.two_stage import (
    TARGET_KEYS, OutputStageSwitch, Proposals, RefineHead, RefineOutput, predict_refined, proposal_budgets,
    refine_loss, require_keys, rois_for_refinement,
)

POINT_HEAD_KEYS = ("cls_fc", "reg_fc", "extra_width", "fg_bottom_lift", "mean_size", "box_coding", "bin",
                   "loss_weights")
SAMPLING_KEYS = ("num_points", "far_threshold", "shuffle")
TEST_SPLIT_KEYS = ("enabled", "distance", "near_share")


class PointRCNNOutput(NamedTuple):
    xyz: torch.Tensor  # (B, N, 3) the sampled points
    valid: torch.Tensor  # (B, N) bool, False for filler points of empty frames
    point: PointHeadOutput  # per-point logits and box residuals
    proposals: Proposals  # after NMS (before target sampling)
    refine: RefineOutput  # the second stage on the RoIs


class PointRCNN(OutputStageSwitch, nn.Module):
    STAGES = {"backbone": ["backbone"], "point_head": ["point_head"], "roi_head": ["roi_head", "refine"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = cfg
        bb, rh = cfg["backbone"], cfg["roi_head"]
        s = require_keys(cfg["sampling"], SAMPLING_KEYS, "pointrcnn model.sampling")
        ph = require_keys(cfg["point_head"], POINT_HEAD_KEYS, "pointrcnn model.point_head")
        self.num_points, self.far_threshold = int(s["num_points"]), float(s["far_threshold"])
        self.shuffle = bool(s["shuffle"])
        if isinstance(ph["mean_size"], str):
            raise ValueError("PointRCNN: point_head.mean_size is still 'auto'; resolve it from the training data "
                             "(tools/train.py does) or give [length, width, height] in metres")
        npoints = [None if v in (None, -1) else int(v) for v in bb["npoints"]]
        self.backbone = PointNet2MSG(1, npoints, bb["radii"], bb["nsamples"], bb["mlps"], bb["fp_mlps"])
        self.point_head = PointHead(self.backbone.out_channels, ph["cls_fc"], ph["reg_fc"], ph["mean_size"],
                                    extra_width=ph["extra_width"], box_coding=ph["box_coding"], bin_cfg=ph["bin"],
                                    loss_weights=ph["loss_weights"], fg_bottom_lift=ph["fg_bottom_lift"])
        self.proposal_cfg = proposal_budgets(rh["proposals"], "pointrcnn model.roi_head.proposals")
        self.target_cfg = require_keys(rh["targets"], TARGET_KEYS, "pointrcnn model.roi_head.targets")
        sa_np = [None if v in (None, -1) else int(v) for v in rh["sa_npoints"]]
        self.roi_head = PointRCNNRoIHead(self.backbone.out_channels, rh["num_points"], rh["pool_extra_width"],
                                         rh["depth_normalizer"], rh["xyz_up"], sa_np, rh["sa_radii"],
                                         rh["sa_nsamples"], rh["sa_mlps"], batch_norm=bool(rh["batch_norm"]),
                                         scaled_xyz=bool(rh["scaled_xyz"]), roi_size=bool(rh["roi_size"]),
                                         detach_features=bool(rh["detach_features"]))
        split = require_keys(rh["test_split"], TEST_SPLIT_KEYS, "pointrcnn model.roi_head.test_split")
        self.test_split = ({"distance": float(split["distance"]), "near_share": float(split["near_share"])}
                           if split["enabled"] else None)
        self.refine = RefineHead(self.roi_head.out_channels, list(rh["fc"]), rh["dropout"])
        self.coder = ResidualBoxCoder()
        self.loss_weights = require_keys(rh["loss_weights"], ("rcnn_cls", "rcnn_reg", "rcnn_corner"),
                                         "pointrcnn model.roi_head.loss_weights")
        self.post = dict(cfg["post"])

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """Resolve `point_head.mean_size: auto` to the mean (length, width, height) of the training boxes (m)."""
        cfg = copy.deepcopy(model_cfg)
        if cfg["point_head"].get("mean_size", "auto") != "auto":
            return cfg
        sizes = np.asarray(train_boxes, dtype=np.float64).reshape(-1, 7)[:, 3:6]
        if len(sizes) == 0:
            raise ValueError("PointRCNN: point_head.mean_size is 'auto' but the training split has no LiDAR-detected "
                             "vehicles to size it from; give point_head.mean_size explicitly")
        cfg["point_head"]["mean_size"] = [round(float(v), 3) for v in sizes.mean(axis=0)]
        return cfg

    def forward(self, batch: Batch) -> PointRCNNOutput:
        b, n = batch.batch_size, self.num_points
        gen = None if self.training else torch.Generator().manual_seed(0)  # evaluation: the same points every time
        sp = sample_frame_points(batch.points, b, n, self.far_threshold, generator=gen, shuffle=self.shuffle)
        xyz = sp.points[:, :3].contiguous()
        feats = self.backbone(xyz, sp.points[:, 3:4].contiguous(), n)
        point = self.point_head(feats, b)
        boxes, scores = self.point_head.decode(point, xyz.reshape(b, n, 3))
        valid = sp.valid.reshape(b, n)
        r = rois_for_refinement(boxes, scores, valid, batch.gt_boxes, batch.gt_mask, self.proposal_cfg,
                                self.target_cfg, self.training, self.test_split)
        cls, reg = self.refine(self.roi_head(xyz, feats, scores.reshape(-1), r.rois, n))
        return PointRCNNOutput(xyz.reshape(b, n, 3), valid, point, r.proposals,
                               RefineOutput(cls, reg, r.rois, r.mask, r.targets))

    def loss(self, out: PointRCNNOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        t = point_targets(out.xyz, out.valid, batch.gt_boxes, batch.gt_mask, self.point_head.extra_width,
                          bottom_lift=self.point_head.fg_bottom_lift)
        point_total, point_parts = self.point_head.loss(out.point, t, out.xyz)
        rcnn_total, rcnn_parts = refine_loss(out.refine, self.coder, self.loss_weights)
        return point_total + rcnn_total, {**point_parts, **rcnn_parts}

    @torch.no_grad()
    def predict(self, out: PointRCNNOutput, batch: Batch) -> list[Detections]:
        if self.output_stage == "proposals":
            boxes, scores = self.point_head.decode(out.point, out.xyz)
            return [select_detections(boxes[i][out.valid[i]], scores[i][out.valid[i]], **self.post)
                    for i in range(boxes.shape[0])]
        return predict_refined(out.refine, self.coder, self.post)
