"""Checkpoints: written atomically, the last N kept, validated on load (`weights_only=True`).

A checkpoint is a dict of tensors, numbers, strings, lists and dicts only:

```
format "detbench-checkpoint", version 1
model_name  str              the registered detector name, e.g. "second"
config      dict             the full run config (after overrides)
config_digest str            SHA-256 of `config` (canonical JSON): a config edited after saving is refused
data        dict             the training data: {"source": ROOT, "height": 1.8, "frames_sha1": the content
                             fingerprint of the training frames (frames_fingerprint)}
state       dict             TrainState: epoch (completed), step_in_epoch, global_step, seed
model       state_dict       weights (DDP wrapper removed)
optimizer / scheduler / scaler   state_dicts (absent in weight-only exports)
rng         list[dict]       per rank: python / numpy / torch / cuda generator states (detbench.train.rng)
```

File names in OUT/checkpoints/: `epoch_003.pt` after 3 complete epochs;
`epoch_003_step_000120.pt` 120 batches into the 4th epoch (written on Ctrl-C or every
`checkpoint_every_steps`). `CheckpointManager.latest()` is the newest of them.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import warnings
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch
from torch import nn

from detbench.train.rng import restore_rng_state
from detbench.config import MAX_CONFIG_VALUES, shipped_default
from detbench.utils.atomic import atomic_save
from detbench.utils.untrusted import clip, excerpt, structure_problem

__all__ = [
    "CKPT_FORMAT", "CKPT_VERSION", "CheckpointError", "TrainState", "CheckpointManager",
    "save_checkpoint", "load_checkpoint", "restore_training", "load_model_weights", "check_finite_weights",
    "config_diff", "config_digest", "init_from_checkpoint", "DATA_FINGERPRINT_KEY",
]

CKPT_FORMAT = "detbench-checkpoint"
CKPT_VERSION = 1
_NAME_RE = re.compile(r"^epoch_(\d+)(?:_step_(\d+))?\.pt$")


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used; the message names the file and the fix."""


