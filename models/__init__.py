"""Detectors, one file each, built from the shared stages in models/stages.

`REGISTRY` maps a model name to its class; `build_model(name, model_cfg)` builds one from
the `model:` section of its config, configs/<name>.yaml (the key and that file's name are
the only places a model's name is written: the run config's `model.name` comes from the
file). Every class follows the detector contract `detbench.train.detector.Detector`
(forward, loss, predict, STAGES and `prepare_config(model_cfg, train_boxes) -> model_cfg`,
which fills data-derived values: SECOND sizes its anchors from the training boxes); the
two-stage ones also `TwoStageDetector` (set_output_stage). tests/models/test_contract.py
checks each registered model. tools/train.py calls `prepare_model_config` once before building,
and the result is stored in the checkpoint so evaluation rebuilds the same model.
"""
from __future__ import annotations

import difflib
from typing import TYPE_CHECKING

import numpy as np
import torch.nn as nn

from .ct3d import CT3D
from .pillarnet import PillarNet
from .pointrcnn import PointRCNN
from .second import SECOND
from .stages import ModelConfigError, check_model_config

if TYPE_CHECKING:  # detbench.train loads the whole training stack: imported for the annotations only
    from detbench.train.detector import Detector

REGISTRY: dict[str, type[Detector]] = {
    "second": SECOND,
    "pillarnet": PillarNet,
    "ct3d": CT3D,
    "pointrcnn": PointRCNN,
}


def get_model_class(name: str) -> type[Detector]:
    if name not in REGISTRY:
        close = difflib.get_close_matches(name, list(REGISTRY), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ValueError(f"unknown model {name!r}{hint} (registered: {', '.join(sorted(REGISTRY))})")
    return REGISTRY[name]


def prepare_model_config(name: str, model_cfg: dict, train_boxes: np.ndarray) -> dict:
    """Fill data-derived values of `model_cfg` (a copy is returned); ModelConfigError for a value out of range."""
    cls = get_model_class(name)
    check_model_config(model_cfg)
    return cls.prepare_config(model_cfg, train_boxes)


def build_model(name: str, model_cfg: dict) -> nn.Module:
    """The registered detector `name` (an `nn.Module` following `Detector`) built from `model_cfg`, whose values
    are range-checked first (`check_model_config`: ModelConfigError naming the key)."""
    cls = get_model_class(name)
    check_model_config(model_cfg)
    return cls(model_cfg)


__all__ = ["REGISTRY", "ModelConfigError", "build_model", "check_model_config", "get_model_class",
           "prepare_model_config"]


def load_from_checkpoint(path, device="cpu"):
    """(model in eval mode on `device`, checkpoint dict) from a tools/train.py checkpoint.

    The model is rebuilt from the config stored in the checkpoint (weights_only loading),
    so nothing else is needed; errors name the file and the fix.
    """
    # imported on use: detbench.train loads the whole training stack (TensorBoard, DDP helpers)
    from detbench.train.checkpoint import CheckpointError, load_checkpoint, load_model_weights

    ckpt = load_checkpoint(path)
    name = ckpt["model_name"]
    try:
        model = build_model(name, ckpt["config"]["model"])
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{path}: cannot rebuild model {name!r} from the checkpoint's config ({e}); the "
                              f"config stored in it was edited or written by another detbench version; use a "
                              f"checkpoint as tools/train.py wrote it") from None
    load_model_weights(model, ckpt, path)
    return model.to(device).eval(), ckpt


__all__.append("load_from_checkpoint")
