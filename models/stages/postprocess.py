"""Post-processing shared by all heads: score threshold, top-k, rotated BEV NMS.

`PostConfig` is the `post:` block of every model's YAML (its score threshold is also the floor
under the evaluator's: a box scored below it never leaves the model).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from detbench.data.batch import Detections
from detbench.ops import nms_bev, normalize_heading

from .config import Section, StageConfig


@dataclass(frozen=True)
class PostConfig(StageConfig):
    """The final selection of a detector's boxes (`model.post`)."""

    score_threshold: float  # candidates scoring below are dropped
    pre_nms_top_k: int  # the best candidates that enter NMS
    nms_threshold: float  # BEV IoU above which the lower-scored box is suppressed
    post_nms_top_k: int  # at most this many detections per frame

    @classmethod
    def read(cls, s: Section) -> PostConfig:
        return cls(score_threshold=s.fraction("score_threshold"), pre_nms_top_k=s.count("pre_nms_top_k"),
                   nms_threshold=s.fraction("nms_threshold", "an IoU"), post_nms_top_k=s.count("post_nms_top_k"))

    def select(self, boxes: torch.Tensor, scores: torch.Tensor) -> Detections:
        """`select_detections` of one frame's candidates under these settings."""
        return select_detections(boxes, scores, self.score_threshold, self.pre_nms_top_k, self.nms_threshold,
                                 self.post_nms_top_k)


def select_detections(boxes: torch.Tensor, scores: torch.Tensor, score_threshold: float, pre_nms_top_k: int,
                      nms_threshold: float, post_nms_top_k: int, labels: torch.Tensor | None = None) -> Detections:
    """One frame's candidates (A, 7) boxes and (A,) scores in [0, 1] -> `Detections`.

    Keeps scores >= `score_threshold`, the `pre_nms_top_k` best, rotated BEV NMS at
    `nms_threshold` (IoU), then at most `post_nms_top_k`, highest score first. Headings are
    wrapped to [-pi, pi). Non-finite boxes are dropped rather than passed on.
    """
    device = boxes.device
    if labels is None:
        labels = torch.zeros(scores.shape[0], dtype=torch.int64, device=device)
    keep = (scores >= score_threshold) & torch.isfinite(boxes).all(dim=1) & torch.isfinite(scores)
    boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
    if scores.numel() == 0:
        return Detections.empty(device)
    if scores.numel() > pre_nms_top_k:
        scores, order = scores.topk(pre_nms_top_k)
        boxes, labels = boxes[order], labels[order]
    boxes = boxes.float().clone()
    boxes[:, 3:6] = boxes[:, 3:6].clamp(min=1e-3)
    boxes[:, 6] = normalize_heading(boxes[:, 6])
    kept = nms_bev(boxes.detach(), scores.detach(), nms_threshold, max_keep=post_nms_top_k)
    return Detections(boxes[kept].detach(), scores[kept].detach().float(), labels[kept])
