"""YAML configs: inheritance, command-line overrides and validation against known keys.

A config file may name bases with `_base_: other.yaml` (or a list of files), resolved
relative to the file; later bases and the file itself override earlier ones, dictionaries
merge key by key, anything else is replaced. `--set a.b.c=value` overrides parse `value`
as YAML (so `1e-3`, `true`, `[1, 2]` work).

Validation is against a *reference* config (the defaults a tool ships): a key that is not
in the reference is an error that names the key, the file it came from and the closest
known key. Keys under a mapping listed in `open_keys` may be free-form. A value must also
be of the kind its reference holds (`check_value`): a section stays a section, a switch
true or false, a count an integer, a number a number, a list a list (of numbers, where the
reference's are; keys whose reference is a string or null take any value: `auto` or a
list, a path or null).

The YAML files users read are the one home of the defaults: `shipped_defaults(section)` is
a section of configs/default.yaml (data, train, augment, eval), from which the library's
typed configs (TrainConfig, AugmentConfig, GTSamplingConfig) and the simulated dataset take
every missing key; `shipped_default("eval.iou_threshold")` is one key, which functions that
take None for a default (IoU and score thresholds, test_fraction, frames_per_scene) and the
tools' argparse defaults read. `CONFIG_DIR` is configs/ installed with the package (the data package
`detbench.configs`, see pyproject.toml) or, in a checkout, the top-level configs/.
"""
from __future__ import annotations

import copy
import difflib
import functools
from pathlib import Path
from collections.abc import Iterable, Mapping
from typing import Any

import yaml

from detbench.utils.untrusted import MAX_DEPTH, clip, excerpt, structure_problem

# values a config may hold once YAML aliases are expanded: a run's config has a few hundred; an alias bomb
# (each anchor repeating the one before) would expand to billions wherever the config is walked or printed
MAX_CONFIG_VALUES = 100_000


def _config_dir() -> Path:
    """configs/ as installed with the package (detbench/configs), else the checkout's top-level configs/."""
    here = Path(__file__).resolve().parent
    installed = here / "configs"
    return installed if installed.is_dir() else here.parent / "configs"


CONFIG_DIR = _config_dir()
DEFAULTS_FILE = "default.yaml"


class ConfigError(ValueError):
    """A config problem, worded for the user: what is wrong, where, and how to fix it."""


def yaml_value(text: str, where: str) -> Any:
    """`text` parsed as YAML, refused (ConfigError naming `where`) when it nests deeper than MAX_DEPTH levels,
    holds itself, or expands through aliases to more than MAX_CONFIG_VALUES values. yaml.YAMLError passes."""
    try:
        data = yaml.safe_load(text)
    except RecursionError:
        data = _TOO_DEEP
    problem = (f"it is nested deeper than {MAX_DEPTH} levels" if data is _TOO_DEEP
               else structure_problem(data, max_values=MAX_CONFIG_VALUES))
    if problem:
        raise ConfigError(f"{where}: not read: {problem}; write the values out (a config holds a few hundred)")
    return data


_TOO_DEEP = object()


def _read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        data = yaml_value(path.read_text(encoding="utf-8"), str(path))
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {clip(e)}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (byte {e.start} cannot be decoded); save the config file "
                          f"as UTF-8") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of keys, got {type(data).__name__}")
    return data


def deep_merge(base: Mapping, over: Mapping) -> dict:
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def resolve_config_path(name: str | Path, relative_to: Path | None = None) -> Path:
    """A path as given, else relative to `relative_to`, else in the project's configs/."""
    p = Path(name)
    candidates = [p]
    if relative_to is not None:
        candidates.append(relative_to / p)
    candidates.append(CONFIG_DIR / p)
    if p.suffix == "":
        candidates += [c.with_suffix(".yaml") for c in candidates]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    known = sorted(x.stem for x in CONFIG_DIR.glob("*.yaml")) if CONFIG_DIR.is_dir() else []
    hint = f"; configs shipped: {', '.join(known)}" if known else ""
    raise ConfigError(f"config {str(name)!r} not found "
                      f"(looked in {', '.join(str(c.parent) for c in candidates[:3])}){hint}")


