"""PointRCNN's first-stage head: foreground segmentation and one box per point.

- `point_targets`: a point is foreground when it lies inside a ground-truth box with its bottom
  raised by `bottom_lift` (the study's rule for a detected vehicle, 0.05 m, keeps the road under
  and at the wheels of a vehicle out of it); points in the box enlarged by `extra_width` (metres
  per side; configs/pointrcnn.yaml) but outside the box are ignored by the segmentation loss
  (their label is unsure: a box edge, a mirror), except below the raised bottom (road);
  the rest is background. A foreground point's box target is the box it lies in.
- Box coding, chosen by `box_coding` (the presets use bins; docs/results.md, "PointRCNN", has the runs behind that):
  - `residual`: against a box of the mean vehicle size centred on the point (OpenPCDet's
    PointResidualCoder with mean sizes): centre offsets divided by the mean BEV diagonal (z by
    the mean height), log size ratios, heading as (cos, sin); smooth-L1 on all 8 values.
  - `bin`: the PointRCNN paper's bin-based coding (`detbench.ops.PointBinCoder`): the x and y
    offsets as bins within a scope around the point (cross-entropy) plus a residual inside the
    true bin (smooth-L1), z as a plain residual, the heading as bins + residual, the size as a
    residual against the mean size (weighted `point_size`). The paper's values (0.5 m bins
    within +-3 m, 12 heading bins, size weight 3) are in configs/pointrcnn.yaml.
- `PointHead`: two shared-MLP branches on the backbone's per-point features; `loss` (sigmoid
  focal loss for segmentation, the coding's box loss on the foreground points) and `decode`.

Every configurable value comes from the `model.point_head` section of configs/pointrcnn.yaml,
their one home, read by `PointHeadConfig`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from detbench.ops import PointBinCoder, ResidualBoxCoder, points_in_boxes_mask

from .config import Section, StageConfig, is_size3
from .losses import sigmoid_focal_loss, weighted_smooth_l1


@dataclass(frozen=True)
class BinCodingConfig(StageConfig):
    """The bin-based box coding (`point_head.bin`)."""

    loc_scope: float  # m: the x / y bins cover +- this around the point
    loc_bin_size: float  # m per x / y bin
    num_heading_bins: int

    @classmethod
    def read(cls, s: Section) -> BinCodingConfig:
        return cls(loc_scope=s.positive("loc_scope", "a positive number of metres"),
                   loc_bin_size=s.positive("loc_bin_size", "a positive number of metres"),
                   num_heading_bins=s.count("num_heading_bins"))


@dataclass(frozen=True)
class PointLossWeights(StageConfig):
    """Multipliers of the point head's loss terms (`point_head.loss_weights`)."""

    point_cls: float  # segmentation focal loss
    point_box: float  # box loss of the foreground points
    point_size: float  # the bin coding's size term inside the box loss

    @classmethod
    def read(cls, s: Section) -> PointLossWeights:
        return cls(point_cls=s.non_negative("point_cls"), point_box=s.non_negative("point_box"),
                   point_size=s.non_negative("point_size"))


@dataclass(frozen=True)
class PointHeadConfig(StageConfig):
    """PointRCNN's point head (`model.point_head`)."""

    cls_fc: tuple[int, ...]  # widths of the segmentation branch's hidden layers
    reg_fc: tuple[int, ...]  # widths of the box branch's hidden layers
    extra_width: float  # m per side: points in this margin around a box are ignored by segmentation
    fg_bottom_lift: float  # m: foreground = inside a box with its bottom raised this much
    mean_size: tuple[float, float, float] | None  # m of the box coding; None = auto (from the training boxes)
    box_coding: str  # bin (the paper's) or residual (OpenPCDet's PointResidualCoder)
    bin: BinCodingConfig
    focal_alpha: float  # segmentation focal loss: weight of the foreground
    focal_gamma: float  # segmentation focal loss: focusing exponent
    loss_weights: PointLossWeights

    @classmethod
    def read(cls, s: Section) -> PointHeadConfig:
        size = s.check("mean_size", lambda v: v == "auto" or is_size3(v), "auto or [length, width, height] in "
                                                                           "positive metres")
        return cls(cls_fc=s.counts("cls_fc", empty=True), reg_fc=s.counts("reg_fc", empty=True),
                   extra_width=s.non_negative("extra_width", "a number of metres >= 0"),
                   fg_bottom_lift=s.non_negative("fg_bottom_lift", "a number of metres >= 0"),
                   mean_size=None if size == "auto" else tuple(float(v) for v in size),
                   box_coding=s.choice("box_coding", ("residual", "bin")), bin=s.section("bin", BinCodingConfig),
                   focal_alpha=s.fraction("focal_alpha", "a weight"), focal_gamma=s.non_negative("focal_gamma"),
                   loss_weights=s.section("loss_weights", PointLossWeights))


