"""The shared second stage (models/stages/two_stage.py): proposals, target sampling, coding, losses."""
import math

import numpy as np
import pytest
import torch

from detbench.ops import ResidualBoxCoder, boxes_iou3d, from_canonical, to_canonical
from detbench.train.run_config import load_run_config
from models.stages.losses import corner_loss
from models.stages.two_stage import (
    PAD_ROI, Proposals, RefineLossWeights, RefineOutput, TargetConfig, confidence_targets, decode_refined,
    encode_refine_targets, fold_heading, refine_loss, sample_proposal_targets, select_proposals,
)

CAR = [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.3]
TARGETS = load_run_config("ct3d", "paper")["model"]["roi_head"]["targets"]  # the published values


def targets_cfg(**over) -> TargetConfig:
    return TargetConfig.from_config({**TARGETS, **over}, "model.roi_head.targets")


def proposals_of(rows, b=1):
    rois = torch.tensor(rows, dtype=torch.float32).reshape(b, -1, 7)
    return Proposals(rois, torch.ones(rois.shape[:2]), torch.ones(rois.shape[:2], dtype=torch.bool))


def shifted(box, dx=0.0, dy=0.0, dh=0.0):
    x, y, z, length, w, h, r = box
    c, s = math.cos(r), math.sin(r)
    return [x + c * dx - s * dy, y + s * dx + c * dy, z, length, w, h, r + dh]


def test_select_proposals_budgets_nms_and_padding():
    boxes = torch.tensor([[CAR, shifted(CAR, 0.1), shifted(CAR, 20.0), [float("nan")] * 7]])
    scores = torch.tensor([[0.9, 0.8, 0.7, 0.99]])
    p = select_proposals(boxes, scores, pre_nms_top_k=10, post_nms_top_k=4, nms_threshold=0.5)
    assert p.rois.shape == (1, 4, 7) and p.mask.tolist() == [[True, True, False, False]]
    assert torch.allclose(p.scores[0, :2], torch.tensor([0.9, 0.7]))  # the near duplicate is suppressed, NaN dropped
    assert torch.allclose(p.rois[0, 2], torch.tensor(PAD_ROI))
    p = select_proposals(boxes, scores, pre_nms_top_k=1, post_nms_top_k=4, nms_threshold=0.5)
    assert int(p.mask.sum()) == 1  # only the best finite candidate survives the pre-NMS budget


def test_target_sampling_keeps_the_requested_ratio():
    torch.manual_seed(0)
    gt = torch.tensor([[CAR]])
    fg = [shifted(CAR, dx) for dx in np.linspace(-0.3, 0.3, 40)]  # IoU > 0.55
    hard = [shifted(CAR, dx) for dx in np.linspace(2.0, 2.8, 40)]  # 0.1 <= IoU < 0.55
    easy = [shifted(CAR, 30.0 + dx) for dx in range(40)]  # IoU 0
    props = proposals_of(fg + hard + easy)
    cfg = targets_cfg(roi_per_image=64, fg_ratio=0.25, hard_bg_ratio=0.75)
    t = sample_proposal_targets(props, gt, torch.ones(1, 1, dtype=torch.bool), cfg)
    iou = t.iou[0]
    assert t.valid.all() and int((iou >= 0.55).sum()) == 16  # round(0.25 * 64)
    bg = iou < 0.55
    assert int((bg & (iou >= 0.1)).sum()) == 36 and int((iou < 0.1).sum()) == 12  # 0.75 of the 48 are hard
    assert torch.equal(t.reg_mask[0], iou >= 0.55)
    # the IoU stored is the RoI's 3D IoU with the box it is matched to
    assert torch.allclose(iou, boxes_iou3d(t.rois[0], gt[0]).max(dim=1).values.float(), atol=1e-5)
    # foreground only: all slots foreground (drawn with replacement); nothing: padding, invalid
    t = sample_proposal_targets(proposals_of(fg[:3]), gt, torch.ones(1, 1, dtype=torch.bool), cfg)
    assert bool(t.reg_mask.all())
    empty = Proposals(torch.zeros(1, 0, 7), torch.zeros(1, 0), torch.zeros(1, 0, dtype=torch.bool))
    t = sample_proposal_targets(empty, torch.zeros(1, 0, 7), torch.zeros(1, 0, dtype=torch.bool), cfg)
    assert not t.valid.any() and not t.cls_mask.any()


