"""The second stage shared by the two-stage detectors (PointRCNN, CT3D).

OpenPCDet's `roi_head_template` and `proposal_target_layer` are the shape, written as plain
functions and small modules with explicit tensors in and out:

  first-stage boxes + scores --select_proposals--> RoIs (B, R, 7) per frame (NMS, train/test budgets)
  RoIs + ground truth --sample_proposal_targets--> a fixed number of RoIs per frame with their
      matched box, 3D IoU, regression mask and confidence target      (training only)
  RoI features (model-specific) --RefineHead--> confidence logit + residual box per RoI
  refine_loss: confidence (binary cross-entropy to the IoU-guided or binary target),
      residual smooth-L1 and the corner loss on foreground RoIs
  decode_refined: residuals -> boxes in the ego frame

Box residuals live in the RoI's canonical frame (`detbench.ops.to_canonical`): the ground truth is moved
so the RoI's centre is the origin and its heading is +x, then coded with the residual coder
against a box of the RoI's size at the origin. The heading target is folded into
[-pi/2, pi/2] (a box regressed backwards is as good as forwards for 3D IoU), and the corner
loss takes the smaller of the two corner distances (ground truth and ground truth turned by
pi), as PointRCNN. Corner loss stability: the size residuals are clamped before `exp` (a
box can grow or shrink by at most e^3 per refinement) and the corner distance goes through
a Huber loss, so neither the loss nor its gradient can explode on a wild early prediction.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from detbench.data.batch import Detections
from detbench.ops import ResidualBoxCoder, boxes_iou3d, nms_bev, normalize_heading

from .config import Section, StageConfig, is_list_of, is_number
from .losses import corner_loss, weighted_smooth_l1
from .postprocess import PostConfig

LOG_SIZE_CLAMP = 3.0  # |log(size / roi size)| at most e^3 when decoding residuals
# A padding RoI (frames with fewer proposals than slots): a car-sized box far from anything,
# so its geometry stays finite; it is masked out of every loss and prediction.
PAD_ROI = (1000.0, 0.0, 1.0, 4.0, 1.8, 1.5, 0.0)


# --------------------------------------------------------------------------------------
# the second stage's configs (a two-stage model's `roi_head:` section holds them)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProposalBudget(StageConfig):
    """One NMS budget of `roi_head.proposals` (train or test)."""

    pre_nms_top_k: int  # the best first-stage boxes that enter NMS (0: none, the second stage idles)
    post_nms_top_k: int  # RoI slots per frame after NMS
    nms_threshold: float  # BEV IoU above which the lower-scored box is suppressed

    @classmethod
    def read(cls, s: Section) -> ProposalBudget:
        return cls(pre_nms_top_k=s.count("pre_nms_top_k", 0), post_nms_top_k=s.count("post_nms_top_k", 0),
                   nms_threshold=s.fraction("nms_threshold", "an IoU"))


@dataclass(frozen=True)
class ProposalConfig(StageConfig):
    """`roi_head.proposals`: the budgets in training and in evaluation."""

    train: ProposalBudget
    test: ProposalBudget

    @classmethod
    def read(cls, s: Section) -> ProposalConfig:
        return cls(train=s.section("train", ProposalBudget), test=s.section("test", ProposalBudget))


CLS_SCORE_TYPES = ("roi_iou", "binary")


@dataclass(frozen=True)
class TargetConfig(StageConfig):
    """`roi_head.targets`: proposal target sampling in training (`sample_proposal_targets`)."""

    roi_per_image: int  # RoIs per frame the second stage is trained on
    fg_ratio: float  # share of foreground RoIs among them (when there are enough)
    reg_fg_thresh: float  # 3D IoU from which a RoI is foreground and regressed
    cls_fg_thresh: float  # confidence target 1 from this IoU ...
    cls_bg_thresh: float  # ... 0 below this one (roi_iou: linear in between; binary: in between ignored)
    cls_bg_thresh_lo: float  # below: easy background; from here to reg_fg_thresh: hard background
    hard_bg_ratio: float  # share of hard background among the background RoIs
    cls_score_type: str  # roi_iou (IoU-guided confidence) or binary
    gt_jitter_copies: int  # jittered copies of each ground-truth box added as training RoIs
    gt_jitter: tuple[float, ...]  # their std: x y z (m), log sizes, heading (rad)

    @classmethod
    def read(cls, s: Section) -> TargetConfig:
        c = cls(roi_per_image=s.count("roi_per_image", 0), fg_ratio=s.fraction("fg_ratio", "a share"),
                reg_fg_thresh=s.fraction("reg_fg_thresh", "an IoU"),
                cls_fg_thresh=s.fraction("cls_fg_thresh", "an IoU"),
                cls_bg_thresh=s.fraction("cls_bg_thresh", "an IoU"),
                cls_bg_thresh_lo=s.fraction("cls_bg_thresh_lo", "an IoU"),
                hard_bg_ratio=s.fraction("hard_bg_ratio", "a share"),
                cls_score_type=s.choice("cls_score_type", CLS_SCORE_TYPES),
                gt_jitter_copies=s.count("gt_jitter_copies", 0),
                gt_jitter=tuple(float(v) for v in s.check(
                    "gt_jitter", lambda v: is_list_of(v, lambda x: is_number(x) and x >= 0) and len(v) == 7,
                    "7 standard deviations >= 0: x y z (m), log sizes, heading (rad)")))
        s.order("cls_bg_thresh", "cls_fg_thresh")
        s.order("cls_bg_thresh_lo", "cls_bg_thresh")
        return c


@dataclass(frozen=True)
class RefineLossWeights(StageConfig):
    """Multipliers of the second stage's loss terms (`roi_head.loss_weights`)."""

    rcnn_cls: float  # confidence binary cross-entropy
    rcnn_reg: float  # residual smooth-L1
    rcnn_corner: float  # corner loss

    @classmethod
    def read(cls, s: Section) -> RefineLossWeights:
        return cls(rcnn_cls=s.non_negative("rcnn_cls"), rcnn_reg=s.non_negative("rcnn_reg"),
                   rcnn_corner=s.non_negative("rcnn_corner"))


