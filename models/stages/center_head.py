"""Center-based dense head (CenterPoint-style) with PillarNet's IoU-aware branch and OD-IoU loss.

A vehicle is a peak of a class heat map on the BEV grid at `stride` pillars per cell; the
other maps, read at the peak's cell, regress the box:

  heatmap   (B, 1, H, W) logits of "a vehicle centre lies in this cell"
  offset    (B, 2, H, W) centre - cell corner, in cells (x, y), in [0, 1) for the target
  z         (B, 1, H, W) box centre z (m)
  log_size  (B, 3, H, W) log(dx, dy, dz) (m)
  rot       (B, 2, H, W) sin(heading), cos(heading)
  iou       (B, 1, H, W) 2 * IoU - 1 of the decoded box with its target (IoU-aware branch)

Pieces, each usable alone:
- `gaussian_radius`: CenterNet's radius for a box of (length, width) cells: the largest
  shift (or shrink or growth) of the box that keeps its IoU with itself >= `min_overlap`.
- `draw_gaussian_heatmap`: Gaussian peaks, exactly 1 at each centre cell (sigma =
  (2 r + 1) / 6, max where peaks overlap); `build_center_targets` does the whole encoding.
- its losses are plain functions in models/stages/losses.py: `centernet_focal_loss`
  (CenterNet's variant, with the (1 - y)^4 penalty reduction around peaks) and
  `od_iou_loss` (orientation-decoupled IoU regression loss).
- `CenterHead`: the convolutions, `loss` and `predict` (local maxima by 3x3 max-pool or
  rotated NMS, IoU-rectified scores score^(1-a) * iou^a, score threshold, top-k).
- `CenterHeadConfig` and `CenterPostConfig`: PillarNet's `model.head` and `model.post` sections.

One class (Vehicle, label 0): the Batch carries no class labels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from detbench.data.batch import Detections
from detbench.ops import boxes_iou3d_aligned

from .config import Section, StageConfig
from .grid import VoxelGrid
from .losses import centernet_focal_loss, od_iou_loss
from .norm import dense_bn
from .postprocess import PostConfig, select_detections

REG_CHANNELS = 8  # offset x, offset y, z, log dx, log dy, log dz, sin h, cos h
LOG_SIZE_RANGE = (-8.0, 6.0)  # clamp of log(size) when decoding: 3e-4 m .. 403 m


# --------------------------------------------------------------------------------------
# targets
# --------------------------------------------------------------------------------------
def gaussian_radius(length: torch.Tensor, width: torch.Tensor, min_overlap: float) -> torch.Tensor:
    """CenterNet's Gaussian radius (cells) for boxes of `length` x `width` cells (same shape, float).

    The smallest of three radii r at which a box of the same size, moved by r in both
    directions / shrunk by r on every side / grown by r on every side, still has IoU
    `min_overlap` with the original. Each is the smaller (valid) root of a quadratic in r
    (the corrected roots, not the widely copied ones that use the wrong denominator).
    Returns a float tensor (>= 0) of the inputs' shape; callers floor it and apply a minimum.
    """
    if not 0.0 < min_overlap < 1.0:
        raise ValueError(f"gaussian_radius: min_overlap must lie in (0, 1), got {min_overlap}")
    h, w = length.clamp(min=0).double(), width.clamp(min=0).double()
    o = float(min_overlap)
    s, p = h + w, h * w
    # moved by (r, r): (h - r)(w - r) (1 + o) = 2 o h w
    r1 = (s - torch.sqrt((s * s - 4 * p * (1 - o) / (1 + o)).clamp(min=0))) / 2
    # shrunk by r per side: (h - 2r)(w - 2r) = o h w
    r2 = (2 * s - torch.sqrt((4 * s * s - 16 * (1 - o) * p).clamp(min=0))) / 8
    # grown by r per side: h w = o (h + 2r)(w + 2r)
    r3 = (-2 * o * s + torch.sqrt((4 * o * o * s * s + 16 * o * (1 - o) * p).clamp(min=0))) / (8 * o)
    return torch.minimum(torch.minimum(r1, r2), r3).clamp(min=0).to(length.dtype)


def draw_gaussian_heatmap(shape: tuple[int, int, int], batch_index: torch.Tensor, cx: torch.Tensor, cy: torch.Tensor,
                          radius: torch.Tensor) -> torch.Tensor:
    """Heat map (B, H, W) with a Gaussian peak per centre; `shape` = (B, H, W).

    batch_index, cx, cy, radius: (K,) int64 frame, cell column, cell row and radius (cells)
    of each peak; cells must lie inside the map. Peak k is exp(-d^2 / (2 sigma_k^2)) with
    sigma_k = (2 r_k + 1) / 6 over the (2 r_k + 1)^2 window around its cell (exactly 1 at
    the cell); overlapping peaks take the max. Vectorised over peaks (no Python loop).
    """
    b, h, w = shape
    device = cx.device
    out = torch.zeros(b * h * w, dtype=torch.float32, device=device)
    if cx.numel() == 0:
        return out.view(b, h, w)
    radius = radius.long().clamp(min=0, max=max(h, w))
    r_max = int(radius.max())
    d = torch.arange(-r_max, r_max + 1, device=device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")  # (D, D)
    dx, dy = dx.reshape(1, -1), dy.reshape(1, -1)
    sigma = (2 * radius.float() + 1) / 6
    value = torch.exp(-(dx * dx + dy * dy).float() / (2 * sigma[:, None] ** 2))  # (K, D*D)
    x, y = cx[:, None] + dx, cy[:, None] + dy
    keep = (dx.abs() <= radius[:, None]) & (dy.abs() <= radius[:, None]) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    flat = (batch_index[:, None] * h + y) * w + x
    out.scatter_reduce_(0, flat[keep], value[keep], "amax", include_self=True)
    return out.view(b, h, w)


class CenterTargets(NamedTuple):
    """Encoded ground truth of a batch for a center head (M = padded box count)."""

    heatmap: torch.Tensor  # (B, 1, H, W) float32 in [0, 1], 1 at centre cells
    index: torch.Tensor  # (B, M) int64 flat cell index y * W + x of each box's centre (0 where masked)
    mask: torch.Tensor  # (B, M) bool: a real box whose centre lies on the map
    reg: torch.Tensor  # (B, M, 8) offset x, offset y (cells), z (m), log dx, log dy, log dz, sin h, cos h
    boxes: torch.Tensor  # (B, M, 7) the ground-truth boxes (for IoU targets and OD-IoU)


def build_center_targets(gt_boxes: torch.Tensor, gt_mask: torch.Tensor, grid: VoxelGrid, stride: int,
                         min_radius: int, min_overlap: float) -> CenterTargets:
    """Encode padded ground truth (B, M, 7) with mask (B, M) for the map at `stride` pillars per cell.

    A box's centre cell is floor((x - x0) / cell_x), floor((y - y0) / cell_y); boxes whose
    centre falls off the map (or whose row is not finite) are left out (mask False). The
    heat-map radius is max(min_radius, floor(gaussian_radius(dx / cell_x, dy / cell_y))).
    """
    if gt_boxes.dim() != 3 or gt_boxes.shape[-1] < 7 or gt_mask.shape != gt_boxes.shape[:2]:
        raise ValueError(f"build_center_targets: gt_boxes must be (B, M, 7) and gt_mask (B, M), got "
                         f"{tuple(gt_boxes.shape)} and {tuple(gt_mask.shape)}")
    device = gt_boxes.device
    nx, ny, _ = grid.grid_size
    if nx % stride or ny % stride:
        raise ValueError(f"build_center_targets: the grid {nx} x {ny} does not divide by the stride {stride}")
    w, h = nx // stride, ny // stride
    b, m = gt_mask.shape
    cell_x, cell_y = grid.bev_cell(stride)
    x0, y0 = grid.point_cloud_range[0], grid.point_cloud_range[1]
    boxes = gt_boxes[..., :7].float()
    fx = (boxes[..., 0] - x0) / cell_x
    fy = (boxes[..., 1] - y0) / cell_y
    ix, iy = torch.floor(fx), torch.floor(fy)
    finite = torch.isfinite(boxes).all(dim=-1)
    mask = gt_mask.bool() & finite & (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    ix = torch.where(mask, ix, torch.zeros_like(ix)).long()
    iy = torch.where(mask, iy, torch.zeros_like(iy)).long()
    index = iy * w + ix
    size = boxes[..., 3:6].clamp(min=1e-3)
    heading = boxes[..., 6]
    reg = torch.stack([fx - ix, fy - iy, boxes[..., 2], *torch.log(size).unbind(-1), torch.sin(heading),
                       torch.cos(heading)], dim=-1)
    reg = torch.where(mask[..., None], reg, torch.zeros_like(reg))
    radius = torch.floor(gaussian_radius(size[..., 0] / cell_x, size[..., 1] / cell_y, min_overlap)).long()
    radius = radius.clamp(min=int(min_radius))
    bi = torch.arange(b, device=device)[:, None].expand(b, m)
    heat = draw_gaussian_heatmap((b, h, w), bi[mask], ix[mask], iy[mask], radius[mask])
    return CenterTargets(heat[:, None], index, mask, reg, torch.where(mask[..., None], boxes, torch.zeros_like(boxes)))


def decode_regression(reg: torch.Tensor, index: torch.Tensor, grid: VoxelGrid, stride: int) -> torch.Tensor:
    """Boxes (..., 7) from regression values (..., 8) read at flat cell indices (...).

    x = x0 + (column + offset_x) * cell_x (likewise y); z as regressed; sizes exp(log size)
    (log clamped to LOG_SIZE_RANGE); heading atan2(sin, cos) in (-pi, pi].
    """
    nx = grid.grid_size[0]
    w = nx // stride
    cell_x, cell_y = grid.bev_cell(stride)
    x0, y0 = grid.point_cloud_range[0], grid.point_cloud_range[1]
    col = (index % w).to(reg.dtype)
    row = torch.div(index, w, rounding_mode="floor").to(reg.dtype)
    x = x0 + (col + reg[..., 0]) * cell_x
    y = y0 + (row + reg[..., 1]) * cell_y
    size = torch.exp(reg[..., 3:6].clamp(*LOG_SIZE_RANGE))
    heading = torch.atan2(reg[..., 6], reg[..., 7])
    return torch.cat([x[..., None], y[..., None], reg[..., 2:3], size, heading[..., None]], dim=-1)


# --------------------------------------------------------------------------------------
# the head
# --------------------------------------------------------------------------------------
class CenterHeadOutput(NamedTuple):
    """Raw maps of a `CenterHead` (see the module docstring for channels and units)."""

    heatmap: torch.Tensor  # (B, 1, H, W) logits
    offset: torch.Tensor  # (B, 2, H, W) cells
    z: torch.Tensor  # (B, 1, H, W) m
    log_size: torch.Tensor  # (B, 3, H, W) log m
    rot: torch.Tensor  # (B, 2, H, W) sin, cos
    iou: torch.Tensor | None  # (B, 1, H, W) 2 * IoU - 1, None without the IoU branch

    def regression(self) -> torch.Tensor:
        """(B, 8, H, W) offset, z, log_size, rot stacked in the REG_CHANNELS order."""
        return torch.cat([self.offset, self.z, self.log_size, self.rot], dim=1)


def _gather(maps: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """maps (B, C, H, W), flat cell index (B, M) -> (B, M, C)."""
    b, c = maps.shape[:2]
    flat = maps.reshape(b, c, -1)
    return flat.gather(2, index[:, None, :].expand(b, c, index.shape[1])).permute(0, 2, 1)


def _branch(cin: int, mid: int, cout: int, num_convs: int, final_bias: float | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for _ in range(num_convs - 1):
        layers += [nn.Conv2d(cin, mid, 3, padding=1, bias=False), dense_bn(mid), nn.ReLU()]
        cin = mid
    last = nn.Conv2d(cin, cout, 3, padding=1, bias=True)
    if final_bias is not None:
        nn.init.constant_(last.bias, final_bias)
    layers.append(last)
    return nn.Sequential(*layers)


@dataclass(frozen=True)
class CenterLossWeights(StageConfig):
    """Multipliers of the center head's loss terms (`head.loss_weights`)."""

    hm: float  # heat-map focal loss
    reg: float  # code-weighted L1 of the regression maps
    iou: float  # IoU branch (counted with iou_branch only)
    od_iou: float  # orientation-decoupled IoU loss

    @classmethod
    def read(cls, s: Section) -> CenterLossWeights:
        return cls(hm=s.non_negative("hm"), reg=s.non_negative("reg"), iou=s.non_negative("iou"),
                   od_iou=s.non_negative("od_iou"))


