"""Anchor-based dense head (SECOND): anchors, target assignment, losses and decoding.

Pieces, each usable alone (torchvision-style):
- `AnchorGenerator`: one anchor per BEV cell, per size and per rotation, bottom on the road
  (z = 0 in the ego ground frame, so the z centre is h/2). Order (H, W, size, rotation),
  matching the head's (B, A*C, H, W) -> (B, H*W*A, C) reshaping.
- `assign_targets`: BEV IoU between anchors and ground truth; positive >= pos_iou, negative
  < neg_iou, in between ignored; each ground-truth box also keeps its best anchor(s).
- `AnchorHead`: 1x1 convolutions for class, box residual and direction logits; `loss`
  (focal + smooth-L1 with the sine-difference heading + direction cross-entropy, plain
  functions from losses.py) and `predict` (decode, direction fix, NMS).
- `AnchorHeadConfig`: the `model.head` section of configs/second.yaml (SECOND's and CT3D's head).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn

from detbench.data.batch import Detections
from detbench.ops import ResidualBoxCoder, boxes_iou_bev, limit_period, normalize_heading

from .config import Section, StageConfig, is_size3
from .grid import VoxelGrid, check_memory
from .losses import add_sin_difference, sigmoid_focal_loss, weighted_cross_entropy, weighted_smooth_l1
from .postprocess import PostConfig

MAX_ANCHOR_SIZES = 16  # k-means clusters of the training boxes' sizes (num_anchor_sizes)


@dataclass(frozen=True)
class AnchorLossWeights(StageConfig):
    """Multipliers of the anchor head's loss terms (`head.loss_weights`)."""

    cls: float  # focal classification loss
    box: float  # box residual smooth-L1
    dir: float  # direction classification

    @classmethod
    def read(cls, s: Section) -> AnchorLossWeights:
        return cls(cls=s.non_negative("cls"), box=s.non_negative("box"), dir=s.non_negative("dir"))


@dataclass(frozen=True)
class AnchorHeadConfig(StageConfig):
    """SECOND's anchor head (`model.head`): anchors, target assignment, direction bins and loss settings."""

    anchor_sizes: tuple[tuple[float, float, float], ...] | None  # m; None = auto (from the training boxes)
    num_anchor_sizes: int  # with auto: k-means clusters of the training boxes' sizes
    rotations: tuple[float, ...]  # anchor headings, radians
    pos_iou: float  # BEV IoU from which an anchor is positive
    neg_iou: float  # ... below which it is negative (in between: ignored)
    num_dir_bins: int  # bins of the direction classifier over the full turn
    dir_offset: float  # radians: where the first direction bin starts
    focal_alpha: float  # focal loss: weight of the positives
    focal_gamma: float  # focal loss: focusing exponent
    loss_weights: AnchorLossWeights

    @classmethod
    def read(cls, s: Section) -> AnchorHeadConfig:
        sizes = s.check("anchor_sizes", lambda v: v == "auto" or (isinstance(v, (list, tuple)) and len(v) > 0
                                                                    and all(map(is_size3, v))),
                        "auto or a non-empty list of [length, width, height] in positive metres")
        c = cls(anchor_sizes=None if sizes == "auto" else tuple(tuple(float(x) for x in v) for v in sizes),
                num_anchor_sizes=s.count("num_anchor_sizes", 1, MAX_ANCHOR_SIZES,
                                         " (k-means clusters of the training boxes' sizes)"),
                rotations=s.numbers("rotations", need="a non-empty list of anchor angles in radians, e.g. "
                                                      "[0.0, 1.5707963]"),
                pos_iou=s.fraction("pos_iou", "an IoU"), neg_iou=s.fraction("neg_iou", "an IoU"),
                num_dir_bins=s.count("num_dir_bins"), dir_offset=s.number("dir_offset", "an angle in radians"),
                focal_alpha=s.fraction("focal_alpha", "a weight"), focal_gamma=s.non_negative("focal_gamma"),
                loss_weights=s.section("loss_weights", AnchorLossWeights))
        s.order("neg_iou", "pos_iou")
        return c


