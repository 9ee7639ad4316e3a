"""CT3D-style two-stage detector (Sheng et al., "Improving 3D Object Detection with
Channel-wise Transformer", ICCV 2021): SECOND's proposals refined by a channel-wise transformer.

The model is SECOND's network (`SECONDStages`, its modules registered under SECOND's names,
so a SECOND checkpoint initialises them) with a second stage:

  points --SECOND (vfe, backbone3d, to_bev, backbone2d, head)--> anchor scores and boxes
  --select_proposals (NMS; train / test budgets)--> RoIs (B, R, 7)
  --sample_proposal_targets (training: fg / bg ratio, IoU thresholds)--> RoIs with targets
  --CT3DRoIHead (cylinder points, keypoint encoding, self-attention encoder,
     channel-wise decoder)--> (B, R, d) --RefineHead--> IoU-guided confidence + residual box
  loss: SECOND's anchor loss + confidence BCE + residual smooth-L1 + corner loss
  predict: refined boxes scored by the confidence branch (or, with
     `set_output_stage("proposals")`, the first stage's own detections, for comparison)

Configuration: configs/ct3d.yaml (SECOND's keys plus `roi_head:`). Both stages train
jointly from the first step, as the published configuration.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn

from detbench.data.batch import Batch, Detections
from detbench.ops import ResidualBoxCoder

from .second import SECOND, SECONDStages
from .stages import AnchorHeadOutput
from .stages.ct3d_head import CT3DRoIHead
from .stages.two_stage import (
    TARGET_KEYS, OutputStageSwitch, Proposals, RefineHead, RefineOutput, predict_refined, proposal_budgets,
    refine_loss, require_keys, rois_for_refinement,
)

ROI_HEAD_KEYS = ("num_points", "radius_scale", "hidden_dim", "heads", "enc_layers", "dim_feedforward", "dropout",
                 "mlp_hidden", "max_pool_skip", "fc", "proposals", "targets", "loss_weights")


class TwoStageOutput(NamedTuple):
    rpn: AnchorHeadOutput  # the first stage's dense outputs
    proposals: Proposals  # after NMS (before target sampling)
    refine: RefineOutput  # the second stage on the RoIs


class CT3D(OutputStageSwitch, nn.Module):
    STAGES = {**SECOND.STAGES, "roi_head": ["roi_head", "refine"]}

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = cfg
        self.rpn = SECONDStages(cfg)  # the first stage; its modules are this model's children
        self.rpn.attach(self)
        rh = require_keys(cfg.get("roi_head"), ROI_HEAD_KEYS, "ct3d model.roi_head")
        self.rh = rh
        self.proposal_cfg = proposal_budgets(rh["proposals"], "ct3d model.roi_head.proposals")
        self.target_cfg = require_keys(rh["targets"], TARGET_KEYS, "ct3d model.roi_head.targets")
        self.loss_weights = require_keys(rh["loss_weights"], ("rpn", "rcnn_cls", "rcnn_reg", "rcnn_corner"),
                                         "ct3d model.roi_head.loss_weights")
        self.roi_head = CT3DRoIHead(rh["num_points"], rh["radius_scale"], rh["hidden_dim"], rh["heads"],
                                    rh["enc_layers"], rh["dim_feedforward"], rh["dropout"], point_features=1,
                                    mlp_hidden=rh["mlp_hidden"], max_pool_skip=rh["max_pool_skip"])
        self.refine = RefineHead(self.roi_head.out_channels, list(rh["fc"]), rh["dropout"])
        self.coder = ResidualBoxCoder()

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """SECOND's: `head.anchor_sizes: auto` resolved from the training boxes (N, 7)."""
        return SECOND.prepare_config(model_cfg, train_boxes)

    def forward(self, batch: Batch) -> TwoStageOutput:
        rpn = self.rpn(batch)
        boxes, scores = self.rpn.head.decode(rpn)
        r = rois_for_refinement(boxes, scores, None, batch.gt_boxes, batch.gt_mask, self.proposal_cfg,
                                self.target_cfg, self.training)
        cls, reg = self.refine(self.roi_head(batch.points, r.rois))
        return TwoStageOutput(rpn, r.proposals, RefineOutput(cls, reg, r.rois, r.mask, r.targets))

    def loss(self, out: TwoStageOutput, batch: Batch) -> tuple[torch.Tensor, dict]:
        w = self.loss_weights
        rpn_total, rpn_parts = self.rpn.loss(out.rpn, batch)
        rcnn_total, rcnn_parts = refine_loss(out.refine, self.coder, w)
        return w["rpn"] * rpn_total + rcnn_total, {**rpn_parts, **rcnn_parts}

    def predict(self, out: TwoStageOutput, batch: Batch) -> list[Detections]:
        if self.output_stage == "proposals":
            return self.rpn.predict(out.rpn)
        return predict_refined(out.refine, self.coder, self.rpn.head.post)
