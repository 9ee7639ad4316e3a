"""The `train` section of a run config as `TrainConfig`, checked before any training starts.

Each key's default and unit is in configs/default.yaml (`TRAIN_DEFAULTS`); `TrainConfig.from_dict`
fills in the defaults, converts each value to its field's type and refuses an unknown key, a
non-finite number or a value out of its range with a ConfigError naming the key and what it must
be. `RESUME_SAFE_KEYS` are the train keys a resumed run may change, because they change no result.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from collections.abc import Mapping
from typing import Any

from detbench.config import ConfigError, section_with_defaults, shipped_defaults

__all__ = ["RESUME_IGNORE_KEYS", "RESUME_SAFE_KEYS", "TRAIN_DEFAULTS", "TrainConfig"]

TRAIN_DEFAULTS: dict[str, Any] = shipped_defaults("train")  # configs/default.yaml `train:`, each key documented there
# train.* keys that may change between an interrupted run and its resume (they do not change results)
RESUME_SAFE_KEYS = ("workers", "log_every", "tensorboard", "bev_image", "eval_every", "keep_checkpoints",
                    "checkpoint_every_steps", "max_nonfinite_steps")
# dotted config keys `train` lets differ on resume: those above, and the eval section (it measures, never trains)
RESUME_IGNORE_KEYS = (*(f"train.{k}" for k in RESUME_SAFE_KEYS), "eval")


@dataclass(frozen=True)
class TrainConfig:
    """Typed view of the `train` config section; each key's default and unit is in configs/default.yaml."""

    epochs: int
    batch_size: int  # frames per process per step
    workers: int
    seed: int
    lr: float
    weight_decay: float
    betas: tuple[float, float]
    pct_start: float
    div_factor: float
    final_div_factor: float
    momentum_range: tuple[float, float]
    grad_clip: float
    amp: bool
    keep_checkpoints: int
    checkpoint_every_steps: int
    eval_every: int
    log_every: int
    drop_last: bool
    find_unused_parameters: bool
    channels_last: bool  # 2D convolution weights in NHWC memory format
    tensorboard: bool
    bev_image: bool
    max_nonfinite_steps: int  # skipped non-finite steps in a row that stop the run
    precise_bn_batches: int  # training batches that recompute the BatchNorm statistics of each checkpoint (0: off)

    @classmethod
    def from_dict(cls, d: Mapping | None, where: str = "train") -> TrainConfig:
        """Parse the `train` section (missing keys: TRAIN_DEFAULTS); ConfigError on unknown keys or bad values."""
        v = section_with_defaults(d, TRAIN_DEFAULTS, where)
        cfg = cls(**{f.name: _as_field_type(f.type, v[f.name], f"{where}.{f.name}") for f in fields(cls)})
        for f in fields(cls):
            value = getattr(cfg, f.name)
            if f.type in ("float", "tuple[float, float]") and not all(map(math.isfinite, _as_tuple(value))):
                raise ConfigError(f"{where}: {f.name} must be finite (no NaN or inf), got {value!r}")
        checks = [("epochs", cfg.epochs >= 1, ">= 1"), ("batch_size", cfg.batch_size >= 1, ">= 1"),
                  ("workers", cfg.workers >= 0, ">= 0"), ("seed", cfg.seed >= 0, ">= 0"),
                  ("lr", cfg.lr > 0, "> 0"), ("weight_decay", cfg.weight_decay >= 0, ">= 0"),
                  ("pct_start", 0 < cfg.pct_start < 1, "in (0, 1)"), ("grad_clip", cfg.grad_clip >= 0, ">= 0"),
                  ("eval_every", cfg.eval_every >= 1, ">= 1"), ("log_every", cfg.log_every >= 1, ">= 1"),
                  ("checkpoint_every_steps", cfg.checkpoint_every_steps >= 0, ">= 0"),
                  ("max_nonfinite_steps", cfg.max_nonfinite_steps >= 1, ">= 1"),
                  ("precise_bn_batches", cfg.precise_bn_batches >= 0, ">= 0 (0: off)"),
                  ("div_factor", cfg.div_factor >= 1, ">= 1 (the schedule starts at lr / div_factor)"),
                  ("final_div_factor", cfg.final_div_factor >= 1,
                   ">= 1 (the schedule ends at lr / div_factor / final_div_factor)"),
                  ("betas", all(0 <= b < 1 for b in cfg.betas), "two numbers in [0, 1)"),
                  ("momentum_range", all(0 <= m < 1 for m in cfg.momentum_range)
                   and cfg.momentum_range[0] <= cfg.momentum_range[1],
                   "[low, high] with 0 <= low <= high < 1 (Adam's beta1, cycled opposite to the lr)")]

        for key, ok, need in checks:
            if not ok:
                raise ConfigError(f"{where}: {key} must be {need}, got {getattr(cfg, key)!r}")
        return cfg


def _as_tuple(value: Any) -> tuple:
    return tuple(value) if isinstance(value, tuple) else (value,)


def _as_field_type(annotation: str, value: Any, key: str) -> Any:
    """A YAML value (of its default's kind, `validate`d) as a TrainConfig field's type, named by its annotation."""
    if annotation != "tuple[float, float]":
        return {"int": int, "float": float, "bool": bool}[annotation](value)
    if len(value) != 2:  # `validate` made it a list of numbers
        raise ConfigError(f"{key} must be a list of two numbers, e.g. [0.9, 0.99], got {value!r}")
    return float(value[0]), float(value[1])
