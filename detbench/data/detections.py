"""`Detections`: the boxes, scores and class labels of one frame, from the detector to the evaluator.

```
model.predict(outputs, Batch) -> list[Detections]   torch tensors on the model's device, one per frame
Detections.numpy()            -> Detections         numpy arrays on the host: what the evaluator, the
                                                    prediction files and the studies take
```

Shapes and units (ego ground frame, metres, radians; docs/architecture.md, Conventions):
`boxes` (K, 7) x, y, z, dx, dy, dz, heading; `scores` (K,) confidence in [0, 1]; `labels` (K,)
int64 class index (the model documents its class list; every detbench model predicts one class,
0). A model's tensors are float32; predictions read from a file are float64 (`from_arrays`), with
labels 0, since a file's class names are not read. The evaluator converts either to float64.

The module imports no torch: the evaluator and the prediction files use `Detections` without
loading it; `empty` and `to` need torch and import it when called.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    import torch

    Array = torch.Tensor | np.ndarray

__all__ = ["Detections"]


class Detections(NamedTuple):
    """A detector's output for one frame: torch tensors from `model.predict`, numpy arrays after `numpy()`."""

    boxes: Array  # (K, 7) x, y, z, dx, dy, dz, heading
    scores: Array  # (K,) confidence in [0, 1]
    labels: Array  # (K,) int64 class index

    @staticmethod
    def empty(device: torch.device | str = "cpu") -> Detections:
        """No detections: (0, 7), (0,), (0,) tensors on `device`."""
        import torch

        return Detections(torch.zeros((0, 7), dtype=torch.float32, device=device),
                          torch.zeros((0,), dtype=torch.float32, device=device),
                          torch.zeros((0,), dtype=torch.int64, device=device))

    @staticmethod
    def from_arrays(boxes, scores, labels=None) -> Detections:
        """Numpy detections of boxes (K, 7) and scores (K,) as given (no copy when they are arrays already);
        `labels` None: class 0 for every box."""
        boxes, scores = np.asarray(boxes), np.asarray(scores)
        labels = np.zeros(len(scores), dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
        return Detections(boxes, scores, labels)

    def to(self, device: torch.device | str) -> Detections:
        """The same detections on `device` (torch tensors)."""
        return Detections(self.boxes.to(device), self.scores.to(device), self.labels.to(device))

    def numpy(self) -> Detections:
        """The same detections as numpy arrays on the host: boxes (K, 7) float32, scores (K,) float32, labels
        (K,) int64 from a model's tensors; numpy detections are returned as they are."""
        if isinstance(self.boxes, np.ndarray):
            return self
        return Detections(self.boxes.detach().cpu().float().numpy(), self.scores.detach().cpu().float().numpy(),
                          self.labels.detach().cpu().long().numpy())
