"""PointRCNN's first-stage head: foreground segmentation and one box per point.

- `point_targets`: a point is foreground when it lies inside a ground-truth box; points in the
  box enlarged by `extra_width` (0.2 m per side, the published value) but outside the box are
  ignored by the segmentation loss (their label is unsure: a box edge, a mirror); the rest is
  background. A foreground point's box target is the box it lies in.
- Box coding: residual coding against a box of the mean vehicle size centred on the point
  (OpenPCDet's PointResidualCoder with mean sizes): centre offsets divided by the mean BEV
  diagonal (z by the mean height), log size ratios, heading as (cos, sin). We chose this over
  the PointRCNN paper's bin-based coding: one vehicle class on a highway needs no multi-bin
  search for x/y, the residual form has no bin-size hyper-parameters tied to the scene extent,
  and it is what OpenPCDet's maintained PointRCNN uses; docs/architecture.md says the same.
- `PointHead`: two shared-MLP branches on the backbone's per-point features; `loss` (sigmoid
  focal loss for segmentation, smooth-L1 for the foreground boxes) and `decode`.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
import torch.nn as nn

from detbench.ops import ResidualBoxCoder, points_in_boxes_mask

from .losses import sigmoid_focal_loss, weighted_smooth_l1


class PointTargets(NamedTuple):
    labels: torch.Tensor  # (B, N) int64: 1 foreground, 0 background, -1 ignored
    boxes: torch.Tensor  # (B, N, 7) the box a foreground point lies in (zeros elsewhere)


@torch.no_grad()
def point_targets(xyz: torch.Tensor, valid: torch.Tensor, gt_boxes: torch.Tensor, gt_mask: torch.Tensor,
                  extra_width: float = 0.2) -> PointTargets:
    """Segmentation labels and box targets for points (B, N, 3) against padded ground truth (B, M, 7).

    `valid` (B, N) False marks filler points (ignored). A point inside several boxes takes
    the first. Boxes are tested with `points_in_boxes_mask` (inclusive faces, no bottom lift).
    """
    b, n = xyz.shape[:2]
    labels = torch.zeros(b, n, dtype=torch.int64, device=xyz.device)
    boxes = torch.zeros(b, n, 7, dtype=torch.float32, device=xyz.device)
    for i in range(b):
        gt = gt_boxes[i][gt_mask[i]].float()
        if gt.shape[0] == 0:
            continue
        inside = points_in_boxes_mask(xyz[i], gt).to(xyz.device)  # (N, M) bool
        big = gt.clone()
        big[:, 3:6] += 2.0 * extra_width
        near = points_in_boxes_mask(xyz[i], big).to(xyz.device).any(dim=1)
        fg = inside.any(dim=1)
        labels[i][near & ~fg] = -1
        labels[i][fg] = 1
        first = inside.float().argmax(dim=1)
        boxes[i][fg] = gt[first[fg]]
    labels[~valid] = -1
    return PointTargets(labels, boxes)


class PointHeadOutput(NamedTuple):
    cls_logits: torch.Tensor  # (B, N) foreground logits
    box_deltas: torch.Tensor  # (B, N, 8) residuals against the mean-size box at each point


class PointHead(nn.Module):
    """Segmentation and box branches on per-point features (B, N, C)."""

    def __init__(self, in_channels: int, cls_fc: Sequence[int], reg_fc: Sequence[int],
                 mean_size: Sequence[float], extra_width: float = 0.2, focal_alpha: float = 0.25,
                 focal_gamma: float = 2.0, loss_weights: dict | None = None):
        super().__init__()
        self.cls = self._branch(in_channels, cls_fc, 1)
        self.reg = self._branch(in_channels, reg_fc, 8)
        nn.init.constant_(self.cls[-1].bias, -4.6)  # prior foreground probability 0.01
        self.coder = ResidualBoxCoder(encode_angle_by_sincos=True)
        ms = [float(v) for v in mean_size]
        if len(ms) != 3 or min(ms) <= 0:
            raise ValueError(f"PointRCNN: point_head.mean_size must be [length, width, height] > 0 m, got {mean_size}")
        self.register_buffer("mean_size", torch.tensor(ms), persistent=False)
        self.extra_width = float(extra_width)
        self.focal_alpha, self.focal_gamma = float(focal_alpha), float(focal_gamma)
        self.loss_weights = {"point_cls": 1.0, "point_box": 1.0, **(loss_weights or {})}

    @staticmethod
    def _branch(cin: int, fc: Sequence[int], cout: int) -> nn.Sequential:
        layers: list[nn.Module] = []
        for c in fc:
            layers += [nn.Linear(cin, c, bias=False), nn.BatchNorm1d(c), nn.ReLU(inplace=True)]
            cin = c
        layers.append(nn.Linear(cin, cout))
        return nn.Sequential(*layers)

    def forward(self, features: torch.Tensor, batch_size: int) -> PointHeadOutput:
        """features (B * N, C) -> logits (B, N), deltas (B, N, 8)."""
        n = features.shape[0] // max(batch_size, 1)
        return PointHeadOutput(self.cls(features).reshape(batch_size, n),
                               self.reg(features).reshape(batch_size, n, 8))

    def anchors(self, xyz: torch.Tensor) -> torch.Tensor:
        """(B, N, 7) mean-size boxes centred on the points, heading 0."""
        a = torch.zeros(*xyz.shape[:-1], 7, dtype=torch.float32, device=xyz.device)
        a[..., :3] = xyz[..., :3]
        a[..., 3:6] = self.mean_size
        return a

    def decode(self, out: PointHeadOutput, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes (B, N, 7) and foreground probabilities (B, N)."""
        deltas = out.box_deltas.float()
        deltas = torch.cat([deltas[..., :3], deltas[..., 3:6].clamp(-3.0, 3.0), deltas[..., 6:]], dim=-1)
        return self.coder.decode(deltas, self.anchors(xyz)), torch.sigmoid(out.cls_logits.float())

    def loss(self, out: PointHeadOutput, targets: PointTargets, xyz: torch.Tensor) -> tuple[torch.Tensor, dict]:
        b = targets.labels.shape[0]
        fg = targets.labels == 1
        n_fg = fg.sum().clamp(min=1).float()
        cls_w = (targets.labels >= 0).float() / n_fg
        loss_cls = sigmoid_focal_loss(out.cls_logits.float(), fg.float(), cls_w, self.focal_alpha, self.focal_gamma)
        target = self.coder.encode(targets.boxes, self.anchors(xyz))
        target = torch.where(fg[..., None], target, torch.zeros_like(target))
        loss_box = weighted_smooth_l1(out.box_deltas.float(), target, fg.float() / n_fg)
        w = self.loss_weights
        total = w["point_cls"] * loss_cls + w["point_box"] * loss_box
        return total, {"loss_point_cls": float(loss_cls.detach()), "loss_point_box": float(loss_box.detach()),
                       "num_fg_points": float(fg.sum()) / max(b, 1)}
