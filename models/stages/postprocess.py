"""Post-processing shared by all heads: score threshold, top-k, rotated BEV NMS."""
from __future__ import annotations

import torch

from detbench.data.batch import Detections
from detbench.ops import nms_bev, normalize_heading


def select_detections(boxes: torch.Tensor, scores: torch.Tensor, score_threshold: float = 0.1,
                      pre_nms_top_k: int = 1000, nms_threshold: float = 0.1, post_nms_top_k: int = 100,
                      labels: torch.Tensor | None = None) -> Detections:
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
