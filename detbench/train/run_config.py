"""The run config of a detector: defaults, model file, preset, command-line overrides.

Resolution order (later wins):
  configs/default.yaml              data / train / augment / eval defaults for every model
  configs/<model>.yaml              the model section (and `_base_: default.yaml`)
  configs/presets/<preset>.yaml     data size and schedule common to all models (smoke|cpu|paper)
  <model>.yaml `presets.<preset>`   the model's own changes for that preset (e.g. widths)
  command-line flags and --set key=value
Every key a later layer sets must exist in the first two layers; an unknown key is an
error naming the closest known one. The evaluator's score threshold may not be below the
model's own (`check_score_thresholds`): the model never returns the boxes in between.

The run config's `model.name` is the detector's registered name, which its config file's
name gives (configs/<name>.yaml; `detbench.config.model_name_of`). A model's YAML also
declares `width_keys`: the keys of its `model:` section that hold channel widths, which the
trade study scales (`width_keys(model)`); they describe the model, not a run, so the run
config leaves them out.
"""
from __future__ import annotations

from pathlib import Path
from collections.abc import Sequence

from detbench.config import (
    CONFIG_DIR, ConfigError, apply_overrides, deep_merge, get, load_config, model_name_of, validate,
)
from detbench.data.augment import AugmentConfig
from detbench.data.road import RoadConfig
from detbench.eval.evaluate import EvalConfig
from detbench.train.train_config import TrainConfig

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
    base.pop("width_keys", None)
    name = model_name_of(source)
    if "model" not in base or not name:
        raise ConfigError(f"{source}: the config names no detector; model configs live in configs/<name>.yaml, "
                          f"and a config elsewhere inherits from one (_base_: <name>.yaml) or sets model.name")
    base["model"] = {"name": name, **base["model"]}
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
    RoadConfig.from_dict(cfg.get("road"), where=f"{source} road")  # its own keys: a model's YAML may set them
    EvalConfig.from_dict(cfg.get("eval"), where="eval")  # before training, not after its first epoch
    check_score_thresholds(get(cfg, "eval.score_threshold"), get(cfg, "model.post.score_threshold"))
    return cfg


def check_score_thresholds(eval_threshold, model_threshold, eval_key: str = "eval.score_threshold", where: str = "",
                           lower_model: str = "set model.post.score_threshold to {value:g} as well") -> None:
    """ConfigError when the evaluator's score threshold lies below the model's `model.post.score_threshold`:
    the model drops every box scoring below its own before the evaluator sees it, so the lower value would
    change nothing. The message names both, `where` first, and the two fixes (`lower_model` formatted with
    the evaluator's value). Values that are not scores in [0, 1] are left to their own checks."""
    def score(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1

    if score(eval_threshold) and score(model_threshold) and eval_threshold < model_threshold:
        raise ConfigError(f"{where}{eval_key} {eval_threshold:g} is below model.post.score_threshold "
                          f"{model_threshold:g}, under which the model keeps no box; "
                          f"{lower_model.format(value=eval_threshold)}, or use {eval_key} {model_threshold:g} or above")


def width_keys(model: str) -> tuple[str, ...]:
    """The dotted keys under `model:` whose values are channel widths, from the `width_keys` list
    of configs/<model>.yaml (the trade study's width knob scales them; empty: the model has
    none). ConfigError when the YAML declares no list or lists a key its `model:` section lacks."""
    source = f"{model}.yaml"
    cfg = load_config(source)
    keys = cfg.get("width_keys")
    if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
        raise ConfigError(f"{source}: needs `width_keys`, a list of the dotted keys under model: that hold channel "
                          f"widths (e.g. [backbone2d.num_filters]; [] when the model has none), got {keys!r}")
    missing = [k for k in keys if get(cfg.get("model") or {}, k) is None]
    if missing:
        raise ConfigError(f"{source}: width_keys {missing} are not keys of its model: section")
    return tuple(keys)
