"""What a training run reports: TensorBoard scalars and a bird's-eye image, a console line per epoch,
and OUT/history.json (one record per epoch, machine-readable).

Only rank 0 logs; other ranks get a disabled logger whose methods do nothing.
TensorBoard files go to OUT/tensorboard (`tensorboard --logdir OUT/tensorboard`); every
scalar and image is indexed by the optimizer step (epoch figures at the step that ends the
epoch), so a resumed run continues the same curves.
"""
from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from detbench.config import shipped_default
from detbench.ops import boxes_to_corners_bev
from detbench.utils.atomic import atomic_write_json

__all__ = ["TrainLogger", "bev_figure", "drawable_boxes", "format_epoch_summary"]


def drawable_boxes(boxes: np.ndarray, point_cloud_range: Sequence[float]) -> np.ndarray:
    """(K,) bool: the boxes (K, 7) a bird's-eye figure of `point_cloud_range` draws. A box with a non-finite
    value, or a corner beyond one view's width or height from the view, is left out: matplotlib cannot lay
    out a line or a label 1e20 m away (its text renderer fails), and such a box would be off the figure."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    ok = np.isfinite(b).all(axis=1)
    ok[ok] &= (np.abs(b[ok, :2]).max(axis=1) < 1e9) & (np.abs(b[ok, 3:5]).max(axis=1) < 1e9)
    if not ok.any():
        return ok
    r = [float(v) for v in point_cloud_range]
    w, h = max(r[3] - r[0], 1e-6), max(r[4] - r[1], 1e-6)
    c = boxes_to_corners_bev(b[ok])  # (K', 4, 2)
    inside = ((c[..., 0] >= r[0] - w) & (c[..., 0] <= r[3] + w) & (c[..., 1] >= r[1] - h) & (c[..., 1] <= r[4] + h))
    ok[ok] = inside.all(axis=1)
    return ok


def bev_figure(points: np.ndarray, gt_boxes: np.ndarray, pred_boxes: np.ndarray, pred_scores: np.ndarray,
               point_cloud_range: Sequence[float], score_threshold: float | None = None, title: str = "",
               max_points: int = 20000) -> Figure:
    """Bird's-eye view of one frame: points (grey), ground truth (green), predictions (red, with scores).

    Args:
        points: (N, >=2) x, y metres (at most `max_points` are drawn, evenly strided).
        gt_boxes: (M, 7); pred_boxes: (K, 7); pred_scores: (K,) in [0, 1].
        point_cloud_range: [x_min, y_min, z_min, x_max, y_max, z_max] metres; sets the axes.
        score_threshold: predictions below it are not drawn (None: the evaluator's, configs/default.yaml).
    Boxes off the view (`drawable_boxes`) are not drawn; the legend counts them. A score label is drawn at
    its box's first corner when that corner lies in the view.
    Returns:
        A matplotlib Figure (no pyplot state), x forward to the right, y left upwards, metres.
    """
    score_threshold = shipped_default("eval.score_threshold", score_threshold)
    r = [float(v) for v in point_cloud_range]
    width = 12.0
    aspect = max(0.15, min(1.0, (r[4] - r[1]) / max(r[3] - r[0], 1e-6)))
    fig = Figure(figsize=(width, max(2.5, width * aspect + 1.0)), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    pts = np.asarray(points)
    if pts.shape[0] > max_points:
        pts = pts[:: int(math.ceil(pts.shape[0] / max_points))]
    if pts.shape[0]:
        ax.scatter(pts[:, 0], pts[:, 1], s=0.8, c="0.45", linewidths=0, rasterized=True)

    def draw(boxes: np.ndarray, color: str, label: str, scores: np.ndarray | None = None) -> None:
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        shown = drawable_boxes(boxes, r)
        off = boxes.shape[0] - int(shown.sum())
        legend = f"{label} ({boxes.shape[0]}" + (f"; {off} off the view, not drawn)" if off else ")")
        if not shown.any():
            ax.plot([], [], color=color, label=legend)
            return
        for n, k in enumerate(np.flatnonzero(shown)):
            c = boxes_to_corners_bev(boxes[k:k + 1])[0]
            loop = np.vstack([c, c[:1]])
            ax.plot(loop[:, 0], loop[:, 1], color=color, linewidth=1.0, label=legend if n == 0 else None)
            front = 0.5 * (c[0] + c[3])  # heading tick: centre -> front edge
            ax.plot([boxes[k, 0], front[0]], [boxes[k, 1], front[1]], color=color, linewidth=0.8)
            if scores is not None and r[0] <= c[0, 0] <= r[3] and r[1] <= c[0, 1] <= r[4]:
                ax.text(c[0, 0], c[0, 1], f"{scores[k]:.2f}", color=color, fontsize=6, clip_on=True)

    draw(gt_boxes, "tab:green", "ground truth")
    keep = np.asarray(pred_scores).reshape(-1) >= score_threshold
    draw(np.asarray(pred_boxes).reshape(-1, 7)[keep], "tab:red", f"predictions >= {score_threshold:g}",
         np.asarray(pred_scores).reshape(-1)[keep])
    ax.set_xlim(r[0], r[3])
    ax.set_ylim(r[1], r[4])
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.legend(loc="upper right", fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def _fmt(v: float) -> str:
    if v is None or not math.isfinite(v):
        return "nan"
    return f"{v:.3g}" if abs(v) < 1e-2 or abs(v) >= 1e3 else f"{v:.4f}"


def format_epoch_summary(epoch: int, epochs: int, losses: Mapping[str, float], lr: float, seconds: float,
                         frames: int, metrics: Mapping[str, float] | None = None) -> str:
    """One console line: 'epoch 3/20 | loss 1.23 (cls 0.5, box 0.7) | lr 2.1e-3 | 45.2 s, 12.3 frames/s | ...'."""
    total = losses.get("loss", float("nan"))
    parts = ", ".join(f"{k} {_fmt(v)}" for k, v in losses.items() if k != "loss")
    line = f"epoch {epoch}/{epochs} | loss {_fmt(total)}" + (f" ({parts})" if parts else "")
    line += f" | lr {lr:.3g} | {seconds:.1f} s, {frames / max(seconds, 1e-9):.1f} frames/s"
    if metrics:
        line += " | eval: " + ", ".join(f"{k} {_fmt(float(v))}" for k, v in metrics.items())
    return line


class TrainLogger:
    """TensorBoard + history.json for one run; every method is a no-op when `enabled` is False."""

    def __init__(self, out_dir: str | Path, enabled: bool = True, tensorboard: bool = True,
                 purge_step: int | None = None):
        """`purge_step`: on resume, TensorBoard hides events an interrupted run wrote at steps >= it."""
        self.out_dir = Path(out_dir)
        self.enabled = bool(enabled)
        self.history: list[dict] = []
        self.writer = None
        if self.enabled and tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError as e:  # tensorboard is a declared dependency; keep training without it
                warnings.warn(f"TensorBoard logging is off: {e}; pip install tensorboard to get it", stacklevel=2)
            else:
                self.writer = SummaryWriter(log_dir=str(self.out_dir / "tensorboard"), purge_step=purge_step)

    def scalars(self, values: Mapping[str, float], step: int, prefix: str = "") -> None:
        """Write scalars as '<prefix><name>' at `step` (x axis: optimizer steps or epochs)."""
        if self.writer is None:
            return
        for k, v in values.items():
            if v is not None and math.isfinite(float(v)):
                self.writer.add_scalar(f"{prefix}{k}", float(v), step)

    def figure(self, tag: str, fig: Figure, step: int) -> None:
        """Write a matplotlib figure as an image."""
        if self.writer is not None:
            self.writer.add_figure(tag, fig, step, close=True)

    def preview(self, tag: str, step: int, make_figure: Callable[[], Figure], what: str) -> None:
        """Write the figure `make_figure()` returns as an image. The figure is a view of the run, not part of
        it: when it cannot be made or rendered, `what` and the reason are one warning line on stderr and the
        training goes on."""
        if self.writer is None:
            return
        try:
            self.writer.add_figure(tag, make_figure(), step, close=True)
        except Exception as e:  # noqa: BLE001 - any failure of a figure, by design
            reason = " ".join(f"{type(e).__name__}: {e}".split())[:300]
            print(f"warning: {what} was not drawn ({reason}); the training goes on", file=sys.stderr, flush=True)

    def set_history(self, records: list[dict]) -> None:
        """Replace the in-memory history (on resume: the records of the completed epochs)."""
        self.history = [dict(r) for r in records]

    def add_epoch(self, record: Mapping) -> None:
        """Append an epoch record and rewrite OUT/history.json atomically."""
        if not self.enabled:
            return
        self.history.append(dict(record))
        self._write()

    def _write(self) -> None:
        atomic_write_json(self.out_dir / "history.json", {"epochs": self.history})
        if self.writer is not None:
            self.writer.flush()

    def set_last_metrics(self, metrics: Mapping[str, float]) -> None:
        """Fill the newest epoch record's evaluation metrics (computed after its checkpoint) and rewrite
        OUT/history.json."""
        if not self.enabled or not self.history or not metrics:
            return
        self.history[-1]["metrics"] = dict(metrics)
        self._write()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