class Proposals(NamedTuple):
    rois: torch.Tensor  # (B, R, 7) boxes, PAD_ROI where mask is False
    scores: torch.Tensor  # (B, R) first-stage confidence in [0, 1] (0 for padding)
    mask: torch.Tensor  # (B, R) bool, True for real proposals
    dropped: torch.Tensor | None = None  # (B,) int64: first-stage boxes left out as non-finite (`finite_geometry`)


class RoiTargets(NamedTuple):
    rois: torch.Tensor  # (B, S, 7) sampled RoIs
    gt_of_rois: torch.Tensor  # (B, S, 7) the ground-truth box each RoI is matched to (zeros if none)
    iou: torch.Tensor  # (B, S) 3D IoU of RoI and its matched box
    reg_mask: torch.Tensor  # (B, S) bool: foreground, regressed (IoU >= reg_fg_thresh)
    cls_target: torch.Tensor  # (B, S) float confidence target in [0, 1]
    cls_mask: torch.Tensor  # (B, S) bool: contributes to the confidence loss
    valid: torch.Tensor  # (B, S) bool: a real RoI (False for padding of empty frames)


class RefineOutput(NamedTuple):
    cls_logits: torch.Tensor  # (B, R) confidence logits of the refined boxes
    box_deltas: torch.Tensor  # (B, R, 7) residuals in the RoI's canonical frame
    rois: torch.Tensor  # (B, R, 7) the RoIs refined
    roi_mask: torch.Tensor  # (B, R) bool, real RoIs
    targets: RoiTargets | None  # training targets of these RoIs (None in evaluation)


OUTPUT_STAGES = ("refined", "proposals")  # what `set_output_stage` accepts


