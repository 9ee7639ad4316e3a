"""Range checks of a model's config (the `model:` section), by what each key means, before anything is built.

Every detector's config is checked the same way (`check_model_config`), whether it comes
from a run config, a study or a checkpoint: a key is checked by its name wherever it sits,
so a new stage's keys are covered when they follow the names below.

  every number                    finite (no NaN or inf), in lists too
  point_cloud_range, voxel_size   6 numbers, min < max; 3 positive numbers (VoxelGrid checks the rest)
  score, nms and IoU thresholds,  a fraction in [0, 1]
  *_thresh, *_iou,
  *_ratio, min_overlap, dropout,
  iou_rectifier
  *top_k, num_points              an integer >= 1 (a proposal budget, proposals.*top_k and
                                  roi_per_image, may be 0)
  num_anchor_sizes                an integer in [1, MAX_ANCHOR_SIZES]
  *strides, *channels, num_filters,   integers >= 1
  *_channels, hidden_dim, heads, fc
  rotations                       a non-empty list of angles (radians)
  anchor_sizes, mean_size         auto, or positive [length, width, height] (m)
  pos_iou / neg_iou               neg_iou <= pos_iou
  cls_bg_thresh_lo <= cls_bg_thresh <= cls_fg_thresh
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

MAX_ANCHOR_SIZES = 16  # k-means clusters of the training boxes' sizes (num_anchor_sizes)

_FRACTION_SUFFIXES = ("score_threshold", "nms_threshold", "iou_threshold", "_thresh", "_thresh_lo", "_iou", "_ratio")
_FRACTION_KEYS = ("min_overlap", "dropout", "iou_rectifier")
_COUNT_KEYS = ("num_points", "hidden_dim", "heads")
_POSITIVE_INT_LIST_SUFFIXES = ("strides", "channels", "num_filters", "fc")


class ModelConfigError(ValueError):
    """A model config value out of its range; the message names the key and what it must be."""


def _numbers(value: Any):
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield value
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _numbers(v)


def _is_count(value: Any, low: int = 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _positive_sizes(value: Any) -> bool:
    return (isinstance(value, (list, tuple)) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in value))


def _check_key(key: str, value: Any, dotted: str, where: str) -> None:
    def bad(need: str) -> ModelConfigError:
        return ModelConfigError(f"{where}: {dotted} must be {need}, got {value!r}")

    if any(not math.isfinite(v) for v in _numbers(value)):
        raise bad("finite (no NaN or inf)")
    if key == "point_cloud_range":
        if not (isinstance(value, (list, tuple)) and len(value) == 6 and len(list(_numbers(value))) == 6):
            raise bad("6 numbers [x_min, y_min, z_min, x_max, y_max, z_max] in metres")
        if any(value[i] >= value[i + 3] for i in range(3)):
            raise bad("a range whose minima are below its maxima")
    elif key == "voxel_size":
        if not _positive_sizes(value):
            raise bad("3 positive numbers [vx, vy, vz] in metres")
    elif key in ("anchor_sizes", "mean_size"):
        if value == "auto":
            return
        ok = (_positive_sizes(value) if key == "mean_size" else
              isinstance(value, (list, tuple)) and value and all(map(_positive_sizes, value)))
        if not ok:
            raise bad("auto or " + ("[length, width, height]" if key == "mean_size" else
                                    "a non-empty list of [length, width, height]") + " in positive metres")
    elif key == "rotations":
        if not (isinstance(value, (list, tuple)) and value and len(list(_numbers(value))) == len(value)):
            raise bad("a non-empty list of anchor angles in radians, e.g. [0.0, 1.5707963]")
    elif key == "num_anchor_sizes":
        if not (_is_count(value) and value <= MAX_ANCHOR_SIZES):
            raise bad(f"an integer from 1 to {MAX_ANCHOR_SIZES} (k-means clusters of the training boxes' sizes)")
    elif (".proposals." in dotted and key.endswith("top_k")) or key == "roi_per_image":
        if not _is_count(value, 0):  # a two-stage model's proposal budget of 0 leaves the second stage idle
            raise bad("an integer >= 0")
    elif key.endswith("top_k") or key in _COUNT_KEYS:
        if not _is_count(value):
            raise bad("an integer >= 1")
    elif "weights" in dotted:
        return  # loss and code weights: any finite number
    elif key.endswith(_FRACTION_SUFFIXES) or key in _FRACTION_KEYS:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and not 0 <= value <= 1:
            raise bad("a fraction in [0, 1]")
    elif key.endswith(_POSITIVE_INT_LIST_SUFFIXES):
        items = value if isinstance(value, (list, tuple)) else [value]
        if not all(_is_count(v) for v in items):
            raise bad("made of integers >= 1" if isinstance(value, (list, tuple)) else "an integer >= 1")


def _pairs(section: Mapping, dotted: str, where: str) -> None:
    def order(low: str, high: str) -> None:
        lo, hi = section.get(low), section.get(high)
        if isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and lo > hi:
            raise ModelConfigError(f"{where}: {dotted}{low} ({lo}) must not exceed {dotted}{high} ({hi})")

    order("neg_iou", "pos_iou")
    order("cls_bg_thresh", "cls_fg_thresh")
    order("cls_bg_thresh_lo", "cls_bg_thresh")


def check_model_config(cfg: Mapping, where: str = "config") -> None:
    """ModelConfigError naming the first key of `cfg` (a `model:` section) whose value is out of its range."""
    def walk(section: Mapping, prefix: str) -> None:
        for key, value in section.items():
            dotted = f"{prefix}{key}"
            if isinstance(value, Mapping):
                walk(value, f"{dotted}.")
            else:
                _check_key(str(key), value, dotted, where)
        _pairs(section, prefix, where)

    walk(cfg, "model.")
