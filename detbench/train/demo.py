"""A checkpoint's predictions on one frame, drawn (tools/demo.py).

`demo_frame` runs a detector loaded from a checkpoint on one frame of a dataset split (the same input
preparation and post-processing as evaluation, `checkpoint_predictions`) and returns a `DemoFrame`:
the points the model sees, the ground truth and the predictions. `write_demo` draws it in bird's-eye
view with the training preview's figure (`bev_figure`: points grey, ground truth green, predictions at
or above the score threshold red with their scores) into `<frame_id>.png`, and writes the boxes drawn
into `<frame_id>.json`. Boxes are `x y z dx dy dz heading` in metres and radians in the ego ground
frame; scores are in [0, 1].
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from torch import nn

from detbench.config import ConfigError, get, shipped_default
from detbench.data.dataset import Height3Dataset
from detbench.data.errors import DatasetError
from detbench.data.frame import data_key, key_heading, key_value
from detbench.data.road import RoadConfig
from detbench.train.inference import checkpoint_predictions, frame_sample
from detbench.train.logger import bev_figure
from detbench.train.run_config import check_score_thresholds
from detbench.train.run_layout import demo_dir_name, run_dir_of_checkpoint
from detbench.utils.cli import UserError
from detbench.utils.atomic import atomic_save, atomic_write_json

BOX_UNITS = "x y z dx dy dz heading: metres and radians, ego ground frame (origin on the road below the LiDAR)"


def select_frame(dataset: Height3Dataset, frame: str) -> str:
    """The frame id `frame` names in `dataset`: a frame id, or else an index into the split's frames (negative
    counts from the end). UserError naming the split's ids and index range otherwise."""
    ids = dataset.frame_ids
    if frame in ids:
        return frame
    where = f"the {dataset.split} split at {key_heading(dataset.height_key)}"
    if not ids:
        raise UserError(f"--frame {frame}: {where} holds no frames; choose another --split")
    try:
        index = int(frame)
    except ValueError:
        index = None
    if index is None or not -len(ids) <= index < len(ids):
        shown = ", ".join(ids[:3]) + (" ..." if len(ids) > 3 else "")
        raise UserError(f"--frame {frame}: neither a frame id of {where} ({shown}) nor an index in "
                        f"0..{len(ids) - 1}")
    return ids[index]


@dataclass
class DemoFrame:
    """One frame with a checkpoint's predictions on it."""

    frame_id: str
    height: float | str  # metres, the LiDAR the frame was recorded with (a rig: its name)
    split: str
    model: str
    checkpoint: str
    stage: str  # "refined", or "proposals" for a two-stage model's first stage alone
    points: np.ndarray  # (N, 4) float32: the points the model sees (cropped to its range, road as it was trained)
    gt_boxes: np.ndarray  # (M, 7) float32 ground truth
    boxes: np.ndarray  # (K, 7) float32 every prediction after the model's own post-processing
    scores: np.ndarray  # (K,) float32 in [0, 1]
    score_threshold: float  # predictions below it are not drawn
    point_cloud_range: list[float]  # [x_min, y_min, z_min, x_max, y_max, z_max] metres: the figure's extent

    @property
    def drawn(self) -> np.ndarray:
        """(K,) bool: the predictions at or above the score threshold."""
        return self.scores >= self.score_threshold


def demo_frame(model: nn.Module, ck: dict, dataset: Height3Dataset, frame: str, *, checkpoint: str | os.PathLike,
               device="cpu", stage: str = "refined", score_threshold: float | None = None) -> DemoFrame:
    """Run the checkpoint's `model` (`ck` its dict) on the frame `frame` (id or index, `select_frame`) of
    `dataset`. `score_threshold` None: the evaluator's (configs/default.yaml eval.score_threshold)."""
    score_threshold = float(shipped_default("eval.score_threshold", score_threshold))
    if not (math.isfinite(score_threshold) and 0 <= score_threshold <= 1):
        raise UserError(f"--score-threshold {score_threshold:g}: must be a score in [0, 1]")
    try:
        check_score_thresholds(score_threshold, get(ck["config"], "model.post.score_threshold"),
                               eval_key="--score-threshold", where=f"--ckpt {checkpoint}: ",
                               lower_model="train it with --set model.post.score_threshold={value:g}")
    except ConfigError as e:
        raise UserError(str(e)) from None
    fid = select_frame(dataset, frame)
    try:
        f = dataset.load(fid)
    except DatasetError as e:  # a malformed file of the frame
        raise UserError(str(e)) from None
    pc_range = [float(v) for v in ck["config"]["model"]["point_cloud_range"]]
    preds = checkpoint_predictions(model, ck, [f], device=device, batch_size=1, progress=False, stage=stage,
                                   source=checkpoint)
    boxes, scores = preds[fid].boxes, preds[fid].scores
    sample = frame_sample(f, pc_range, RoadConfig.of_run_config(ck["config"]))
    return DemoFrame(frame_id=fid, height=key_value(dataset.height_key), split=dataset.split, model=ck["model_name"],
                     checkpoint=str(checkpoint), stage=stage, points=sample.points,
                     gt_boxes=np.asarray(f.boxes, np.float32).reshape(-1, 7),
                     boxes=np.asarray(boxes, np.float32).reshape(-1, 7),
                     scores=np.asarray(scores, np.float32).reshape(-1), score_threshold=score_threshold,
                     point_cloud_range=pc_range)