class OutputStageSwitch:
    """`set_output_stage` of a two-stage detector (`detbench.train.detector.TwoStageDetector`):
    the model's `predict` returns its first stage's detections while `output_stage` is 'proposals'."""

    output_stage: str = "refined"

    def set_output_stage(self, stage: str) -> None:
        """'refined' (default): the second stage's boxes; 'proposals': the first stage's detections."""
        if stage not in OUTPUT_STAGES:
            raise ValueError(f"output stage must be 'refined' or 'proposals', got {stage!r}")
        self.output_stage = stage


# --------------------------------------------------------------------------------------
# proposals
# --------------------------------------------------------------------------------------
def finite_geometry(boxes: torch.Tensor) -> torch.Tensor:
    """(...,) bool: the box (..., 7) and the squares of its centre and size are finite in float32, so every
    derived length (a cylinder's radius, a corner, a BEV area) is finite too. A first stage that decodes a
    box to inf, or to 1e20 m (finite, but its BEV diagonal overflows), fails this."""
    b = boxes.float()
    return torch.isfinite(b).all(dim=-1) & torch.isfinite(b[..., :6].square().sum(dim=-1))


@torch.no_grad()
def select_proposals(boxes: torch.Tensor, scores: torch.Tensor, pre_nms_top_k: int, post_nms_top_k: int,
                     nms_threshold: float, valid: torch.Tensor | None = None) -> Proposals:
    """Per frame: the `pre_nms_top_k` best candidates, rotated BEV NMS, at most `post_nms_top_k`.

    boxes (B, A, 7), scores (B, A) in [0, 1], valid (B, A) bool or None (all valid).
    Returns padded `Proposals` with R = post_nms_top_k slots, best first. A valid candidate whose box fails
    `finite_geometry` or whose score is not finite is never proposed; `Proposals.dropped` counts them per
    frame, so a first stage that decodes a box to infinity costs that box, not the step or the evaluation.
    """
    b = boxes.shape[0]
    r = int(post_nms_top_k)
    device = boxes.device
    rois = torch.tensor(PAD_ROI, dtype=torch.float32, device=device).repeat(b, r, 1)
    out_scores = torch.zeros(b, r, dtype=torch.float32, device=device)
    mask = torch.zeros(b, r, dtype=torch.bool, device=device)
    dropped = []
    for i in range(b):
        ok = finite_geometry(boxes[i]) & torch.isfinite(scores[i])
        if valid is not None:
            dropped.append(int((valid[i] & ~ok).sum()))
            ok &= valid[i]
        else:
            dropped.append(int((~ok).sum()))
        idx = ok.nonzero(as_tuple=True)[0]
        if idx.numel() == 0:
            continue
        s = scores[i, idx].float()
        if s.numel() > pre_nms_top_k:
            s, order = s.topk(int(pre_nms_top_k))
            idx = idx[order]
        cand = boxes[i, idx].float().clone()
        cand[:, 3:6] = cand[:, 3:6].clamp(min=1e-2)
        cand[:, 6] = normalize_heading(cand[:, 6])
        kept = nms_bev(cand, s, nms_threshold, max_keep=r).to(device)
        k = kept.numel()
        rois[i, :k] = cand[kept]
        out_scores[i, :k] = s[kept]
        mask[i, :k] = True
    return Proposals(rois, out_scores, mask, torch.tensor(dropped, dtype=torch.int64, device=device))


