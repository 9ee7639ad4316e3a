"""CT3D-style two-stage detector (Sheng et al., "Improving 3D Object Detection with
Channel-wise Transformer", ICCV 2021): SECOND's proposals refined by a channel-wise transformer.

The model is SECOND's network (`SECONDStages`, its modules registered under SECOND's names,
so a SECOND checkpoint initialises them) with a second stage:

  points --SECOND (vfe, backbone3d, to_bev, backbone2d, head)--> anchor scores and boxes
  --select_proposals (boxes with non-finite geometry dropped and counted; NMS; train / test budgets)
  --> RoIs (B, R, 7)
  --sample_proposal_targets (training: fg / bg ratio, IoU thresholds)--> RoIs with targets
  --CT3DRoIHead (cylinder points, keypoint encoding, self-attention encoder,
     channel-wise decoder)--> (B, R, d) --RefineHead--> IoU-guided confidence + residual box
  loss: SECOND's anchor loss + confidence BCE + residual smooth-L1 + corner loss
  predict: refined boxes scored by the confidence branch (or, with
     `set_output_stage("proposals")`, the first stage's own detections, for comparison)

Configuration: configs/ct3d.yaml (SECOND's keys plus `roi_head:`), read by `CT3DConfig`.
Both stages train jointly from the first step, as the published configuration.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections
from detbench.ops import ResidualBoxCoder

from .second import SECOND, SECONDConfig, SECONDStages
from .stages import AnchorHeadOutput, Section, StageConfig
from .stages.ct3d_head import CT3DHeadConfig, CT3DRoIHead
from .stages.two_stage import (
    OutputStageSwitch, Proposals, RefineHead, RefineOutput, dropped_proposals_part, predict_refined, refine_loss,
    rois_for_refinement,
)

POINT_FEATURES = 1  # a Batch's point columns after x, y, z: the intensity


@dataclass(frozen=True)
class CT3DConfig(StageConfig):
    """CT3D's `model:` section (configs/ct3d.yaml): SECOND's keys for the first stage, plus `roi_head`."""

    rpn: SECONDConfig
    roi_head: CT3DHeadConfig

    @classmethod
    def read(cls, s: Section) -> CT3DConfig:
        return cls(rpn=SECONDConfig.read(s), roi_head=s.section("roi_head", CT3DHeadConfig))


class TwoStageOutput(NamedTuple):
    rpn: AnchorHeadOutput  # the first stage's dense outputs
    proposals: Proposals  # after NMS (before target sampling)
    refine: RefineOutput  # the second stage on the RoIs


class CT3D(OutputStageSwitch, nn.Module):
    CONFIG = CT3DConfig  # reads and checks the `model:` section
    STAGES = {**SECOND.STAGES, "roi_head": ["roi_head", "refine"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = CT3DConfig.from_config(cfg, source="configs/ct3d.yaml")
        self.rpn = SECONDStages(self.cfg.rpn)  # the first stage; its modules are this model's children
        self.rpn.attach(self)
        rh = self.cfg.roi_head
        self.roi_head = CT3DRoIHead(rh, POINT_FEATURES)
        self.refine = RefineHead(self.roi_head.out_channels, rh.fc, rh.dropout)
        self.coder = ResidualBoxCoder()

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """SECOND's: `head.anchor_sizes: auto` resolved from the training boxes (N, 7)."""
        return SECOND.prepare_config(model_cfg, train_boxes)

    def forward(self, batch: Batch) -> TwoStageOutput:
        rpn = self.rpn(batch)
        boxes, scores = self.rpn.head.decode(rpn)
        rh = self.cfg.roi_head
        gt = (batch.gt_boxes, batch.gt_mask) if self.training else None  # evaluation never reads ground truth
        r = rois_for_refinement(boxes, scores, None, rh.proposals, rh.targets, gt)
        cls, reg = self.refine(self.roi_head(batch.points, r.rois))
        return TwoStageOutput(rpn, r.proposals, RefineOutput(cls, reg, r.rois, r.mask, r.targets))

    def loss(self, out: TwoStageOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        w = self.cfg.roi_head.loss_weights
        rpn_total, rpn_parts = self.rpn.loss(out.rpn, batch)
        rcnn_total, rcnn_parts = refine_loss(out.refine, self.coder, w.refine)
        return w.rpn * rpn_total + rcnn_total, {**rpn_parts, **rcnn_parts, **dropped_proposals_part(out.proposals)}

    def predict(self, out: TwoStageOutput, batch: Batch) -> list[Detections]:
        if self.output_stage == "proposals":
            return self.rpn.predict(out.rpn)
        return predict_refined(out.refine, self.coder, self.cfg.rpn.post)
