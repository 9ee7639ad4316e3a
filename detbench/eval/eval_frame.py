"""What the evaluator takes: `EvalFrame`, one frame's ground truth and predictions, checked on construction.

`eval_frame_from_frame` builds one from a `detbench.data.Frame` and the frame's `Detections`, counting the
points in each box by the LiDAR-detected rule; `as_eval_frames` accepts EvalFrames or dicts of their
fields. A malformed input (a wrong shape, a NaN, a negative size) is a ValueError naming the frame, the
field and the row.
"""
from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from detbench.data.detections import Detections
from detbench.data.regions import detected_point_counts

__all__ = ["EvalFrame", "as_eval_frames", "eval_frame_from_frame"]


def _as_boxes(value: Any, name: str, where: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 7), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(f"{where}: {name} must have shape (N, 7) = x, y, z, dx, dy, dz, heading; "
                         f"got shape {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        row = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise ValueError(f"{where}: {name} row {row} is not finite ({arr[row].tolist()}); "
                         f"remove or fix that box")
    if (arr[:, 3:6] < 0).any():
        row = int(np.flatnonzero((arr[:, 3:6] < 0).any(axis=1))[0])
        raise ValueError(f"{where}: {name} row {row} has a negative size dx, dy, dz = "
                         f"{arr[row, 3:6].tolist()}; sizes are lengths in metres, >= 0")
    return np.ascontiguousarray(arr)


def _as_vector(value: Any, name: str, where: str, n: int, dtype, integral: bool) -> np.ndarray:
    raw = np.asarray(value)
    if raw.size == 0 and n == 0:
        return np.zeros(0, dtype=dtype)
    if raw.ndim != 1 or raw.shape[0] != n:
        raise ValueError(f"{where}: {name} must have shape ({n},) to match the boxes; got shape "
                         f"{tuple(raw.shape)}")
    if integral:
        f = raw.astype(np.float64)
        if not np.isfinite(f).all() or (f != np.round(f)).any():
            raise ValueError(f"{where}: {name} must hold whole numbers; got {raw.tolist()[:8]}")
        return f.astype(dtype)
    arr = raw.astype(dtype)
    if not np.isfinite(arr).all():
        raise ValueError(f"{where}: {name} must be finite; got {arr.tolist()[:8]}")
    return arr


@dataclass
class EvalFrame:
    """Ground truth and predictions of one frame, as the evaluator needs them.

    gt_boxes: (N, 7) x, y, z, dx, dy, dz, heading (metres, radians), ego ground frame.
    gt_num_points: (N,) number of LiDAR points inside each box with its bottom raised 0.05 m
        (`detbench.data.regions.detected_point_counts(points, boxes)`); a box with >= 1
        point (DETECTED_MIN_POINTS) is LiDAR-detected.
    gt_lane: (N,) lane relative to the ego (0 ego, +1 left, -1 right; any other value takes
        no part in Top-k).
    pred_boxes: (M, 7) predicted boxes, same layout as gt_boxes.
    pred_scores: (M,) confidence scores (compared with the score threshold, e.g. 0.1).
    frame_id: optional name used in error messages.
    scene_id: optional scene the frame belongs to: the unit `evaluate(..., bootstrap=B)`
        resamples (frames of one scene are 0.5 s apart and strongly correlated); a frame
        without one is its own cluster.

    Arrays are converted on construction (float64 boxes and scores, int64 counts and lanes);
    empty inputs may be given as `[]` or arrays of shape (0,) / (0, 7).
    """

    gt_boxes: np.ndarray
    gt_num_points: np.ndarray
    gt_lane: np.ndarray
    pred_boxes: np.ndarray
    pred_scores: np.ndarray
    frame_id: str | None = None
    scene_id: str | None = None

    def __post_init__(self) -> None:
        where = f"EvalFrame {self.frame_id!r}" if self.frame_id is not None else "EvalFrame"
        self.gt_boxes = _as_boxes(self.gt_boxes, "gt_boxes", where)
        n = len(self.gt_boxes)
        self.gt_num_points = _as_vector(self.gt_num_points, "gt_num_points", where, n, np.int64, True)
        if (self.gt_num_points < 0).any():
            raise ValueError(f"{where}: gt_num_points must be >= 0; got {self.gt_num_points.tolist()[:8]}")
        self.gt_lane = _as_vector(self.gt_lane, "gt_lane", where, n, np.int64, True)
        self.pred_boxes = _as_boxes(self.pred_boxes, "pred_boxes", where)
        self.pred_scores = _as_vector(self.pred_scores, "pred_scores", where, len(self.pred_boxes),
                                      np.float64, False)


def as_eval_frames(frames: Iterable[EvalFrame | Mapping]) -> list[EvalFrame]:
    """The frames as EvalFrames (a dict of EvalFrame's fields is built into one); TypeError naming the frame."""
    out = []
    for i, f in enumerate(frames):
        if isinstance(f, EvalFrame):
            out.append(f)
        elif isinstance(f, Mapping):
            try:
                out.append(EvalFrame(**f))
            except TypeError as e:
                raise TypeError(f"frame {i}: cannot build an EvalFrame from keys {sorted(f)} ({e}); "
                                f"give gt_boxes, gt_num_points, gt_lane, pred_boxes, pred_scores") from None
        else:
            raise TypeError(f"frame {i}: expected an EvalFrame (or a dict of its fields), got "
                            f"{type(f).__name__}")
    return out


def eval_frame_from_frame(frame, predictions: Detections | tuple | None) -> EvalFrame:
    """EvalFrame of a `detbench.data.Frame` (boxes, lanes, points) and its predictions.

    The point counts follow the LiDAR-detected rule (`detbench.data.regions.detected_point_counts`:
    points inside each box with its bottom raised 0.05 m). `predictions` is the frame's numpy `Detections`
    (`Detections.numpy()`), a (boxes (M, 7), scores (M,)) pair, or None.
    """
    boxes = np.asarray(frame.boxes)
    counts = detected_point_counts(np.asarray(frame.points), boxes)
    if predictions is None:
        pb, ps = np.zeros((0, 7)), np.zeros(0)
    else:
        pb, ps = predictions[0], predictions[1]
    return EvalFrame(boxes, np.asarray(counts), np.asarray(frame.lanes), pb, ps, frame_id=frame.frame_id,
                     scene_id=getattr(frame, "scene_id", None))