@torch.no_grad()
def select_proposals_by_distance(boxes: torch.Tensor, scores: torch.Tensor, pre_nms_top_k: int, post_nms_top_k: int,
                                 nms_threshold: float, valid: torch.Tensor | None, distance: float,
                                 near_share: float) -> Proposals:
    """`select_proposals` with the budget split by range (PointRCNN's test-time proposals).

    Candidates whose box centre lies within `distance` metres of the sensor (BEV) get
    round(near_share * budget) of both the pre- and the post-NMS budget, the farther ones the
    rest, so near vehicles cannot take every slot. Near slots come first; a part that finds
    fewer proposals than its slots leaves them as padding.
    """
    ok = torch.ones(scores.shape, dtype=torch.bool, device=scores.device) if valid is None else valid
    near = torch.hypot(boxes[..., 0], boxes[..., 1]) <= float(distance)
    share = min(max(float(near_share), 0.0), 1.0)
    post_near = int(round(share * int(post_nms_top_k)))
    pre_near = int(round(share * int(pre_nms_top_k)))
    a = select_proposals(boxes, scores, pre_near, post_near, nms_threshold, ok & near)
    b = select_proposals(boxes, scores, int(pre_nms_top_k) - pre_near, int(post_nms_top_k) - post_near,
                         nms_threshold, ok & ~near)
    return Proposals(torch.cat([a.rois, b.rois], dim=1), torch.cat([a.scores, b.scores], dim=1),
                     torch.cat([a.mask, b.mask], dim=1), a.dropped + b.dropped)


def dropped_proposals_part(p: Proposals) -> dict[str, float]:
    """The loss part that logs `Proposals.dropped`: first-stage boxes left out as non-finite, per frame."""
    n = 0.0 if p.dropped is None else float(p.dropped.sum())
    return {"num_dropped_proposals": n / max(p.rois.shape[0], 1)}


# --------------------------------------------------------------------------------------
# proposal targets
# --------------------------------------------------------------------------------------
def _jitter_gt(gt: torch.Tensor, copies: int, std: list, gen: torch.Generator | None) -> torch.Tensor:
    if copies <= 0 or gt.shape[0] == 0:
        return gt.new_zeros(0, 7)
    rep = gt.repeat(copies, 1)
    noise = torch.randn(rep.shape, generator=gen, device="cpu").to(gt.device) * torch.tensor(std, device=gt.device)
    out = rep.clone()
    out[:, :3] += noise[:, :3]
    out[:, 3:6] = rep[:, 3:6] * torch.exp(noise[:, 3:6])
    out[:, 6] = normalize_heading(rep[:, 6] + noise[:, 6])
    return out


def _pick(idx: torch.Tensor, n: int, gen: torch.Generator | None, replace: bool) -> torch.Tensor:
    """n entries of idx: a random subset (without replacement when possible) or random draws."""
    if n <= 0 or idx.numel() == 0:
        return idx[:0]
    if replace or n > idx.numel():
        return idx[torch.randint(idx.numel(), (n,), generator=gen).to(idx.device)]
    return idx[torch.randperm(idx.numel(), generator=gen)[:n].to(idx.device)]


