"""Anchor-based dense head (SECOND): anchors, target assignment, losses and decoding.

Pieces, each usable alone (torchvision-style):
- `AnchorGenerator`: one anchor per BEV cell, per size and per rotation (default 0 and
  pi/2), bottom on the road (z centre = bottom_z + h/2). Order (H, W, size, rotation),
  matching the head's (B, A*C, H, W) -> (B, H*W*A, C) reshaping.
- `assign_targets`: BEV IoU between anchors and ground truth; positive >= 0.6, negative
  < 0.45, in between ignored; each ground-truth box also keeps its best anchor(s).
- `AnchorHead`: 1x1 convolutions for class, box residual and direction logits; `loss`
  (focal + smooth-L1 with the sine-difference heading + direction cross-entropy, plain
  functions from losses.py) and `predict` (decode, direction fix, NMS).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn as nn

from detbench.data.batch import Detections
from detbench.ops import ResidualBoxCoder, boxes_iou_bev, limit_period, normalize_heading

from .grid import VoxelGrid, check_memory
from .losses import add_sin_difference, sigmoid_focal_loss, weighted_cross_entropy, weighted_smooth_l1
from .postprocess import select_detections


class AnchorGenerator:
    def __init__(self, sizes: Sequence[Sequence[float]], rotations: Sequence[float] = (0.0, math.pi / 2),
                 bottom_z: float = 0.0):
        self.sizes = [tuple(float(v) for v in s) for s in sizes]
        if not self.sizes or any(len(s) != 3 or min(s) <= 0 for s in self.sizes):
            raise ValueError(f"anchor sizes must be a list of positive [length, width, height] (m), got {sizes}")
        self.rotations = [float(r) for r in rotations]
        self.bottom_z = float(bottom_z)

    @property
    def num_per_location(self) -> int:
        return len(self.sizes) * len(self.rotations)

    def __call__(self, grid: VoxelGrid, stride: int, device: torch.device | str = "cpu") -> torch.Tensor:
        """Anchors (H * W * num_per_location, 7) for the BEV map at `stride` voxels per cell."""
        x0, y0 = grid.point_cloud_range[0], grid.point_cloud_range[1]
        cx, cy = grid.bev_cell(stride)
        nx, ny, _ = grid.grid_size
        w, h = nx // stride, ny // stride
        xs = x0 + (torch.arange(w, dtype=torch.float32, device=device) + 0.5) * cx
        ys = y0 + (torch.arange(h, dtype=torch.float32, device=device) + 0.5) * cy
        sizes = torch.tensor(self.sizes, dtype=torch.float32, device=device)  # (S, 3)
        rots = torch.tensor(self.rotations, dtype=torch.float32, device=device)  # (R,)
        s, r = sizes.shape[0], rots.shape[0]
        check_memory(4.0 * h * w * s * r * 7, f"the anchors of a {w} x {h} BEV map ({s} size(s) x {r} rotation(s))")
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")  # (H, W)
        out = torch.zeros(h, w, s, r, 7, dtype=torch.float32, device=device)
        out[..., 0] = xx[:, :, None, None]
        out[..., 1] = yy[:, :, None, None]
        out[..., 3:6] = sizes[None, None, :, None, :]
        out[..., 2] = self.bottom_z + sizes[None, None, :, None, 2] / 2
        out[..., 6] = rots[None, None, None, :]
        return out.reshape(-1, 7)


class Targets(NamedTuple):
    labels: torch.Tensor  # (A,) int64: 1 positive, 0 negative, -1 ignored
    boxes: torch.Tensor  # (A, 7) matched ground-truth box (zeros where not positive)


@torch.no_grad()
def assign_targets(anchors: torch.Tensor, gt_boxes: torch.Tensor, pos_iou: float = 0.6,
                   neg_iou: float = 0.45) -> Targets:
    """Label anchors (A, 7) against one frame's ground truth (M, 7) by BEV IoU.

    Only anchors whose centre lies within reach of a box (sum of the two half-diagonals)
    get an exact IoU; all others have IoU 0 and are negatives.
    """
    a, m = anchors.shape[0], gt_boxes.shape[0]
    labels = torch.zeros(a, dtype=torch.int64, device=anchors.device)
    matched = torch.zeros(a, 7, dtype=anchors.dtype, device=anchors.device)
    if m == 0 or a == 0:
        return Targets(labels, matched)
    gt = gt_boxes[:, :7].to(anchors.dtype)
    half_a = 0.5 * torch.hypot(anchors[:, 3], anchors[:, 4])
    half_g = 0.5 * torch.hypot(gt[:, 3], gt[:, 4])
    dist = torch.cdist(anchors[:, :2], gt[:, :2])  # (A, M)
    near = dist <= half_a[:, None] + half_g[None, :]
    cand = near.any(dim=1).nonzero(as_tuple=True)[0]
    iou = torch.zeros(a, m, dtype=anchors.dtype, device=anchors.device)
    if cand.numel():
        iou[cand] = boxes_iou_bev(anchors[cand], gt).to(anchors.dtype)
    max_iou, argmax = iou.max(dim=1)
    labels[(max_iou >= neg_iou) & (max_iou < pos_iou)] = -1
    pos = max_iou >= pos_iou
    gt_best = iou.max(dim=0).values  # (M,)
    force_a, force_g = ((iou == gt_best[None, :]) & (gt_best[None, :] > 0)).nonzero(as_tuple=True)
    argmax[force_a] = force_g
    pos[force_a] = True
    labels[pos] = 1
    matched[pos] = gt[argmax[pos]]
    return Targets(labels, matched)


class AnchorHeadOutput(NamedTuple):
    cls_logits: torch.Tensor  # (B, A) one class (Vehicle)
    box_deltas: torch.Tensor  # (B, A, 7) residuals against the anchors
    dir_logits: torch.Tensor  # (B, A, num_dir_bins)


class AnchorHead(nn.Module):
    """Single-class anchor head on a BEV map at `stride` voxels per cell."""

    def __init__(self, in_channels: int, grid: VoxelGrid, stride: int, anchor_sizes: Sequence[Sequence[float]],
                 rotations: Sequence[float] = (0.0, math.pi / 2), pos_iou: float = 0.6, neg_iou: float = 0.45,
                 num_dir_bins: int = 2, dir_offset: float = math.pi / 4, loss_weights: dict | None = None,
                 focal_alpha: float = 0.25, focal_gamma: float = 2.0, post: dict | None = None):
        super().__init__()
        self.generator = AnchorGenerator(anchor_sizes, rotations)
        self.grid, self.stride = grid, int(stride)
        self.register_buffer("anchors", self.generator(grid, self.stride), persistent=False)
        k = self.generator.num_per_location
        self.conv_cls = nn.Conv2d(in_channels, k, 1)
        self.conv_box = nn.Conv2d(in_channels, k * 7, 1)
        self.conv_dir = nn.Conv2d(in_channels, k * num_dir_bins, 1)
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - 0.01) / 0.01))
        nn.init.normal_(self.conv_box.weight, std=0.001)
        nn.init.zeros_(self.conv_box.bias)
        self.coder = ResidualBoxCoder()
        self.pos_iou, self.neg_iou = float(pos_iou), float(neg_iou)
        self.num_dir_bins, self.dir_offset = int(num_dir_bins), float(dir_offset)
        self.loss_weights = {"cls": 1.0, "box": 2.0, "dir": 0.2, **(loss_weights or {})}
        self.focal_alpha, self.focal_gamma = float(focal_alpha), float(focal_gamma)
        self.post = {"score_threshold": 0.1, "pre_nms_top_k": 1000, "nms_threshold": 0.1, "post_nms_top_k": 100,
                     **(post or {})}

    def forward(self, bev: torch.Tensor) -> AnchorHeadOutput:
        b = bev.shape[0]
        cls = self.conv_cls(bev).permute(0, 2, 3, 1).reshape(b, -1)
        box = self.conv_box(bev).permute(0, 2, 3, 1).reshape(b, -1, 7)
        dirl = self.conv_dir(bev).permute(0, 2, 3, 1).reshape(b, -1, self.num_dir_bins)
        if cls.shape[1] != self.anchors.shape[0]:
            raise ValueError(f"AnchorHead: the BEV map gives {cls.shape[1]} anchors but the grid has "
                             f"{self.anchors.shape[0]}; the BEV map size does not match grid / stride")
        return AnchorHeadOutput(cls, box, dirl)

    def _dir_targets(self, headings: torch.Tensor) -> torch.Tensor:
        period = 2 * math.pi / self.num_dir_bins
        rot = limit_period(headings - self.dir_offset, 0.0, 2 * math.pi)
        return torch.floor(rot / period).long().clamp(0, self.num_dir_bins - 1)

    def loss(self, out: AnchorHeadOutput, gt_boxes: torch.Tensor, gt_mask: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Total loss and its parts for padded ground truth (B, M, 7) with mask (B, M)."""
        b = out.cls_logits.shape[0]
        labels, matched = [], []
        for i in range(b):
            t = assign_targets(self.anchors, gt_boxes[i][gt_mask[i]], self.pos_iou, self.neg_iou)
            labels.append(t.labels)
            matched.append(t.boxes)
        labels = torch.stack(labels)  # (B, A)
        matched = torch.stack(matched)  # (B, A, 7)
        pos = labels == 1
        num_pos = pos.sum(dim=1, keepdim=True).clamp(min=1).float()  # per frame, as the reference
        cls_w = (labels >= 0).float() / num_pos
        reg_w = pos.float() / num_pos
        logits = out.cls_logits.float()
        loss_cls = sigmoid_focal_loss(logits, pos.float(), cls_w, self.focal_alpha, self.focal_gamma) / b
        anchors = self.anchors[None].expand(b, -1, -1)
        target_deltas = self.coder.encode(matched, anchors)
        target_deltas = torch.where(pos[..., None], target_deltas, torch.zeros_like(target_deltas))
        pred, tgt = add_sin_difference(out.box_deltas.float(), target_deltas)
        loss_box = weighted_smooth_l1(pred, tgt, reg_w) / b
        dir_t = self._dir_targets(matched[..., 6])
        loss_dir = weighted_cross_entropy(out.dir_logits.float(), dir_t, reg_w) / b
        w = self.loss_weights
        total = w["cls"] * loss_cls + w["box"] * loss_box + w["dir"] * loss_dir
        parts = {"loss_cls": float(loss_cls.detach()), "loss_box": float(loss_box.detach()),
                 "loss_dir": float(loss_dir.detach()), "num_pos": float(pos.sum()) / b}
        return total, parts

    def decode(self, out: AnchorHeadOutput) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes (B, A, 7) with direction fixed, and scores (B, A) in [0, 1]."""
        anchors = self.anchors[None].expand(out.box_deltas.shape[0], -1, -1)
        boxes = self.coder.decode(out.box_deltas.float(), anchors)
        period = 2 * math.pi / self.num_dir_bins
        dir_labels = out.dir_logits.argmax(dim=-1)
        rot = limit_period(boxes[..., 6] - self.dir_offset, 0.0, period)
        boxes = torch.cat([boxes[..., :6], normalize_heading(rot + self.dir_offset + period * dir_labels)[..., None]],
                          dim=-1)
        return boxes, torch.sigmoid(out.cls_logits.float())

    @torch.no_grad()
    def predict(self, out: AnchorHeadOutput) -> list[Detections]:
        boxes, scores = self.decode(out)
        return [select_detections(boxes[i], scores[i], **self.post) for i in range(boxes.shape[0])]