def test_iou_guided_confidence_targets_on_hand_made_boxes():
    iou = torch.tensor([0.0, 0.25, 0.5, 0.75, 0.9])
    target, mask = confidence_targets(iou, targets_cfg(cls_score_type="roi_iou"))
    assert torch.allclose(target, torch.tensor([0.0, 0.0, 0.5, 1.0, 1.0])) and mask.all()
    target, mask = confidence_targets(iou, targets_cfg(cls_score_type="binary", cls_fg_thresh=0.75, cls_bg_thresh=0.25))
    assert target.tolist() == [0, 0, 0, 1, 1] and mask.tolist() == [True, False, False, True, True]
    # a RoI equal to the car: target 1; shifted by half its length: IoU 1/3, target (1/3 - 0.25) / 0.5
    gt = torch.tensor([[CAR]])
    t = sample_proposal_targets(proposals_of([CAR, shifted(CAR, 2.25)]), gt, torch.ones(1, 1, dtype=torch.bool),
                                targets_cfg(roi_per_image=2, fg_ratio=0.5))
    pairs = sorted(zip(t.iou[0].tolist(), t.cls_target[0].tolist()))
    assert pairs[0] == (pytest.approx(1 / 3, abs=1e-4), pytest.approx((1 / 3 - 0.25) / 0.5, abs=1e-4))
    assert pairs[1] == (pytest.approx(1.0, abs=1e-5), pytest.approx(1.0))


def test_canonical_transform_round_trips():
    g = torch.Generator().manual_seed(1)
    rois = (torch.rand(3, 7, generator=g) * torch.tensor([50, 20, 2, 5, 2, 2, 6.28])
            - torch.tensor([0, 10, 0, 0, 0, 0, 3.14]))
    pts = torch.rand(3, 50, 4, generator=g) * 40
    local = to_canonical(pts[..., :3], rois)
    assert torch.allclose(from_canonical(local, rois), pts[..., :3], atol=1e-4)
    # a point at the RoI's centre + 1 m along its heading lands at (1, 0) in the RoI frame
    ahead = rois[:, None, :3].clone()
    ahead[..., 0] += torch.cos(rois[:, 6:7])
    ahead[..., 1] += torch.sin(rois[:, 6:7])
    assert torch.allclose(to_canonical(ahead, rois)[..., :2], torch.tensor([1.0, 0.0]).expand(3, 1, 2), atol=1e-5)


def test_refine_coding_round_trips_up_to_a_half_turn():
    coder = ResidualBoxCoder()
    rois = torch.tensor([CAR, [40.0, -5.0, 1.5, 12.0, 2.5, 3.5, -2.9]])
    gts = torch.tensor([shifted(CAR, 0.4, -0.2, 0.2), [40.6, -4.5, 1.7, 11.0, 2.6, 3.6, 0.4]])  # second: turned ~pi
    deltas = encode_refine_targets(gts, rois, coder)
    assert deltas[:, 6].abs().max() <= math.pi / 2 + 1e-6
    back = decode_refined(deltas, rois, coder)
    assert torch.allclose(back[:, :6], gts[:, :6], atol=1e-4)
    assert torch.allclose(torch.sin(2 * back[:, 6]), torch.sin(2 * gts[:, 6]), atol=1e-4)
    assert fold_heading(torch.tensor(3.0)).item() == pytest.approx(3.0 - math.pi)


def test_corner_loss_zero_for_the_box_and_its_half_turn_and_bounded_gradient():
    gt = torch.tensor([CAR, CAR])
    pred = torch.tensor([CAR, shifted(CAR, 0, 0, math.pi)], requires_grad=True)
    assert torch.allclose(corner_loss(pred, gt), torch.zeros(2), atol=1e-5)
    assert float(corner_loss(torch.tensor([shifted(CAR, 1.0)]), gt[:1])) > 0.4
    # a wild early prediction: the decode clamps the size residual and Huber bounds the gradient
    coder = ResidualBoxCoder()
    deltas = torch.tensor([[50.0, -40.0, 30.0, 80.0, 80.0, 80.0, 3.0]], requires_grad=True)
    box = decode_refined(deltas, gt[:1], coder, canonical=True)
    loss = corner_loss(box, torch.tensor([[0.0, 0.0, 0.0, 4.5, 1.9, 1.6, 0.0]])).sum()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(deltas.grad).all()
    assert float(deltas.grad.abs().max()) < 100.0


def test_refine_loss_finite_without_rois_or_foreground():
    coder = ResidualBoxCoder()
    empty = Proposals(torch.zeros(2, 0, 7), torch.zeros(2, 0), torch.zeros(2, 0, dtype=torch.bool))
    t = sample_proposal_targets(empty, torch.zeros(2, 0, 7), torch.zeros(2, 0, dtype=torch.bool),
                                targets_cfg(roi_per_image=4))
    cls = torch.zeros(2, 4, requires_grad=True)
    reg = torch.zeros(2, 4, 7, requires_grad=True)
    total, parts = refine_loss(RefineOutput(cls, reg, t.rois, t.valid, t), coder, RefineLossWeights(1.0, 1.0, 1.0))
    total.backward()
    assert torch.isfinite(total) and float(total.detach()) == 0.0 and parts["num_fg_rois"] == 0
    assert torch.isfinite(cls.grad).all() and torch.isfinite(reg.grad).all()


def test_target_config_must_be_complete():
    with pytest.raises(ValueError, match="model.roi_head.targets.fg_ratio is missing"):
        TargetConfig.from_config({k: v for k, v in TARGETS.items() if k != "fg_ratio"}, "model.roi_head.targets")