@dataclass(frozen=True)
class CenterHeadConfig(StageConfig):
    """PillarNet's center head (`model.head`)."""

    shared_channels: int  # width of the shared 3x3 conv in front of the branches
    head_channels: int  # width of each branch's 3x3 convs
    head_convs: int  # 3x3 convs per branch, the last one is the output
    iou_branch: bool  # the IoU-aware branch (its loss, and score rectification at inference)
    min_radius: int  # heat-map Gaussian radius floor, cells
    min_overlap: float  # CenterNet radius rule: IoU kept by a shifted box, in (0, 1)
    od_iou_distance: bool  # add the DIoU centre-distance term to the OD-IoU loss
    code_weights: tuple[float, ...]  # 8 weights of the L1 regression terms (REG_CHANNELS order)
    loss_weights: CenterLossWeights

    @classmethod
    def read(cls, s: Section) -> CenterHeadConfig:
        return cls(shared_channels=s.count("shared_channels"), head_channels=s.count("head_channels"),
                   head_convs=s.count("head_convs"), iou_branch=s.flag("iou_branch"),
                   min_radius=s.count("min_radius", 0),
                   min_overlap=float(s.check("min_overlap", lambda v: isinstance(v, (int, float)) and 0 < v < 1,
                                             "an IoU in (0, 1)")),
                   od_iou_distance=s.flag("od_iou_distance"),
                   code_weights=s.numbers("code_weights", REG_CHANNELS, need=f"{REG_CHANNELS} numbers (offset x, "
                                          f"offset y, z, log dx, log dy, log dz, sin, cos)"),
                   loss_weights=s.section("loss_weights", CenterLossWeights))