@dataclass
class TrainState:
    """Where training is: `epoch` epochs complete plus `step_in_epoch` batches of the next one."""

    epoch: int = 0
    step_in_epoch: int = 0
    global_step: int = 0
    seed: int = 0  # seeds the sampler permutation (seed + epoch) and each sample's augmentation

    def to_dict(self) -> dict:
        return {k: int(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping) -> TrainState:
        return cls(**{k: int(d[k]) for k in ("epoch", "step_in_epoch", "global_step", "seed")})


def config_digest(config: Mapping) -> str:
    """SHA-256 (hex) of `config` as canonical JSON (sorted keys): what a checkpoint records of its config."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str, allow_nan=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def unwrap_model(model: nn.Module) -> nn.Module:
    """The module inside a DistributedDataParallel / DataParallel wrapper (or `model` itself)."""
    return model.module if hasattr(model, "module") and isinstance(model.module, nn.Module) else model


def save_checkpoint(path: str | os.PathLike, *, model: nn.Module, state: TrainState, config: Mapping,
                    data: Mapping, model_name: str, optimizer: torch.optim.Optimizer | None = None,
                    scheduler: Any | None = None, scaler: Any | None = None,
                    rng: Sequence[Mapping] | None = None) -> Path:
    """Write a checkpoint atomically (temporary file + fsync + rename). Returns `path`.

    `rng` is one `capture_rng_state()` dict per rank (rank order); everything stored is a
    tensor, number, string, list or dict, so `torch.load(weights_only=True)` reads it back.
    """
    ckpt: dict[str, Any] = {
        "format": CKPT_FORMAT,
        "version": CKPT_VERSION,
        "model_name": str(model_name),
        "config": dict(config),
        "config_digest": config_digest(config),
        "data": dict(data),
        "state": state.to_dict(),
        "model": unwrap_model(model).state_dict(),
    }
    if optimizer is not None:
        ckpt["optimizer"] = optimizer.state_dict()
    if scheduler is not None:
        ckpt["scheduler"] = scheduler.state_dict()
    if scaler is not None:
        ckpt["scaler"] = scaler.state_dict()
    if rng is not None:
        ckpt["rng"] = [dict(r) for r in rng]
    return atomic_save(path, lambda tmp: torch.save(ckpt, tmp))


def _flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _is_shipped_default(dotted: str, value: Any) -> bool:
    try:
        return shipped_default(dotted) == value
    except KeyError:
        return False


def with_new_defaults(saved: Mapping, current: Mapping, prefix: str = "") -> dict:
    """`saved` with every key that only `current` has and that holds its configs/default.yaml value filled
    in: a key a newer detbench added takes, at its default, the behaviour the older one had."""
    out = dict(saved)
    for k, v in current.items():
        if k not in out:
            if _is_shipped_default(prefix + str(k), v):
                out[k] = v
        elif isinstance(out[k], Mapping) and isinstance(v, Mapping):
            out[k] = with_new_defaults(out[k], v, f"{prefix}{k}.")
    return out


def config_diff(saved: Mapping, current: Mapping, ignore: Iterable[str] = ()) -> list[str]:
    """Dotted keys whose values differ, as 'key: saved_value (checkpoint) vs current_value (now)'.

    Keys equal to or under an entry of `ignore` (dotted) are skipped. A key that only `current` has
    and that holds its configs/default.yaml value is no difference (`with_new_defaults`): a run made
    before detbench added the key resumes and compares equal.
    """
    a, b = _flatten(with_new_defaults(saved, current)), _flatten(current)
    ignore = tuple(ignore)
    lines = []
    for k in sorted(set(a) | set(b)):
        if any(k == i or k.startswith(i + ".") for i in ignore):
            continue
        va, vb = a.get(k, "<absent>"), b.get(k, "<absent>")
        if va != vb:
            lines.append(f"{clip(k, 80)}: {excerpt(va)} (checkpoint) vs {excerpt(vb)} (now)")
    return lines


def load_checkpoint(path: str | os.PathLike, *, model_name: str | None = None, config: Mapping | None = None,
                    data: Mapping | None = None, ignore_keys: Iterable[str] = (),
                    stored_config: Callable[[Mapping], Mapping] | None = None,
                    map_location: str | torch.device = "cpu") -> dict:
    """Read and validate a checkpoint with `torch.load(weights_only=True)`.

    Args:
        path: the .pt file.
        model_name / config / data: when given, must match what the checkpoint recorded
            (config compared key by key, `ignore_keys` dotted keys excepted; data by height and by the
            training frames' content fingerprint when both record one, else by source path).
        stored_config: turns the checkpoint's stored config into today's keys before it is compared with
            `config` (a checkpoint of an earlier version lacks keys that had values in code then).
        map_location: where tensors are loaded (default CPU; `load_state_dict` moves them).
    Returns:
        The checkpoint dict (see the module doc).
    Raises:
        CheckpointError naming the file and the fix: missing, damaged, not a detbench
        checkpoint, another format version, or another model / config / data.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found; pass a file from a training run's "
                              f"OUT/checkpoints/ folder (tools/train.py --out OUT)")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        if "GLOBAL" in str(e) or "global" in str(e):  # a pickled class or function; random bytes fail otherwise
            raise CheckpointError(
                f"{path}: holds Python objects that safe loading (weights_only=True) refuses, so it was not "
                f"written by detbench; pass a checkpoint from tools/train.py (OUT/checkpoints/*.pt)") from None
        raise CheckpointError(_damaged(path, "UnpicklingError: not a torch checkpoint")) from None
    except (RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile, KeyError, IndexError) as e:
        detail = str(e).splitlines()[0] if str(e) else "the file is empty or cut short"
        raise CheckpointError(_damaged(path, f"{type(e).__name__}: {detail}")) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CKPT_FORMAT:
        keys = sorted(map(str, ckpt))[:8] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(f"{path}: not a detbench checkpoint (found {keys}); pass a checkpoint written by "
                              f"tools/train.py (OUT/checkpoints/*.pt), not a bare state_dict or another "
                              f"project's file")
    if ckpt.get("version") != CKPT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {ckpt.get('version')!r}, this detbench reads "
                              f"version {CKPT_VERSION}; re-train with this version or use the matching detbench")
    missing = [k for k in ("model_name", "config", "data", "state", "model") if k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {missing}; it is incomplete, re-train or use another one")
    for part in ("config", "data"):  # compared and printed below: a bounded structure, before anything walks it
        problem = structure_problem(ckpt[part], max_values=MAX_CONFIG_VALUES)
        if problem or not isinstance(ckpt[part], Mapping):
            raise CheckpointError(f"{path}: the checkpoint's {part} is not read: {problem or 'not a mapping'}; it "
                                  f"was not written by tools/train.py from a config file: pass another checkpoint")
    if "config_digest" not in ckpt:
        warnings.warn(f"{path}: records no config digest (written by an older detbench), so an edit of its stored "
                      f"config cannot be detected; re-save it with this version to have it checked", stacklevel=2)
    elif (not isinstance(ckpt["config"], Mapping)
          or ckpt["config_digest"] != config_digest(ckpt["config"])):
        raise CheckpointError(f"{path}: the config stored in this checkpoint was changed after it was written (it "
                              f"no longer matches its recorded digest), so the weights would run with settings "
                              f"they were not trained with (e.g. another voxel_size or point_cloud_range); use the "
                              f"checkpoint as tools/train.py wrote it, or train with the new config")
    if model_name is not None and ckpt["model_name"] != model_name:
        raise CheckpointError(f"{path}: checkpoint is for model {ckpt['model_name']!r}, not {model_name!r}; "
                              f"use --model {ckpt['model_name']} or a checkpoint of {model_name}, or start a new "
                              f"run in another output folder")
    ignore_keys = tuple(ignore_keys)
    if data is not None:
        _check_same_data(path, ckpt["data"], data)
        if _fingerprint_of(ckpt["data"]) is not None and _fingerprint_of(ckpt["data"]) == _fingerprint_of(data):
            ignore_keys += ("data.root",)  # the same frames, moved: their content decides, not the path
    if config is not None:
        stored = stored_config(ckpt["config"]) if stored_config is not None else ckpt["config"]
        bad = config_diff(stored, config, ignore_keys)
        if bad:
            shown = "; ".join(bad[:6]) + (f"; and {len(bad) - 6} more" if len(bad) > 6 else "")
            raise CheckpointError(f"{path}: checkpoint was written with another config ({shown}); resume with "
                                  f"the same config file and --set options, or start a new run in another "
                                  f"output folder")
    return ckpt


DATA_FINGERPRINT_KEY = "frames_sha1"  # the training frames' content (detbench.data.gt_database.frames_fingerprint)
# recorded for evaluations (detbench.train.run.training_data_warnings), not compared on resume (the fingerprint is)
EVALUATION_ONLY_KEYS = ("dataset_sha1", "dataset_scenes", "train_frames")


def _fingerprint_of(data: Mapping) -> str | None:
    value = data.get(DATA_FINGERPRINT_KEY) if isinstance(data, Mapping) else None
    return str(value) if value else None


def _check_same_data(path: Path, saved: Mapping, now: Mapping) -> None:
    """CheckpointError unless `now` is the data the checkpoint was trained on: the same height and, when both
    record it, the same content fingerprint of the training frames (the path then does not matter: a dataset
    may move). A checkpoint without a fingerprint is compared by its recorded source path."""
    old_fp, new_fp = _fingerprint_of(saved), _fingerprint_of(now)
    ignore = (DATA_FINGERPRINT_KEY, *EVALUATION_ONLY_KEYS) + (("source",) if old_fp and new_fp else ())
    bad = config_diff(saved, now, ignore)
    if bad:
        raise CheckpointError(f"{path}: checkpoint was trained on other data ({'; '.join(bad)}); resume with "
                              f"the same --data/--height, or start a new run in another output folder")
    if old_fp and new_fp and old_fp != new_fp:
        raise CheckpointError(f"{path}: the training frames at {now.get('source', '?')} are not the ones this run "
                              f"was trained on (their content fingerprint is {new_fp[:12]}, the checkpoint's "
                              f"{old_fp[:12]}): the dataset was re-simulated or edited in place since; resume "
                              f"on the data the run started with, or start a new run in another output folder")


def _damaged(path: Path, what: str) -> str:
    older = [p.name for p in CheckpointManager(path.parent).list() if p != path]
    hint = (f"delete it to resume from the previous one ({older[-1]}) or start a new run" if older
            else "pass a checkpoint written by tools/train.py (OUT/checkpoints/*.pt), or delete this one and "
                 "train again")
    return (f"{path}: cannot read this checkpoint ({what}); "
            f"the file is damaged or truncated (e.g. a copy that stopped half-way) or not a checkpoint at all; "
            f"{hint}")


def check_finite_weights(state_dict: Mapping[str, Any], path: str | os.PathLike = "<checkpoint>") -> None:
    """CheckpointError naming the file and the first tensor holding NaN or inf (a run that diverged)."""
    for name, t in state_dict.items():
        if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise CheckpointError(f"{path}: weight {name!r} holds {bad} NaN or inf value(s) of {t.numel()}; the run "
                                  f"diverged before this checkpoint was written; use an earlier checkpoint of the "
                                  f"run, or train again with a lower train.lr")


def load_model_weights(model: nn.Module, ckpt: Mapping, path: str | os.PathLike = "<checkpoint>") -> None:
    """`model.load_state_dict(ckpt["model"])` with an error naming the file if the weights do not fit
    or are not finite."""
    check_finite_weights(ckpt["model"], path)
    try:
        unwrap_model(model).load_state_dict(ckpt["model"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not fit this model ({str(e).splitlines()[0]} ...); the checkpoint "
                              f"was written by a model built with another config; build the model from the "
                              f"checkpoint's config (ckpt['config'])") from None


def _common_model_config_diff(src: Mapping, dst: Mapping) -> list[str]:
    """Model-config keys present in both (flattened, `name` excepted) whose values differ; keys `dst`
    leaves `auto` (resolved from this run's training data, e.g. anchor sizes) may differ."""
    a, b = _flatten(src), _flatten(dst)
    return [f"{k}: {a[k]!r} (checkpoint) vs {b[k]!r} (now)" for k in sorted(set(a) & set(b))
            if k != "name" and b[k] != "auto" and a[k] != b[k]]


def init_from_checkpoint(model: nn.Module, path: str | os.PathLike, model_config: Mapping) -> dict:
    """Start `model` from the weights of another run's checkpoint wherever name and shape match.

    What OpenPCDet users do with `--pretrained_model`: e.g. a two-stage CT3D starts from a
    SECOND trained on the same data (its proposal network is SECOND's every layer), and only
    the refinement head starts from scratch. Refused with a CheckpointError naming the file
    and the fix when no weight fits, when a shared weight has another shape, when the
    weights are not finite, or when a model-config key both configs hold differs (a voxel
    size changes the meaning of every weight without changing its shape). `model_config` is
    the run's config before `auto` values are resolved from its data: those may differ
    (anchor sizes of another height's vehicles, when fine-tuning there).

    Returns a record for the run's summary: path, source model, loaded / new / unused counts.
    """
    path = Path(path)
    ckpt = load_checkpoint(path)
    check_finite_weights(ckpt["model"], path)
    fix = ("train the source with the same model settings (preset and --set model.* options), or start this run "
           "without --init-from")
    bad_cfg = _common_model_config_diff((ckpt.get("config") or {}).get("model") or {}, model_config)
    if bad_cfg:
        shown = "; ".join(bad_cfg[:4]) + (f"; and {len(bad_cfg) - 4} more" if len(bad_cfg) > 4 else "")
        raise CheckpointError(f"{path}: --init-from checkpoint was built with another model config ({shown}); {fix}")
    core = unwrap_model(model)
    own, src = core.state_dict(), ckpt["model"]
    wrong_shape = [f"{k} {tuple(src[k].shape)} vs {tuple(v.shape)}" for k, v in own.items()
                   if k in src and tuple(src[k].shape) != tuple(v.shape)]
    if wrong_shape:
        raise CheckpointError(f"{path}: --init-from weights of another shape ({'; '.join(wrong_shape[:3])}"
                              f"{' ...' if len(wrong_shape) > 3 else ''}); {fix}")
    loaded = [k for k in own if k in src]
    if not loaded:
        raise CheckpointError(f"{path}: no weight of this {ckpt['model_name']} checkpoint fits model "
                              f"{model_config.get('name', type(core).__name__)}; --init-from needs a checkpoint whose "
                              f"layers the model shares (e.g. a second checkpoint for ct3d)")
    merged = dict(own)
    merged.update({k: src[k] for k in loaded})
    core.load_state_dict(merged)
    return {"path": str(path), "model": ckpt["model_name"], "loaded_tensors": len(loaded),
            "new_tensors": len(own) - len(loaded), "unused_tensors": len([k for k in src if k not in own])}


def restore_training(ckpt: Mapping, *, model: nn.Module, optimizer: torch.optim.Optimizer | None = None,
                     scheduler: Any | None = None, scaler: Any | None = None,
                     path: str | os.PathLike = "<checkpoint>", rank: int = 0) -> TrainState:
    """Load weights and optimizer / scheduler / scaler / RNG states; return the saved TrainState.

    The generators get the states saved by `rank` (rank 0's when the run had fewer ranks).
    """
    load_model_weights(model, ckpt, path)
    for name, obj in (("optimizer", optimizer), ("scheduler", scheduler), ("scaler", scaler)):
        if obj is None:
            continue
        if name == "scaler" and not ckpt.get(name):
            continue  # saved by a run without mixed precision (CPU): the scaler starts fresh
        if name not in ckpt:
            raise CheckpointError(f"{path}: holds model weights only (no {name} state), so training cannot resume "
                                  f"from it; start a new run, or resume from a checkpoint in OUT/checkpoints/")
        try:
            obj.load_state_dict(ckpt[name])
        except (ValueError, KeyError, RuntimeError) as e:
            raise CheckpointError(f"{path}: {name} state does not fit ({e}); resume with the same config, or start "
                                  f"a new run in another output folder") from None
    rng = ckpt.get("rng") or []
    if rng:
        restore_rng_state(rng[rank] if rank < len(rng) else rng[0])
    return TrainState.from_dict(ckpt["state"])


class CheckpointManager:
    """The checkpoints of one run in `directory`; keeps the newest `keep_last` (0 or less keeps all)."""

    def __init__(self, directory: str | os.PathLike, keep_last: int = 3):
        self.directory = Path(directory)
        self.keep_last = int(keep_last)

    @staticmethod
    def name_for(state: TrainState) -> str:
        """'epoch_EEE.pt' at an epoch end, else 'epoch_EEE_step_SSSSSS.pt'."""
        if state.step_in_epoch == 0:
            return f"epoch_{state.epoch:03d}.pt"
        return f"epoch_{state.epoch:03d}_step_{state.step_in_epoch:06d}.pt"

    def list(self) -> list[Path]:
        """Checkpoint files, oldest first (by epoch, then step)."""
        if not self.directory.is_dir():
            return []
        found = []
        for p in self.directory.iterdir():
            m = _NAME_RE.match(p.name)
            if m and p.is_file():
                found.append(((int(m.group(1)), int(m.group(2) or 0)), p))
        return [p for _, p in sorted(found)]

    def latest(self) -> Path | None:
        """The newest checkpoint, or None when there is none."""
        files = self.list()
        return files[-1] if files else None

    def save(self, state: TrainState, **kwargs) -> Path:
        """`save_checkpoint` into `directory/name_for(state)`, then delete all but the newest `keep_last`."""
        path = save_checkpoint(self.directory / self.name_for(state), state=state, **kwargs)
        self.prune()
        return path

    def prune(self) -> list[Path]:
        """Delete all but the newest `keep_last` checkpoints; returns the deleted paths."""
        if self.keep_last <= 0:
            return []
        files = self.list()
        doomed = files[:-self.keep_last]
        for p in doomed:
            p.unlink(missing_ok=True)
        return doomed