def demo_record(d: DemoFrame) -> dict:
    """The JSON of a drawing: the frame, the checkpoint, the ground truth and the predictions drawn."""
    keep = d.drawn
    return {
        "frame_id": d.frame_id, "height_m": d.height, "split": d.split, "model": d.model, "checkpoint": d.checkpoint,
        "stage": d.stage, "score_threshold": d.score_threshold, "point_cloud_range_m": d.point_cloud_range,
        "points_drawn": int(len(d.points)),
        "units": {"boxes": BOX_UNITS, "scores": "fraction in [0, 1]"},
        "ground_truth": [[round(float(v), 4) for v in b] for b in d.gt_boxes],
        "predictions": [{"box": [round(float(v), 4) for v in b], "score": round(float(s), 4)}
                        for b, s in zip(d.boxes[keep], d.scores[keep])],
        "predictions_below_threshold": int((~keep).sum()),
    }


def demo_figure(d: DemoFrame) -> Figure:
    """The bird's-eye drawing of `d` (the training preview's `bev_figure`)."""
    title = (f"{d.model} ({d.stage}) on frame {d.frame_id}, {d.split} split, {key_heading(data_key(d.height))}: "
             f"ground truth (green) vs predictions (red)")
    return bev_figure(d.points, d.gt_boxes, d.boxes, d.scores, d.point_cloud_range,
                      score_threshold=d.score_threshold, title=title)


def write_demo(d: DemoFrame, out_dir: str | os.PathLike) -> tuple[Path, Path]:
    """Draw `d` into OUT/<frame_id>.png and write `demo_record(d)` to OUT/<frame_id>.json; returns both paths."""
    out_dir = Path(out_dir)
    fig = demo_figure(d)
    png = atomic_save(out_dir / f"{d.frame_id}.png", lambda tmp: fig.savefig(tmp, format="png", dpi=100))
    return png, atomic_write_json(out_dir / f"{d.frame_id}.json", demo_record(d))


@dataclass
class DemoOptions:
    """tools/demo.py's settings. data and height default to what the checkpoint was trained on, out to the
    run folder's demo_h<height>_<split>/."""

    checkpoint: Path
    frame: str = "0"
    split: str = "test"
    data: Path | None = None
    height: float | None = None
    out: Path | None = None
    stage: str = "refined"
    score_threshold: float | None = None
    device: str = "cpu"


def run_demo(model: nn.Module, ck: dict, opts: DemoOptions) -> tuple[DemoFrame, Path, Path]:
    """Draw the predictions of the checkpoint's `model` (`ck` its dict, loaded from `opts.checkpoint`) on one
    frame: (the frame and its predictions, the PNG, the JSON)."""
    data = Path(opts.data) if opts.data is not None else Path(ck["data"]["source"])
    height = opts.height if opts.height is not None else ck["data"].get("height")
    if height is None:
        raise UserError(f"--ckpt {opts.checkpoint}: records no training height (data.height); give --height H "
                        f"in metres")
    if not data.is_dir():
        raise UserError(f"{data}: dataset root not found; give --data the folder written by tools/simulate.py "
                        f"or holding the Height3 data")
    try:
        dataset = Height3Dataset(data, key_value(height), opts.split)
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UserError(str(e)) from None
    d = demo_frame(model, ck, dataset, opts.frame, checkpoint=opts.checkpoint, device=opts.device,
                   stage=opts.stage, score_threshold=opts.score_threshold)
    out = opts.out if opts.out is not None else \
        run_dir_of_checkpoint(opts.checkpoint) / demo_dir_name(d.height, opts.split)
    png, js = write_demo(d, out)
    return d, png, js


__all__ = ["BOX_UNITS", "DemoFrame", "DemoOptions", "demo_figure", "demo_frame", "demo_record", "run_demo",
           "select_frame", "write_demo"]