def load_config(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict:
    """Load a YAML config with its `_base_` chain merged in."""
    path = resolve_config_path(path)
    if path in _seen:
        raise ConfigError(f"{path}: _base_ cycle: {' -> '.join(str(p) for p in _seen + (path,))}")
    data = _read_yaml(path)
    bases = data.pop("_base_", [])
    if isinstance(bases, str):
        bases = [bases]
    merged: dict = {}
    for b in bases:
        merged = deep_merge(merged, load_config(resolve_config_path(b, path.parent), _seen + (path,)))
    return deep_merge(merged, data)


def model_name_of(path: str | Path) -> str | None:
    """The detector a config file configures, or None when it names none.

    A model's registered name is written once: as the file name of its config,
    configs/<name>.yaml (any top-level file of CONFIG_DIR with a `model:` section). A config
    elsewhere (a user's file, a run's saved config.yaml) names its detector with `model.name`
    or inherits it from a base; of the files `load_config` merges, the last that names one wins.
    """
    path = resolve_config_path(path)
    data = _read_yaml(path)
    model = data.get("model")
    if isinstance(model, Mapping) and model.get("name"):
        return str(model["name"])
    if isinstance(model, Mapping) and path.parent == CONFIG_DIR.resolve():
        return path.stem
    bases = data.get("_base_", [])
    for b in reversed([bases] if isinstance(bases, str) else bases):
        name = model_name_of(resolve_config_path(b, path.parent))
        if name:
            return name
    return None


@functools.lru_cache(maxsize=1)
def _shipped_defaults() -> dict:
    return load_config(CONFIG_DIR / DEFAULTS_FILE)


def shipped_defaults(section: str) -> dict:
    """A copy of `section` (data | train | augment | eval) of configs/default.yaml: the defaults
    every run starts from, and the values a typed config takes for keys it is not given."""
    return copy.deepcopy(_shipped_defaults()[section])


def shipped_default(dotted: str, value: Any = None) -> Any:
    """`value` when it is given (not None), else the key `dotted` of configs/default.yaml, e.g.
    `shipped_default("eval.iou_threshold")`: how a signature that takes None for "the default" finds it."""
    if value is not None:
        return value
    node: Any = _shipped_defaults()
    for k in dotted.split("."):
        if not isinstance(node, Mapping) or k not in node:
            raise KeyError(f"{dotted!r} is not a key of {CONFIG_DIR / DEFAULTS_FILE}")
        node = node[k]
    return copy.deepcopy(node)


def parse_override(item: str) -> tuple[list[str], Any]:
    if "=" not in item:
        raise ConfigError(f"override {excerpt(item)} must look like key.sub=value")
    key, _, raw = item.partition("=")
    key = key.strip()
    if not key:
        raise ConfigError(f"override {excerpt(item)} has an empty key")
    try:
        value = yaml_value(raw, f"--set {excerpt(key)}") if raw.strip() else ""
        return key.split("."), _numbers_from_strings(value)
    except yaml.YAMLError:
        return key.split("."), _numbers_from_strings(raw)
    except ValueError as e:  # Python reads no integer of more than sys.get_int_max_str_digits() digits
        if isinstance(e, ConfigError):
            raise
        raise ConfigError(f"--set {excerpt(key)}: the value is a number {len(raw.strip())} characters long, too "
                          f"long to read as one; no setting takes such a number: give one of a sensible size") from None


def _numbers_from_strings(value: Any) -> Any:
    """`value` with number-like strings made numbers, inside lists and mappings too: YAML 1.1 reads 1e-3 and
    1e30 as strings, and users mean numbers."""
    if isinstance(value, list):
        return [_numbers_from_strings(v) for v in value]
    if isinstance(value, dict):
        return {k: _numbers_from_strings(v) for k, v in value.items()}
    if isinstance(value, str):
        try:
            return float(value) if any(c in value for c in ".eE") else int(value)
        except ValueError:
            pass
    return value


def apply_overrides(cfg: dict, overrides: Iterable[str], reference: Mapping | None = None,
                    open_keys: Iterable[str] = ()) -> dict:
    """Return a copy of `cfg` with `key.sub=value` overrides applied (validated if `reference`)."""
    out = copy.deepcopy(cfg)
    for item in overrides or ():
        keys, value = parse_override(item)
        if reference is not None:
            ref = _check_path(keys, reference, f"--set {item}", tuple(open_keys))
            if ref is not _OPEN:
                check_value(value, ref, f"--set {item}", ".".join(keys))
        node = out
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[keys[-1]] = value
    return out


def _closest(key: str, choices: Iterable[str]) -> str:
    m = difflib.get_close_matches(key, list(choices), n=1, cutoff=0.5)
    return f"; did you mean {m[0]!r}?" if m else ""


_OPEN = object()  # what `_check_path` returns for a key under an open (free-form) section


def _check_path(keys: list[str], reference: Mapping, where: str, open_keys: tuple[str, ...]) -> Any:
    """The reference value at `keys` (ConfigError when a key is unknown), or `_OPEN`."""
    node: Any = reference
    for depth, k in enumerate(keys):
        dotted = ".".join(keys[: depth + 1])
        parent = ".".join(keys[:depth])
        if parent in open_keys:
            return _OPEN
        if not isinstance(node, Mapping):
            raise ConfigError(f"{where}: {'.'.join(keys[:depth])} is a value, not a section; it has no key {k!r}")
        if k not in node:
            known = ", ".join(sorted(map(str, node))) or "(none)"
            raise ConfigError(f"{where}: unknown config key {excerpt(dotted)}{_closest(k, map(str, node))} "
                              f"(known keys here: {known})")
        node = node[k]
    return node


def _kind(value: Any) -> str | None:
    """What a reference value asks for, in words; None when anything goes (a string or null)."""
    if isinstance(value, bool):
        return "true or false"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, (list, tuple)):
        return "a list of numbers" if value and all(map(_is_number, value)) else "a list"
    return None


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _fits(value: Any, kind: str) -> bool:
    is_list = isinstance(value, (list, tuple))
    return {"true or false": isinstance(value, bool), "an integer": _is_number(value) and isinstance(value, int),
            "a number": _is_number(value), "a list": is_list,
            "a list of numbers": is_list and all(map(_is_number, value))}[kind]


