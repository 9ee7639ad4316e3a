"""The detector contract: what the training loop, inference and the benchmark ask of a model.

A detector is an `nn.Module` that satisfies `Detector` (models/ registers one per file;
tests/models/test_contract.py checks every registered model against it). Nothing else
of a model is used by `detbench.train.train`, `detbench.train.inference.predict_frames`
or tools/benchmark.py. A two-stage detector also satisfies `TwoStageDetector`: it can
predict its first stage's boxes instead of the refined ones (tools/eval.py --stage).

Data in (detbench.data.batch):

    Batch.points    (P, 5) float32 [batch_index, x, y, z, intensity], frames concatenated in order
    Batch.gt_boxes  (B, Mmax, 7) float32 x y z dx dy dz heading, zero rows as padding
    Batch.gt_mask   (B, Mmax) bool, True for real boxes (Mmax may be 0)
    Batch.frame_ids list[str]; Batch.batch_size int; Batch.to(device); Batch.boxes_of(i) -> (Mi, 7)

The ground truth in a Batch is the LiDAR-detected vehicles (`detbench.data.regions`: >= 1
point inside the box with its bottom raised 0.05 m), cropped to the model's point-cloud
range. Units: metres and radians in the ego ground frame (x forward, y left, z up; heading
counter-clockwise from +x in [-pi, pi)).
"""
from __future__ import annotations

from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from detbench.data.batch import Batch, Detections

__all__ = ["Detector", "TwoStageDetector", "channels_last_2d"]


@runtime_checkable
class Detector(Protocol):
    """A 3D detector as the library uses it (an `nn.Module` with these members).

    `outputs` is whatever `forward` returns (a NamedTuple of tensors, documented by the
    model); `loss` and `predict` receive it unchanged, with the same batch.
    """

    # top-level child modules per named stage, in order, for tools/benchmark.py's latency
    # split, e.g. {"voxelize": ["vfe"], "backbone3d": ["backbone3d"], "head": ["head"]}
    STAGES: ClassVar[dict[str, list[str]]]

    def forward(self, batch: Batch) -> Any:
        """Raw head outputs for the batch. In training mode a two-stage model may read
        `batch.gt_boxes` / `gt_mask` here (proposal target sampling); in eval mode it must not."""
        ...

    def loss(self, outputs: Any, batch: Batch) -> tuple[torch.Tensor, dict[str, float]]:
        """(total: scalar tensor to back-propagate, parts: name -> float for logging).

        Finite for frames without points or without boxes; `parts` has the same keys at
        every step (they are averaged over ranks by key). Losses are plain functions
        (models/stages/losses.py); a head keeps no loss state.
        """
        ...

    def predict(self, outputs: Any, batch: Batch) -> list[Detections]:
        """One `Detections` per frame in batch order: boxes (K, 7) float32, scores (K,) in
        [0, 1], labels (K,) int64 (the model documents its class list)."""
        ...

    @staticmethod
    def prepare_config(model_cfg: dict, train_boxes: np.ndarray) -> dict:
        """A copy of the `model:` config section with data-derived values filled in from the
        training split's LiDAR-detected boxes (N, 7) (e.g. SECOND's `anchor_sizes: auto`).
        Called once before the model is built; the result is stored in the checkpoint so
        evaluation rebuilds the same model. A model with nothing to derive returns a copy."""
        ...


@runtime_checkable
class TwoStageDetector(Detector, Protocol):
    """A detector with a proposal stage and a refinement stage (PointRCNN, CT3D): `predict`
    returns either stage's boxes. models/stages/two_stage.py implements the switch once
    (`OutputStageSwitch`); tools check for it with `isinstance(model, TwoStageDetector)`.

    Its outputs carry `proposals.dropped`, per frame the first-stage boxes left out between the stages
    because their geometry is not finite; `predict_frames` reports them, and its `loss` logs them
    (`num_dropped_proposals`)."""

    def set_output_stage(self, stage: str) -> None:
        """'refined' (the default): `predict` returns the second stage's boxes; 'proposals': the
        first stage's detections, through the same final selection. Any other stage is a ValueError."""
        ...


def channels_last_2d(model: nn.Module) -> nn.Module:
    """`model` with the weights of its 2D (transposed) convolutions in channels-last memory format (NHWC), in
    place: a dense BEV map meeting them runs through the NHWC convolution kernels, and the ops after keep its
    format (train.channels_last, tools/benchmark.py --channels-last). The sparse and point layers' weights
    (other ranks) stay as they are; the outputs are the contiguous model's up to float32 summation order."""
    for m in model.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            m.to(memory_format=torch.channels_last)
    return model