class PointTargets(NamedTuple):
    labels: torch.Tensor  # (B, N) int64: 1 foreground, 0 background, -1 ignored
    boxes: torch.Tensor  # (B, N, 7) the box a foreground point lies in (zeros elsewhere)


@torch.no_grad()
def point_targets(xyz: torch.Tensor, valid: torch.Tensor, gt_boxes: torch.Tensor, gt_mask: torch.Tensor,
                  extra_width: float, *, bottom_lift: float) -> PointTargets:
    """Segmentation labels and box targets for points (B, N, 3) against padded ground truth (B, M, 7).

    `valid` (B, N) False marks filler points (ignored). A point inside several boxes takes
    the first. Boxes are tested with `points_in_boxes_mask` (inclusive faces), their bottom
    raised by `bottom_lift` metres; the ignore margin's bottom is that same raised face.
    """
    b, n = xyz.shape[:2]
    labels = torch.zeros(b, n, dtype=torch.int64, device=xyz.device)
    boxes = torch.zeros(b, n, 7, dtype=torch.float32, device=xyz.device)
    for i in range(b):
        gt = gt_boxes[i][gt_mask[i]].float()
        if gt.shape[0] == 0:
            continue
        inside = points_in_boxes_mask(xyz[i], gt, bottom_lift=bottom_lift).to(xyz.device)  # (N, M) bool
        big = gt.clone()
        big[:, 3:6] += 2.0 * extra_width
        # the margin's bottom face is the box's raised bottom: below it lies road, background
        near_lift = extra_width + bottom_lift if bottom_lift > 0 else 0.0
        near = points_in_boxes_mask(xyz[i], big, bottom_lift=near_lift).to(xyz.device).any(dim=1)
        fg = inside.any(dim=1)
        labels[i][near & ~fg] = -1
        labels[i][fg] = 1
        first = inside.float().argmax(dim=1)
        boxes[i][fg] = gt[first[fg]]
    labels[~valid] = -1
    return PointTargets(labels, boxes)


class PointHeadOutput(NamedTuple):
    cls_logits: torch.Tensor  # (B, N) foreground logits
    box_deltas: torch.Tensor  # (B, N, C) the box code at each point (residual: C = 8; bin: the coder's code_size)