def check_value(value: Any, ref: Any, where: str, dotted: str) -> None:
    """ConfigError naming `dotted` when `value` is not of the kind the reference value `ref` is."""
    if isinstance(ref, Mapping):
        if not isinstance(value, Mapping):
            first = next(iter(ref), "key")
            raise ConfigError(f"{where}: {dotted} is a section of keys ({', '.join(sorted(map(str, ref)))}), not a "
                              f"value; set one of its keys instead, e.g. {dotted}.{first}=...")
        return
    kind = _kind(ref)
    if kind is not None and not _fits(value, kind):
        shown = str(ref).lower() if isinstance(ref, bool) else repr(ref)
        raise ConfigError(f"{where}: {dotted} must be {kind} (like the default {shown}), got {excerpt(value)}")


def validate(cfg: Mapping, reference: Mapping, where: str = "config", open_keys: Iterable[str] = (),
             _prefix: str = "") -> None:
    """Raise ConfigError for any key of `cfg` that `reference` does not have, or whose value is not
    of the kind the reference's is (`check_value`)."""
    open_keys = tuple(open_keys)
    for k, v in cfg.items():
        dotted = f"{_prefix}{k}"
        if k not in reference:
            known = ", ".join(sorted(map(str, reference))) or "(none)"
            raise ConfigError(f"{where}: unknown config key {excerpt(dotted)}{_closest(str(k), map(str, reference))} "
                              f"(known keys here: {known})")
        if dotted in open_keys:
            continue
        if isinstance(v, Mapping) and isinstance(reference[k], Mapping):
            validate(v, reference[k], where, open_keys, f"{dotted}.")
        else:
            check_value(v, reference[k], where, dotted)


def section_with_defaults(d: Any, defaults: Mapping, where: str) -> dict:
    """A config section `d` (None = empty) checked against `defaults` (`validate`), missing keys filled in."""
    if d is not None and not isinstance(d, Mapping):
        raise ConfigError(f"{where} must be a section of keys (see configs/default.yaml), got {excerpt(d)}")
    d = dict(d or {})
    validate(d, defaults, where=where)  # unknown keys, and each value of its default's kind
    return {**defaults, **d}


def get(cfg: Mapping, dotted: str, default: Any = None) -> Any:
    node: Any = cfg
    for k in dotted.split("."):
        if not isinstance(node, Mapping) or k not in node:
            return default
        node = node[k]
    return node


def dump(cfg: Mapping) -> str:
    return yaml.safe_dump(dict(cfg), sort_keys=False)
