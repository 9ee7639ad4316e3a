"""The typed hand-offs between the data pipeline and a detector: `Sample`, `Batch`, `Detections`.

```
TrainingSet[i] -> Sample (numpy, one frame) --collate--> Batch (torch, B frames)
model.forward(Batch) -> outputs; model.predict(outputs, Batch) -> list[Detections], one per frame
```

Shapes and units (ego ground frame, metres, radians; docs/architecture.md, Conventions):

- `Sample.points` (N, 4) float32 x, y, z, intensity; `Sample.gt_boxes` (M, 7) float32
  x, y, z, dx, dy, dz, heading.
- `Batch.points` (P, 5) float32 [batch_index, x, y, z, intensity], the frames' points
  concatenated in batch order (OpenPCDet's layout, so voxelizers can scatter by column 0).
- `Batch.gt_boxes` (B, Mmax, 7) float32, padded with zero rows; `Batch.gt_mask` (B, Mmax)
  bool marks the real boxes (Mmax = the largest box count of the batch, possibly 0).
  Padding rather than a list keeps target assignment vectorised; `boxes_of(i)` gives the
  (Mi, 7) boxes of one frame.
- `Detections` per frame (detbench/data/detections.py): `boxes` (K, 7) float32, `scores` (K,)
  float32 in [0, 1], `labels` (K,) int64 class indices (the model documents its class list).
"""
from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from detbench.data.detections import Detections

__all__ = ["Sample", "Batch", "Detections", "collate"]


class Sample(NamedTuple):
    """One frame ready for collation (after GT filtering, augmentation and cropping)."""

    points: np.ndarray  # (N, 4) float32 x, y, z, intensity
    gt_boxes: np.ndarray  # (M, 7) float32 x, y, z, dx, dy, dz, heading
    frame_id: str


@dataclass
class Batch:
    """B frames for a detector. See the module docstring for shapes; all tensors share a device."""

    points: torch.Tensor  # (P, 5) float32 [batch_index, x, y, z, intensity]
    gt_boxes: torch.Tensor  # (B, Mmax, 7) float32, zero rows where gt_mask is False
    gt_mask: torch.Tensor  # (B, Mmax) bool, True for real boxes
    frame_ids: list[str]
    batch_size: int

    @property
    def device(self) -> torch.device:
        return self.points.device

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Batch:
        """A copy with every tensor on `device` (frame ids shared)."""
        return Batch(self.points.to(device, non_blocking=non_blocking),
                     self.gt_boxes.to(device, non_blocking=non_blocking),
                     self.gt_mask.to(device, non_blocking=non_blocking),
                     list(self.frame_ids), self.batch_size)

    def pin_memory(self) -> Batch:
        """Page-locked copy (DataLoader(pin_memory=True) calls this for faster CUDA copies)."""
        return Batch(self.points.pin_memory(), self.gt_boxes.pin_memory(), self.gt_mask.pin_memory(),
                     list(self.frame_ids), self.batch_size)

    def points_of(self, i: int) -> torch.Tensor:
        """(Ni, 4) x, y, z, intensity of frame `i`."""
        self._check_index(i)
        return self.points[self.points[:, 0] == i, 1:]

    def boxes_of(self, i: int) -> torch.Tensor:
        """(Mi, 7) ground-truth boxes of frame `i` (padding removed)."""
        self._check_index(i)
        return self.gt_boxes[i][self.gt_mask[i]]

    def num_boxes(self) -> torch.Tensor:
        """(B,) int64 number of real ground-truth boxes per frame."""
        return self.gt_mask.sum(dim=1)

    def _check_index(self, i: int) -> None:
        if not 0 <= i < self.batch_size:
            raise IndexError(f"frame index {i} out of range for a batch of {self.batch_size}")


def _as_sample(s, k: int) -> Sample:
    if not isinstance(s, tuple) or len(s) != 3:
        raise TypeError(f"collate: sample {k} must be a (points, gt_boxes, frame_id) tuple, "
                        f"got {type(s).__name__}")
    points, boxes, frame_id = s
    points = np.asarray(points)
    boxes = np.asarray(boxes)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"collate: sample {k} ({frame_id}) points must be (N, 4) x, y, z, intensity, "
                         f"got shape {points.shape}")
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        if boxes.size == 0:
            boxes = boxes.reshape(0, 7)
        else:
            raise ValueError(f"collate: sample {k} ({frame_id}) gt_boxes must be (M, 7), got shape {boxes.shape}")
    return Sample(points, boxes, str(frame_id))


def collate(samples: Sequence[Sample]) -> Batch:
    """Stack samples into a `Batch` (CPU tensors); use as `DataLoader(collate_fn=collate)`.

    Args:
        samples: B >= 1 `Sample`s (or plain (points (N, 4), gt_boxes (M, 7), frame_id) tuples).
    Returns:
        Batch with points (P, 5) float32 [batch_index, x, y, z, intensity], gt_boxes
        (B, Mmax, 7) float32 zero-padded, gt_mask (B, Mmax) bool.
    """
    if len(samples) == 0:
        raise ValueError("collate: got an empty list of samples; a batch needs at least one frame")
    samples = [_as_sample(s, k) for k, s in enumerate(samples)]
    b = len(samples)
    n_total = sum(int(s.points.shape[0]) for s in samples)
    m_max = max(int(s.gt_boxes.shape[0]) for s in samples)
    points = np.empty((n_total, 5), dtype=np.float32)
    gt_boxes = np.zeros((b, m_max, 7), dtype=np.float32)
    gt_mask = np.zeros((b, m_max), dtype=bool)
    start = 0
    for i, s in enumerate(samples):
        n = s.points.shape[0]
        points[start:start + n, 0] = i
        points[start:start + n, 1:] = s.points
        start += n
        m = s.gt_boxes.shape[0]
        gt_boxes[i, :m] = s.gt_boxes
        gt_mask[i, :m] = True
    return Batch(torch.from_numpy(points), torch.from_numpy(gt_boxes), torch.from_numpy(gt_mask),
                 [s.frame_id for s in samples], b)
