"""Run a detector over frames: the one prediction path of evaluation, the study and benchmarks.

Non-finite model outputs are never dropped silently: post-processing leaves NaN / inf boxes
out of the detections, so a model with broken weights would look merely untrained;
`predict_frames` counts them in the raw outputs and raises `NonFiniteOutputError` naming
the frames. A two-stage model's first-stage boxes that decode to non-finite geometry are left
out between its stages (one wild box is not broken weights); `predict_frames` prints their
count as a warning.
"""
from __future__ import annotations

import dataclasses
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from detbench.data.batch import Sample, collate
from detbench.data.detections import Detections
from detbench.data.errors import DatasetError
from detbench.data.frame import Frame
from detbench.data.road import RoadConfig, crop_model_input
from detbench.train.detector import TwoStageDetector
from detbench.utils.cli import UserError


def frame_sample(frame: Frame, point_cloud_range: Sequence[float], road: RoadConfig | None = None) -> Sample:
    """A frame's points cropped to the model's range, without the road when `road.drop`, with no ground
    truth (inference input; the same preparation as a training sample's, `crop_model_input`)."""
    points = np.asarray(frame.points, dtype=np.float32)
    points, _, _ = crop_model_input(points, np.zeros((0, 7), np.float32), point_cloud_range, road)
    return Sample(np.ascontiguousarray(points), np.zeros((0, 7), np.float32), frame.frame_id)


class NonFiniteOutputError(FloatingPointError):
    """The model's outputs held NaN or inf for some frames (broken weights or a diverged run)."""


def dropped_proposals(outputs: Any) -> int:
    """First-stage boxes a two-stage model left out between its stages as non-finite (`TwoStageDetector`);
    0 for a one-stage model."""
    dropped = getattr(getattr(outputs, "proposals", None), "dropped", None)
    return 0 if dropped is None else int(dropped.sum())


def count_nonfinite(outputs: Any) -> int:
    """NaN / inf values in the floating-point tensors of a model's outputs (dataclasses, named tuples,
    dicts and sequences are searched)."""
    if isinstance(outputs, torch.Tensor):
        return int((~torch.isfinite(outputs)).sum()) if outputs.is_floating_point() else 0
    if dataclasses.is_dataclass(outputs) and not isinstance(outputs, type):
        outputs = [getattr(outputs, f.name) for f in dataclasses.fields(outputs)]
    elif isinstance(outputs, dict):
        outputs = list(outputs.values())
    if isinstance(outputs, (list, tuple)):
        return sum(count_nonfinite(o) for o in outputs)
    return 0


@torch.no_grad()
def predict_frames(model: nn.Module, frames: Sequence[Frame], point_cloud_range: Sequence[float],
                   device: torch.device | str = "cpu", batch_size: int = 4, progress: bool = True,
                   desc: str = "predict", road: RoadConfig | None = None
                   ) -> dict[str, Detections]:
    """{frame_id: numpy Detections (boxes (K, 7) float32, scores (K,) float32, labels (K,) int64)} for every
    frame, in eval mode.

    `frames` is any sequence of Frames (e.g. a Height3Dataset split); `road` is the model's road setting
    (`RoadConfig.of_run_config` of its run config: a model trained without road points sees none here).
    The model follows the detector contract (`Detector`, detbench/train/detector.py). The model's train/eval
    mode is restored. Raises NonFiniteOutputError when the model's outputs hold NaN or inf for any frame.
    """
    was_training = model.training
    model.eval()
    out: dict[str, Detections] = {}
    n = len(frames)
    bar = tqdm(total=n, desc=desc, unit="frame", disable=not progress, leave=False, dynamic_ncols=True)
    bad: list[str] = []  # frames of batches whose outputs were not finite
    dropped = 0  # first-stage boxes of a two-stage model left out as non-finite
    try:
        for start in range(0, n, batch_size):
            samples = [frame_sample(frames[i], point_cloud_range, road)
                       for i in range(start, min(n, start + batch_size))]
            batch = collate(samples).to(device)
            outputs = model(batch)
            if count_nonfinite(outputs):
                bad.extend(s.frame_id for s in samples)
            dropped += dropped_proposals(outputs)
            dets = model.predict(outputs, batch)
            for s, d in zip(samples, dets):
                out[s.frame_id] = d.numpy()
            bar.update(len(samples))
    finally:
        bar.close()
        model.train(was_training)
    if bad:
        raise NonFiniteOutputError(f"the model's outputs hold NaN or inf in the batches of {len(bad)} of {n} "
                                   f"frames (e.g. {', '.join(bad[:3])}); its weights are broken or the run "
                                   f"diverged: use an earlier checkpoint, or train again with a lower train.lr")
    if dropped:
        print(f"warning: {desc}: the first stage decoded {dropped} box(es) over {n} frames to non-finite "
              f"geometry (inf, or too large to measure); they were left out before the second stage",
              file=sys.stderr)
    return out


def checkpoint_predictions(model: nn.Module, ck: dict, dataset, *, device="cpu", batch_size: int = 4,
                           progress: bool = True, stage: str = "refined", source=None) -> dict:
    """`predict_frames` of a model loaded from a checkpoint (`ck`, its dict) over `dataset`, with the
    checkpoint's point-cloud range and road setting. `stage` "proposals" asks a two-stage model for its first
    stage's boxes alone. A user's problem (a one-stage model asked for proposals, outputs that went NaN, a
    malformed frame) is a UserError; `source` (the checkpoint's path) prefixes the NaN message."""
    if stage != "refined":
        if not isinstance(model, TwoStageDetector):
            raise UserError(f"--stage {stage}: {ck['model_name']} is a one-stage detector; --stage applies to "
                            f"two-stage models (pointrcnn, ct3d)")
        model.set_output_stage(stage)
    try:
        return predict_frames(model, dataset, ck["config"]["model"]["point_cloud_range"], device=device,
                              batch_size=batch_size, progress=progress, road=RoadConfig.of_run_config(ck["config"]))
    except FloatingPointError as e:
        raise UserError(f"{source}: {e}") from None
    except DatasetError as e:  # a frame of the split is malformed
        raise UserError(str(e)) from None
