"""The run config of a detector: defaults, model file, preset, command-line overrides.

Resolution order (later wins):
  configs/default.yaml              data / train / augment / eval defaults for every model
  configs/<model>.yaml              the model section (and `_base_: default.yaml`)
  configs/presets/<preset>.yaml     data size and schedule common to all models (smoke|cpu|paper)
  <model>.yaml `presets.<preset>`   the model's own changes for that preset (e.g. widths)
  command-line flags and --set key=value
Every key a later layer sets must exist in the first two layers; an unknown key is an
error naming the closest known one.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

from detbench.config import CONFIG_DIR, ConfigError, apply_overrides, deep_merge, load_config, validate
from detbench.data.augment import AugmentConfig
from detbench.eval.evaluate import EvalConfig
from detbench.train.loop import TrainConfig

PRESETS = ("smoke", "cpu", "paper")


def preset_names() -> list[str]:
    found = sorted(p.stem for p in (CONFIG_DIR / "presets").glob("*.yaml"))
    return found or list(PRESETS)


def load_run_config(model: str | None = None, preset: str | None = None, config: str | Path | None = None,
                    overrides: Sequence[str] = ()) -> dict:
    """The merged, validated run config. Give `model` (configs/<model>.yaml) or `config` (a path)."""
    if config is None and model is None:
        raise ConfigError("give a model name or a config file")
    source = config or f"{model}.yaml"
    base = load_config(source)
    model_presets = base.pop("presets", {}) or {}
    if "model" not in base or "name" not in base.get("model", {}):
        raise ConfigError(f"{source}: the config has no model.name; model configs live in configs/<name>.yaml")
    reference = base
    cfg = base
    if preset:
        if preset not in preset_names():
            raise ConfigError(f"unknown preset {preset!r}; use one of {', '.join(preset_names())}")
        common = load_config(CONFIG_DIR / "presets" / f"{preset}.yaml")
        validate(common, reference, where=f"configs/presets/{preset}.yaml")
        cfg = deep_merge(cfg, common)
        own = model_presets.get(preset) or {}
        validate(own, reference, where=f"{source} presets.{preset}")
        cfg = deep_merge(cfg, own)
    cfg = apply_overrides(cfg, overrides, reference=reference)
    cfg["preset"] = preset
    TrainConfig.from_dict(cfg.get("train"), where="train")  # type and range checks, early
    AugmentConfig.from_dict(cfg.get("augment"), where="augment")
    EvalConfig.from_dict(cfg.get("eval"), where="eval")  # before training, not after its first epoch
    return cfg