class PointHead(nn.Module):
    """Segmentation and box branches on per-point features (B, N, C)."""

    def __init__(self, in_channels: int, cfg: PointHeadConfig):
        """Set up by `cfg`, its mean size resolved (PointRCNN.prepare_config): with `box_coding` 'bin' the
        x / y / heading bins of `cfg.bin`; `extra_width` metres per side; `fg_bottom_lift` metres the
        boxes' bottoms are raised for the foreground labels (`point_targets`)."""
        super().__init__()
        if cfg.mean_size is None:
            raise ValueError("PointRCNN: point_head.mean_size is still 'auto'; resolve it from the training data "
                             "(tools/train.py does) or give [length, width, height] in metres")
        ms = list(cfg.mean_size)
        self.cfg = cfg
        self.box_coding = cfg.box_coding
        if cfg.box_coding == "bin":
            b = cfg.bin
            self.bin_coder = PointBinCoder(ms, b.loc_scope, b.loc_bin_size, b.num_heading_bins)
            code_size = self.bin_coder.code_size
        else:
            code_size = 8
        self.code_size = code_size
        self.cls = self._branch(in_channels, cfg.cls_fc, 1)
        self.reg = self._branch(in_channels, cfg.reg_fc, code_size)
        nn.init.constant_(self.cls[-1].bias, -4.6)  # prior foreground probability 0.01
        self.coder = ResidualBoxCoder(encode_angle_by_sincos=True)
        self.register_buffer("mean_size", torch.tensor(ms), persistent=False)
        self.extra_width, self.fg_bottom_lift = cfg.extra_width, cfg.fg_bottom_lift
        self.loss_weights = cfg.loss_weights

    @staticmethod
    def _branch(cin: int, fc: Sequence[int], cout: int) -> nn.Sequential:
        layers: list[nn.Module] = []
        for c in fc:
            layers += [nn.Linear(cin, c, bias=False), nn.BatchNorm1d(c), nn.ReLU(inplace=True)]
            cin = c
        layers.append(nn.Linear(cin, cout))
        return nn.Sequential(*layers)

    def forward(self, features: torch.Tensor, batch_size: int) -> PointHeadOutput:
        """features (B * N, C) -> logits (B, N), box codes (B, N, code_size)."""
        n = features.shape[0] // max(batch_size, 1)
        return PointHeadOutput(self.cls(features).reshape(batch_size, n),
                               self.reg(features).reshape(batch_size, n, self.code_size))

    def anchors(self, xyz: torch.Tensor) -> torch.Tensor:
        """(B, N, 7) mean-size boxes centred on the points, heading 0."""
        a = torch.zeros(*xyz.shape[:-1], 7, dtype=torch.float32, device=xyz.device)
        a[..., :3] = xyz[..., :3]
        a[..., 3:6] = self.mean_size
        return a

    def decode(self, out: PointHeadOutput, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes (B, N, 7) and foreground probabilities (B, N)."""
        deltas = out.box_deltas.float()
        if self.box_coding == "bin":
            return self.bin_coder.decode(deltas, xyz[..., :3].float()), torch.sigmoid(out.cls_logits.float())
        deltas = torch.cat([deltas[..., :3], deltas[..., 3:6].clamp(-3.0, 3.0), deltas[..., 6:]], dim=-1)
        return self.coder.decode(deltas, self.anchors(xyz)), torch.sigmoid(out.cls_logits.float())

    def loss(self, out: PointHeadOutput, targets: PointTargets, xyz: torch.Tensor) -> tuple[torch.Tensor, dict]:
        b = targets.labels.shape[0]
        fg = targets.labels == 1
        n_fg = fg.sum().clamp(min=1).float()
        cls_w = (targets.labels >= 0).float() / n_fg
        loss_cls = sigmoid_focal_loss(out.cls_logits.float(), fg.float(), cls_w, self.cfg.focal_alpha,
                                      self.cfg.focal_gamma)
        if self.box_coding == "bin":
            loss_box = self._bin_loss(out.box_deltas.float(), targets.boxes, xyz, fg) / n_fg
        else:
            target = self.coder.encode(targets.boxes, self.anchors(xyz))
            target = torch.where(fg[..., None], target, torch.zeros_like(target))
            loss_box = weighted_smooth_l1(out.box_deltas.float(), target, fg.float() / n_fg)
        w = self.loss_weights
        total = w.point_cls * loss_cls + w.point_box * loss_box
        return total, {"loss_point_cls": float(loss_cls.detach()), "loss_point_box": float(loss_box.detach()),
                       "num_fg_points": float(fg.sum()) / max(b, 1)}

    def _bin_loss(self, pred: torch.Tensor, boxes: torch.Tensor, xyz: torch.Tensor, fg: torch.Tensor) -> torch.Tensor:
        """Sum over foreground points of the bin coding's loss (PointRCNN Sec. 3.1): cross-entropy
        of the x, y and heading bins, smooth-L1 of the residuals in the true bins, of z, and of the
        size (weight `point_size`)."""
        if not bool(fg.any()):
            return pred.sum() * 0.0
        p = self.bin_coder.split(pred[fg])
        t = self.bin_coder.encode(boxes[fg].float(), xyz[fg].float())
        ones = torch.ones_like(t.x_res)

        def in_bin(res, bins):
            return res.gather(-1, bins[:, None])[:, 0]

        loss = (F.cross_entropy(p["x_bin"], t.x_bin, reduction="sum")
                + F.cross_entropy(p["y_bin"], t.y_bin, reduction="sum")
                + F.cross_entropy(p["h_bin"], t.h_bin, reduction="sum"))
        res_pred = torch.stack([in_bin(p["x_res"], t.x_bin), in_bin(p["y_res"], t.y_bin), p["z_res"],
                                in_bin(p["h_res"], t.h_bin)], dim=-1)
        res_target = torch.stack([t.x_res, t.y_res, t.z_res, t.h_res], dim=-1)
        loss = loss + weighted_smooth_l1(res_pred, res_target, ones)
        return loss + self.loss_weights.point_size * weighted_smooth_l1(p["size_res"], t.size_res, ones)
