"""Run a detector over frames: the one prediction path of evaluation, the study and benchmarks."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from detbench.data.augment import crop_to_range
from detbench.data.batch import Sample, collate
from detbench.data.frame import Frame


def frame_sample(frame: Frame, point_cloud_range: Sequence[float]) -> Sample:
    """A frame's points cropped to the model's range, with no ground truth (inference input)."""
    points = np.asarray(frame.points, dtype=np.float32)
    points, _, _ = crop_to_range(points, np.zeros((0, 7), np.float32), point_cloud_range)
    return Sample(np.ascontiguousarray(points), np.zeros((0, 7), np.float32), frame.frame_id)


@torch.no_grad()
def predict_frames(model: nn.Module, frames: Sequence[Frame], point_cloud_range: Sequence[float],
                   device: torch.device | str = "cpu", batch_size: int = 4, progress: bool = True,
                   desc: str = "predict") -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{frame_id: (boxes (K, 7) float32, scores (K,) float32)} for every frame, in eval mode.

    `frames` is any sequence of Frames (e.g. a Height3Dataset split). The model follows the
    detector contract (`Detector`, detbench/train/detector.py). The model's train/eval mode is restored.
    """
    was_training = model.training
    model.eval()
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    n = len(frames)
    bar = tqdm(total=n, desc=desc, unit="frame", disable=not progress, leave=False, dynamic_ncols=True)
    try:
        for start in range(0, n, batch_size):
            samples = [frame_sample(frames[i], point_cloud_range) for i in range(start, min(n, start + batch_size))]
            batch = collate(samples).to(device)
            dets = model.predict(model(batch), batch)
            for s, d in zip(samples, dets):
                boxes, scores, _ = d.numpy()
                out[s.frame_id] = (boxes, scores)
            bar.update(len(samples))
    finally:
        bar.close()
        model.train(was_training)
    return out
