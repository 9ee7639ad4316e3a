"""Detectors, one file each, built from the shared stages in models/stages.

`REGISTRY` maps a model name to its class; `build_model(name, model_cfg)` builds one from
the `model:` section of its config, configs/<name>.yaml (the key and that file's name are
the only places a model's name is written: the run config's `model.name` comes from the
file). Every class follows the detector contract `detbench.train.detector.Detector`
(forward, loss, predict, STAGES and `prepare_config(model_cfg, train_boxes) -> model_cfg`,
which fills data-derived values: SECOND sizes its anchors from the training boxes); the
two-stage ones also `TwoStageDetector` (set_output_stage). Each class names its typed config
`CONFIG` (a frozen dataclass of frozen stage configs, models/stages/config.py): building the
model reads its section through it, and `check_model_config` reads one without building.
tests/models/test_contract.py checks each registered model. tools/train.py calls
`prepare_model_config` once before building, and the result is stored in the checkpoint so
evaluation rebuilds the same model (`load_from_checkpoint`, through `upgrade_stored_model_config`
for a config stored by an earlier version).
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
from .stages import ModelConfigError, StageConfig
from .stored_config import upgrade_stored_model_config, upgrade_stored_run_config

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


def check_model_config(model_cfg: dict, where: str | None = None, name: str | None = None) -> StageConfig:
    """The typed config of the `model:` section `model_cfg` of the registered model `name` (default: its
    `name` key), every key read and range-checked without building anything; ModelConfigError naming the
    dotted key and the config file `where` (default configs/<name>.yaml). `auto` values pass (unresolved)."""
    if name is None:
        name = model_cfg.get("name") if isinstance(model_cfg, dict) else None
        if not isinstance(name, str):
            raise ModelConfigError(f"{where or 'the model config'}: model.name is missing; it names the detector "
                                   f"({', '.join(sorted(REGISTRY))})")
    cls = get_model_class(name)
    return cls.CONFIG.from_config(model_cfg, source=where or f"configs/{name}.yaml")


def prepare_model_config(name: str, model_cfg: dict, train_boxes: np.ndarray) -> dict:
    """Fill data-derived values of `model_cfg` (a copy is returned); ModelConfigError for a key missing,
    unknown or out of range."""
    check_model_config(model_cfg, name=name)
    return get_model_class(name).prepare_config(model_cfg, train_boxes)


def build_model(name: str, model_cfg: dict) -> nn.Module:
    """The registered detector `name` (an `nn.Module` following `Detector`) built from `model_cfg`, which its
    `CONFIG` reads first (ModelConfigError naming the key)."""
    return get_model_class(name)(model_cfg)


__all__ = ["REGISTRY", "ModelConfigError", "build_model", "check_model_config", "get_model_class",
           "prepare_model_config", "upgrade_stored_model_config",
           "upgrade_stored_run_config"]


def load_from_checkpoint(path, device="cpu"):
    """(model in eval mode on `device`, checkpoint dict) from a tools/train.py checkpoint.

    The model is rebuilt from the config stored in the checkpoint (weights_only loading), upgraded to
    today's keys (`upgrade_stored_model_config`), so nothing else is needed; errors name the file and the fix.
    """
    # imported on use: detbench.train loads the whole training stack (TensorBoard, DDP helpers)
    from detbench.train.checkpoint import CheckpointError, load_checkpoint, load_model_weights

    ckpt = load_checkpoint(path)
    name = ckpt["model_name"]
    try:
        model = build_model(name, upgrade_stored_model_config(name, ckpt["config"]["model"]))
    except (KeyError, ValueError, TypeError) as e:
        raise CheckpointError(f"{path}: cannot rebuild model {name!r} from the checkpoint's config ({e}); the "
                              f"config stored in it was edited or written by another detbench version; use a "
                              f"checkpoint as tools/train.py wrote it") from None
    load_model_weights(model, ckpt, path)
    return model.to(device).eval(), ckpt


__all__.append("load_from_checkpoint")