class AnchorGenerator:
    """Anchors of `sizes` ([length, width, height] m) at each of `rotations` (radians) per BEV cell."""

    def __init__(self, sizes: Sequence[Sequence[float]], rotations: Sequence[float]):
        self.sizes = [tuple(float(v) for v in s) for s in sizes]
        if not self.sizes or any(len(s) != 3 or min(s) <= 0 for s in self.sizes):
            raise ValueError(f"anchor sizes must be a list of positive [length, width, height] (m), got {sizes}")
        self.rotations = [float(r) for r in rotations]

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
        out[..., 2] = sizes[None, None, :, None, 2] / 2  # bottom on the road, z = 0
        out[..., 6] = rots[None, None, None, :]
        return out.reshape(-1, 7)


class Targets(NamedTuple):
    labels: torch.Tensor  # (A,) int64: 1 positive, 0 negative, -1 ignored
    boxes: torch.Tensor  # (A, 7) matched ground-truth box (zeros where not positive)


@torch.no_grad()
def assign_targets(anchors: torch.Tensor, gt_boxes: torch.Tensor, pos_iou: float, neg_iou: float) -> Targets:
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
    """Single-class anchor head on a BEV map at `stride` voxels per cell, set up by `cfg` (its anchor
    sizes resolved: SECOND.prepare_config) and selecting its detections by `post`."""

    def __init__(self, in_channels: int, grid: VoxelGrid, stride: int, cfg: AnchorHeadConfig, post: PostConfig):
        super().__init__()
        if cfg.anchor_sizes is None:
            raise ValueError("SECOND: head.anchor_sizes is still 'auto'; resolve it from the training data "
                             "(tools/train.py does) or give [[length, width, height], ...] in metres")
        self.cfg = cfg
        self.generator = AnchorGenerator(cfg.anchor_sizes, cfg.rotations)
        self.grid, self.stride = grid, int(stride)
        self.register_buffer("anchors", self.generator(grid, self.stride), persistent=False)
        k = self.generator.num_per_location
        self.conv_cls = nn.Conv2d(in_channels, k, 1)
        self.conv_box = nn.Conv2d(in_channels, k * 7, 1)
        self.conv_dir = nn.Conv2d(in_channels, k * cfg.num_dir_bins, 1)
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - 0.01) / 0.01))
        nn.init.normal_(self.conv_box.weight, std=0.001)
        nn.init.zeros_(self.conv_box.bias)
        self.coder = ResidualBoxCoder()
        self.num_dir_bins, self.dir_offset = cfg.num_dir_bins, cfg.dir_offset
        self.post = post

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
            t = assign_targets(self.anchors, gt_boxes[i][gt_mask[i]], self.cfg.pos_iou, self.cfg.neg_iou)
            labels.append(t.labels)
            matched.append(t.boxes)
        labels = torch.stack(labels)  # (B, A)
        matched = torch.stack(matched)  # (B, A, 7)
        pos = labels == 1
        num_pos = pos.sum(dim=1, keepdim=True).clamp(min=1).float()  # per frame, as the reference
        cls_w = (labels >= 0).float() / num_pos
        reg_w = pos.float() / num_pos
        logits = out.cls_logits.float()
        loss_cls = sigmoid_focal_loss(logits, pos.float(), cls_w, self.cfg.focal_alpha, self.cfg.focal_gamma) / b
        anchors = self.anchors[None].expand(b, -1, -1)
        target_deltas = self.coder.encode(matched, anchors)
        target_deltas = torch.where(pos[..., None], target_deltas, torch.zeros_like(target_deltas))
        pred, tgt = add_sin_difference(out.box_deltas.float(), target_deltas)
        loss_box = weighted_smooth_l1(pred, tgt, reg_w) / b
        dir_t = self._dir_targets(matched[..., 6])
        loss_dir = weighted_cross_entropy(out.dir_logits.float(), dir_t, reg_w) / b
        w = self.cfg.loss_weights
        total = w.cls * loss_cls + w.box * loss_box + w.dir * loss_dir
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
        return [self.post.select(boxes[i], scores[i]) for i in range(boxes.shape[0])]
