"""The Height3 paper's detection results (Table VII), to set beside a study's figures.

Table VII gives, per range and height, the number of vehicles the LiDAR detected and each
detector's recall of them at 3D IoU 0.7 and score >= 0.1, All vehicles (full-size models trained
on 4723 CARLA frames and tested on 2290; the paper does not give its schedule). It reports no
AP. Tables VIII and IX (Top3, Top6) are held back as an independent check and are not here.
"""
from __future__ import annotations

from detbench.data.frame import height_key

# recall of the LiDAR-detected vehicles, All vehicles: {model: {height (m, as text): (small, moderate, large)}}
PAPER_TABLE_VII_RECALL: dict[str, dict[str, tuple[float, float, float]]] = {
    "pointrcnn": {"0.5": (0.93, 0.84, 0.78), "1.0": (0.94, 0.83, 0.77), "1.8": (0.91, 0.80, 0.72)},
    "pillarnet": {"0.5": (0.96, 0.90, 0.84), "1.0": (0.97, 0.90, 0.84), "1.8": (0.98, 0.91, 0.84)},
    "second": {"0.5": (0.97, 0.90, 0.85), "1.0": (0.97, 0.91, 0.85), "1.8": (0.97, 0.91, 0.85)},
    "ct3d": {"0.5": (0.98, 0.92, 0.88), "1.0": (0.98, 0.93, 0.88), "1.8": (0.98, 0.93, 0.88)},
}


def paper_recall(model: str, height: float) -> tuple[float, float, float] | None:
    """Table VII's recall (small, moderate, large) of `model` at exactly `height` m (0.5, 1.0 or 1.8), or None
    where the paper has none."""
    return PAPER_TABLE_VII_RECALL.get(str(model).lower(), {}).get(height_key(height))


__all__ = ["PAPER_TABLE_VII_RECALL", "paper_recall"]