def confidence_targets(iou: torch.Tensor, cfg: TargetConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(target in [0, 1], mask) of the confidence branch for RoIs with 3D IoU `iou`.

    roi_iou (CT3D, the IoU-guided score): 1 at IoU >= cls_fg_thresh, 0 at IoU <= cls_bg_thresh,
    linear in between; every RoI counts. binary (PointRCNN): 1 from cls_fg_thresh, 0 below
    cls_bg_thresh, RoIs in between are ignored.
    """
    fg, bg = cfg.cls_fg_thresh, cfg.cls_bg_thresh
    if cfg.cls_score_type == "roi_iou":
        target = ((iou - bg) / max(fg - bg, 1e-6)).clamp(0.0, 1.0)
        return target, torch.ones_like(iou, dtype=torch.bool)
    if cfg.cls_score_type == "binary":
        target = (iou >= fg).float()
        return target, (iou >= fg) | (iou < bg)
    raise ValueError(f"cls_score_type must be 'roi_iou' or 'binary', got {cfg.cls_score_type!r}")


@torch.no_grad()
def sample_proposal_targets(proposals: Proposals, gt_boxes: torch.Tensor, gt_mask: torch.Tensor, cfg: TargetConfig,
                            generator: torch.Generator | None = None) -> RoiTargets:
    """Sample `roi_per_image` RoIs per frame and give each its training targets.

    Candidates are the frame's proposals (plus `gt_jitter_copies` jittered copies of each
    ground-truth box). Foreground: 3D IoU >= reg_fg_thresh; background: the rest, of which
    "hard" lies in [cls_bg_thresh_lo, reg_fg_thresh). With both kinds present,
    min(round(fg_ratio * S), #fg) foreground RoIs are drawn without replacement and the rest
    is background, hard_bg_ratio of it hard (each kind drawn with replacement, the other kind
    filling in when one is missing). With foreground only, S draws with replacement; with
    background only, S background draws. A frame with no candidate at all gets padding
    RoIs (valid False). Random draws use `generator` (a CPU torch.Generator) when given.
    """
    b = proposals.rois.shape[0]
    s = cfg.roi_per_image
    device = proposals.rois.device
    pad = torch.tensor(PAD_ROI, dtype=torch.float32, device=device)
    rois = pad.repeat(b, s, 1)
    gt_of = torch.zeros(b, s, 7, device=device)
    ious = torch.zeros(b, s, device=device)
    valid = torch.zeros(b, s, dtype=torch.bool, device=device)
    n_fg_want = int(round(cfg.fg_ratio * s))
    for i in range(b):
        gt = gt_boxes[i][gt_mask[i]].float()
        cand = torch.cat([proposals.rois[i][proposals.mask[i]].float(),
                          _jitter_gt(gt, cfg.gt_jitter_copies, list(cfg.gt_jitter), generator)])
        if cand.shape[0] == 0:
            continue
        if gt.shape[0]:
            iou = boxes_iou3d(cand, gt).float().to(device)
            max_iou, assign = iou.max(dim=1)
        else:
            max_iou = torch.zeros(cand.shape[0], device=device)
            assign = torch.zeros(cand.shape[0], dtype=torch.long, device=device)
        fg = (max_iou >= cfg.reg_fg_thresh).nonzero(as_tuple=True)[0]
        hard = ((max_iou < cfg.reg_fg_thresh) & (max_iou >= cfg.cls_bg_thresh_lo)).nonzero(as_tuple=True)[0]
        easy = (max_iou < cfg.cls_bg_thresh_lo).nonzero(as_tuple=True)[0]
        n_bg_avail = hard.numel() + easy.numel()
        if fg.numel() and n_bg_avail:
            take_fg = _pick(fg, min(n_fg_want, fg.numel()), generator, replace=False)
        elif fg.numel():
            take_fg = _pick(fg, s, generator, replace=True)
        else:
            take_fg = fg[:0]
        n_bg = s - take_fg.numel()
        if n_bg > 0 and n_bg_avail:
            n_hard = int(round(n_bg * cfg.hard_bg_ratio)) if easy.numel() else n_bg
            n_hard = n_hard if hard.numel() else 0
            take_bg = torch.cat([_pick(hard, n_hard, generator, replace=True),
                                 _pick(easy, n_bg - n_hard, generator, replace=True)])
        else:
            take_bg = fg[:0]
        take = torch.cat([take_fg, take_bg])
        k = take.numel()
        rois[i, :k] = cand[take]
        ious[i, :k] = max_iou[take]
        if gt.shape[0]:
            gt_of[i, :k] = gt[assign[take]]
        valid[i, :k] = True
    reg_mask = valid & (ious >= cfg.reg_fg_thresh)
    cls_target, cls_mask = confidence_targets(ious, cfg)
    return RoiTargets(rois, gt_of, ious, reg_mask, cls_target, cls_mask & valid, valid)


class RoIs(NamedTuple):
    proposals: Proposals  # after NMS
    rois: torch.Tensor  # (B, R, 7) what the second stage refines: sampled RoIs (training) or the proposals
    mask: torch.Tensor  # (B, R) bool, real RoIs
    targets: RoiTargets | None  # training targets of the RoIs (None in evaluation)


def rois_for_refinement(boxes: torch.Tensor, scores: torch.Tensor, valid: torch.Tensor | None,
                        proposals: ProposalConfig, targets: TargetConfig,
                        gt: tuple[torch.Tensor, torch.Tensor] | None,
                        test_split: tuple[float, float] | None = None) -> RoIs:
    """The step between the stages: proposals under the train or test budget, then (training)
    target sampling; the first stage's boxes (B, A, 7) and scores (B, A) are detached.

    `gt` is the batch's (gt_boxes (B, M, 7), gt_mask (B, M)) in training and None in evaluation,
    which uses the test budget and never sees the ground truth. `test_split` (distance m,
    near_share), or None, splits the test budget by range (`select_proposals_by_distance`).
    """
    if gt is None and test_split is not None:
        distance, near_share = test_split
        props = select_proposals_by_distance(boxes.detach(), scores.detach(), valid=valid,
                                             **_budget(proposals.test), distance=distance, near_share=near_share)
        return RoIs(props, props.rois, props.mask, None)
    props = select_proposals(boxes.detach(), scores.detach(), valid=valid,
                             **_budget(proposals.test if gt is None else proposals.train))
    if gt is None:
        return RoIs(props, props.rois, props.mask, None)
    sampled = sample_proposal_targets(props, gt[0], gt[1], targets)
    return RoIs(props, sampled.rois, sampled.valid, sampled)


def _budget(b: ProposalBudget) -> dict:
    return {"pre_nms_top_k": b.pre_nms_top_k, "post_nms_top_k": b.post_nms_top_k, "nms_threshold": b.nms_threshold}


# --------------------------------------------------------------------------------------
# canonical frame and residual coding
# --------------------------------------------------------------------------------------
def rotate_z(xyz: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate points (..., N, 3 or 2+) about z by `angle` (...) radians, counter-clockwise."""
    c, s = torch.cos(angle)[..., None], torch.sin(angle)[..., None]
    x, y = xyz[..., 0], xyz[..., 1]
    out = xyz.clone()
    out[..., 0] = x * c - y * s
    out[..., 1] = x * s + y * c
    return out


def _local_anchor(rois: torch.Tensor) -> torch.Tensor:
    a = torch.zeros_like(rois)
    a[..., 3:6] = rois[..., 3:6]
    return a


def fold_heading(h: torch.Tensor) -> torch.Tensor:
    """Heading difference folded into [-pi/2, pi/2] (a box turned by pi is the same box)."""
    h = normalize_heading(h)
    h = torch.where(h > math.pi / 2, h - math.pi, h)
    return torch.where(h < -math.pi / 2, h + math.pi, h)


def encode_refine_targets(gt: torch.Tensor, rois: torch.Tensor, coder: ResidualBoxCoder) -> torch.Tensor:
    """Residuals (..., 7) of ground truth `gt` (..., 7) in the canonical frame of `rois` (..., 7)."""
    local = gt.clone()
    local[..., :3] = rotate_z((gt[..., :3] - rois[..., :3])[..., None, :], -rois[..., 6])[..., 0, :]
    local[..., 6] = fold_heading(gt[..., 6] - rois[..., 6])
    return coder.encode(local, _local_anchor(rois))


def decode_refined(deltas: torch.Tensor, rois: torch.Tensor, coder: ResidualBoxCoder,
                   canonical: bool = False) -> torch.Tensor:
    """Boxes (..., 7) from residuals (..., 7) against `rois`; in the RoI frame if `canonical`."""
    d = torch.cat([deltas[..., :3], deltas[..., 3:6].clamp(-LOG_SIZE_CLAMP, LOG_SIZE_CLAMP), deltas[..., 6:]], dim=-1)
    local = coder.decode(d, _local_anchor(rois))
    if canonical:
        return local
    out = local.clone()
    out[..., :3] = rotate_z(local[..., None, :3], rois[..., 6])[..., 0, :] + rois[..., :3]
    out[..., 6] = normalize_heading(local[..., 6] + rois[..., 6])
    return out


# --------------------------------------------------------------------------------------
# the second stage's loss (the loss functions themselves live in losses.py)
# --------------------------------------------------------------------------------------
def refine_loss(out: RefineOutput, coder: ResidualBoxCoder, weights: RefineLossWeights) -> tuple[torch.Tensor, dict]:
    """Loss of the second stage: confidence BCE + residual smooth-L1 + corner loss.

    The confidence loss averages over RoIs with a confidence target; the regression terms
    average over foreground RoIs. Frames with no RoI (or no foreground) contribute 0.
    """
    t = out.targets
    w = weights
    logits = out.cls_logits.float()
    cm = t.cls_mask.float()
    bce = F.binary_cross_entropy_with_logits(logits, t.cls_target, reduction="none")
    loss_cls = (bce * cm).sum() / cm.sum().clamp(min=1.0)
    fg = t.reg_mask
    n_fg = fg.sum().clamp(min=1).float()
    deltas = out.box_deltas.float()
    target = encode_refine_targets(t.gt_of_rois, t.rois, coder)
    target = torch.where(fg[..., None], target, torch.zeros_like(target))
    loss_reg = weighted_smooth_l1(deltas, target, fg.float()) / n_fg
    if fg.any():
        pred_local = decode_refined(deltas[fg], t.rois[fg], coder, canonical=True)
        gt_local = t.gt_of_rois[fg].clone()
        gt_local[:, :3] = rotate_z((gt_local[:, :3] - t.rois[fg][:, :3])[:, None, :], -t.rois[fg][:, 6])[:, 0, :]
        gt_local[:, 6] = gt_local[:, 6] - t.rois[fg][:, 6]
        loss_corner = corner_loss(pred_local, gt_local).sum() / n_fg
    else:
        loss_corner = deltas.sum() * 0.0
    total = w.rcnn_cls * loss_cls + w.rcnn_reg * loss_reg + w.rcnn_corner * loss_corner
    parts = {"loss_rcnn_cls": float(loss_cls.detach()), "loss_rcnn_reg": float(loss_reg.detach()),
             "loss_rcnn_corner": float(loss_corner.detach()), "num_fg_rois": float(fg.sum()) / max(fg.shape[0], 1)}
    return total, parts


# --------------------------------------------------------------------------------------
# the refinement head and prediction
# --------------------------------------------------------------------------------------
class RefineHead(nn.Module):
    """Confidence and residual-box branches on one feature vector per RoI.

    Each branch: `len(fc)` fully connected layers (BatchNorm-free: LayerNorm is stable with
    few RoIs) with ReLU and dropout, then a linear output. The box branch's last layer starts
    near zero (std 0.001) so the first refinements are small.
    """

    def __init__(self, in_channels: int, fc: Sequence[int], dropout: float, code_size: int = 7):
        super().__init__()
        self.cls = self._branch(in_channels, fc, dropout, 1)
        self.reg = self._branch(in_channels, fc, dropout, code_size)
        nn.init.normal_(self.reg[-1].weight, std=0.001)
        nn.init.zeros_(self.reg[-1].bias)

    @staticmethod
    def _branch(cin: int, fc: Sequence[int], dropout: float, cout: int) -> nn.Sequential:
        layers: list[nn.Module] = []
        for c in fc:
            layers += [nn.Linear(cin, c), nn.LayerNorm(c), nn.ReLU(inplace=True)]
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
            cin = c
        layers.append(nn.Linear(cin, cout))
        return nn.Sequential(*layers)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """features (..., C) -> (cls logits (...), box residuals (..., code_size))."""
        return self.cls(features).squeeze(-1), self.reg(features)


@torch.no_grad()
def predict_refined(out: RefineOutput, coder: ResidualBoxCoder, post: PostConfig) -> list[Detections]:
    """Decoded refined boxes, sigmoid confidence, the detector's final NMS, per frame."""
    boxes = decode_refined(out.box_deltas.float(), out.rois.float(), coder)
    scores = torch.sigmoid(out.cls_logits.float())
    dets = []
    for i in range(boxes.shape[0]):
        m = out.roi_mask[i]
        dets.append(post.select(boxes[i][m], scores[i][m]))
    return dets