@dataclass(frozen=True)
class CenterPostConfig(StageConfig):
    """PillarNet's `model.post`: the common selection (`PostConfig`) plus how peaks are found and rescored."""

    method: str  # nms: rotated BEV NMS over all cells; maxpool: 3x3 local maxima, no NMS
    select: PostConfig  # score_threshold (on the heat, before rectification), top-k budgets, NMS IoU
    iou_rectifier: float  # a of score = heat^(1 - a) * iou^a, in [0, 1] (0: off)

    @classmethod
    def read(cls, s: Section) -> CenterPostConfig:
        return cls(method=s.choice("method", ("maxpool", "nms")), select=PostConfig.read(s),
                   iou_rectifier=s.fraction("iou_rectifier", "an exponent"))


class CenterHead(nn.Module):
    """Single-class center head on a BEV map (B, in_channels, H, W) at `stride` pillars per cell.

    Args:
        in_channels: width of the BEV map.
        grid: the pillar grid (H = Y / stride, W = X / stride).
        stride: pillars per map cell.
        cfg: the head's convolutions, target and loss settings (`CenterHeadConfig`).
        post: decoding settings (`CenterPostConfig`): method "maxpool" (3x3 local maxima of the
            heat map, no NMS) or "nms" (all cells, rotated BEV NMS at nms_threshold); score_threshold
            (on the heat), pre_nms_top_k, post_nms_top_k, iou_rectifier a in [0, 1]
            (score = heat^(1-a) * iou^a; 0 turns rectification off).
    """

    def __init__(self, in_channels: int, grid: VoxelGrid, stride: int, cfg: CenterHeadConfig, post: CenterPostConfig):
        super().__init__()
        shared_channels, head_channels, head_convs = cfg.shared_channels, cfg.head_channels, cfg.head_convs
        grid.check_divisible(int(stride), "CenterHead")
        self.grid, self.stride = grid, int(stride)
        nx, ny, _ = grid.grid_size
        self.map_shape = (ny // self.stride, nx // self.stride)  # (H, W)
        self.shared = nn.Sequential(nn.Conv2d(in_channels, shared_channels, 3, padding=1, bias=False),
                                    dense_bn(shared_channels), nn.ReLU())
        prior = 0.1
        self.branches = nn.ModuleDict({
            "heatmap": _branch(shared_channels, head_channels, 1, head_convs, -math.log((1 - prior) / prior)),
            "offset": _branch(shared_channels, head_channels, 2, head_convs),
            "z": _branch(shared_channels, head_channels, 1, head_convs),
            "log_size": _branch(shared_channels, head_channels, 3, head_convs),
            "rot": _branch(shared_channels, head_channels, 2, head_convs),
        })
        if cfg.iou_branch:
            self.branches["iou"] = _branch(shared_channels, head_channels, 1, head_convs)
        self.cfg, self.post = cfg, post
        self.iou_branch = cfg.iou_branch
        self.register_buffer("code_weights", torch.tensor(cfg.code_weights, dtype=torch.float32), persistent=False)

    def forward(self, bev: torch.Tensor) -> CenterHeadOutput:
        """BEV map (B, in_channels, H, W) -> CenterHeadOutput of raw maps."""
        if tuple(bev.shape[-2:]) != self.map_shape:
            raise ValueError(f"CenterHead: the BEV map is {tuple(bev.shape[-2:])} cells but the grid at stride "
                             f"{self.stride} gives {self.map_shape}")
        x = self.shared(bev)
        out = {name: branch(x) for name, branch in self.branches.items()}
        return CenterHeadOutput(out["heatmap"], out["offset"], out["z"], out["log_size"], out["rot"], out.get("iou"))

    def targets(self, gt_boxes: torch.Tensor, gt_mask: torch.Tensor) -> CenterTargets:
        """Encode padded ground truth (B, M, 7), mask (B, M) for this head's map."""
        return build_center_targets(gt_boxes, gt_mask, self.grid, self.stride, self.cfg.min_radius,
                                    self.cfg.min_overlap)

    def loss(self, out: CenterHeadOutput, gt_boxes: torch.Tensor, gt_mask: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Total loss and its parts for padded ground truth (B, M, 7) with mask (B, M).

        hm: CenterNet focal loss / number of boxes; reg: code-weighted L1 of the 8 regression
        values at the boxes' centre cells / number of boxes; iou: L1 of the IoU branch against
        2 * IoU3D(decoded box, target) - 1; od_iou: `od_iou_loss` of the decoded boxes.
        Every term is normalised by max(1, boxes in the batch). A batch without boxes gives
        only the heat-map term (the others are 0 but keep every branch in the graph).
        """
        t = self.targets(gt_boxes, gt_mask)
        n = t.mask.sum().clamp(min=1).float()
        hm_loss, _ = centernet_focal_loss(out.heatmap, t.heatmap)
        hm_loss = hm_loss / n
        reg = _gather(out.regression().float(), t.index)  # (B, M, 8)
        m = t.mask[..., None].float()
        reg_loss = ((reg - t.reg).abs() * self.code_weights * m).sum() / n
        # decoded boxes with the heading detached: atan2 has no gradient at (0, 0), and the
        # OD-IoU loss ignores the predicted heading anyway
        dec = decode_regression(torch.cat([reg[..., :6], reg[..., 6:].detach()], dim=-1), t.index, self.grid,
                                self.stride)
        pred_boxes, gt = dec[t.mask], t.boxes[t.mask]
        od_loss = od_iou_loss(pred_boxes, gt, self.cfg.od_iou_distance).sum() / n
        w = self.cfg.loss_weights
        total = w.hm * hm_loss + w.reg * reg_loss + w.od_iou * od_loss
        parts = {"loss_hm": float(hm_loss.detach()), "loss_reg": float(reg_loss.detach()),
                 "loss_od_iou": float(od_loss.detach())}
        if self.iou_branch:
            iou_pred = _gather(out.iou.float(), t.index)[..., 0][t.mask]
            with torch.no_grad():
                iou_t = boxes_iou3d_aligned(pred_boxes.detach(), gt).to(iou_pred.dtype) if gt.shape[0] else \
                    iou_pred.new_zeros(0)
            iou_loss = (iou_pred - (2 * iou_t - 1)).abs().sum() / n
            total = total + w.iou * iou_loss
            parts["loss_iou"] = float(iou_loss.detach())
            parts["mean_iou"] = float(iou_t.mean()) if iou_t.numel() else 0.0
        parts["num_pos"] = float(t.mask.sum()) / max(1, t.mask.shape[0])
        return total, parts

    @torch.no_grad()
    def rectify(self, heat: torch.Tensor, iou_raw: torch.Tensor | None) -> torch.Tensor:
        """Scores heat^(1-a) * iou^a in [0, 1] from heat (any shape) and the IoU branch's raw
        values (same shape, 2 * IoU - 1); plain heat without the IoU branch or with a = 0."""
        a = self.post.iou_rectifier
        if iou_raw is None or a == 0.0:
            return heat
        iou = ((iou_raw.float() + 1) / 2).clamp(0, 1)
        return heat.pow(1 - a) * iou.pow(a)

    @torch.no_grad()
    def predict(self, out: CenterHeadOutput, valid: torch.Tensor | None = None) -> list[Detections]:
        """Detections per frame. `valid` (B,) bool: frames marked False (e.g. with no points) get none.

        Candidates are the `pre_nms_top_k` cells of highest heat (only 3x3 local maxima with
        method maxpool) whose heat is >= score_threshold; their scores are IoU-rectified, then
        rotated NMS (method nms) and the `post_nms_top_k` best. The threshold is applied to the
        heat, not to the rectified score: with a = 0.68 a cell of heat 0.001 and a predicted
        IoU of 1 would otherwise score 0.11.
        """
        p = self.post.select
        b = out.heatmap.shape[0]
        heat = torch.sigmoid(out.heatmap.float())
        if self.post.method == "maxpool":
            peak = F.max_pool2d(heat, 3, stride=1, padding=1) == heat
            heat = torch.where(peak, heat, torch.zeros_like(heat))
            nms_threshold = 1.0  # a BEV IoU never exceeds 1: select_detections then only sorts and caps
        else:
            nms_threshold = p.nms_threshold
        heat = heat.flatten(1)
        k = min(p.pre_nms_top_k, heat.shape[1])
        top, index = heat.topk(k, dim=1)  # (B, K)
        iou_raw = _gather(out.iou, index)[..., 0] if self.iou_branch else None
        score = self.rectify(top, iou_raw)
        boxes = decode_regression(_gather(out.regression().float(), index), index, self.grid, self.stride)
        keep = top >= p.score_threshold
        dets = []
        for i in range(b):
            if valid is not None and not bool(valid[i]):
                dets.append(Detections.empty(out.heatmap.device))
                continue
            dets.append(select_detections(boxes[i][keep[i]], score[i][keep[i]], 0.0, k, nms_threshold,
                                          p.post_nms_top_k))
        return dets
