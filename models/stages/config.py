"""Reading a model's config into typed, frozen stage configs.

Each stage that a model's YAML sets up has one frozen dataclass (beside its stage, e.g.
`anchor_head.AnchorHeadConfig`), used by every model that has the stage. Its `read(section)`
names every key it reads and checks each value by what it means: a fraction, an IoU, a count, a
length in metres, an angle, a choice among names. No key has a default: every value comes from
configs/<model>.yaml, and the model's `prepare_config` fills only what is derived from the data
(`auto`). `StageConfig.from_config(mapping, path, source)` reads a whole section:

  a missing key        ModelConfigError "<file>: model.head.pos_iou is missing; ..."
  a key nothing reads  ModelConfigError "<file>: unknown key model.head.pos_io; did you mean 'pos_iou'?"
  a value out of range ModelConfigError "<file>: model.head.pos_iou must be an IoU in [0, 1], got 1.5"

`Section` is the reader the dataclasses use: typed getters that mark a key as read, `section`
for a nested dataclass, `finish` for the unknown-key check.
"""
from __future__ import annotations

import difflib
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

T = TypeVar("T")
C = TypeVar("C", bound="StageConfig")


class ModelConfigError(ValueError):
    """A model config key missing, unknown or out of its range; the message names the file and the dotted key."""


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def is_count(v: Any, low: int = 1) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= low


def is_size3(v: Any) -> bool:
    """[length, width, height], each a positive number of metres."""
    return isinstance(v, (list, tuple)) and len(v) == 3 and all(is_number(x) and x > 0 for x in v)


def _is_positive(v: Any) -> bool:
    return is_number(v) and v > 0


def is_list_of(v: Any, item: Callable[[Any], bool], empty: bool = False) -> bool:
    """A list (non-empty unless `empty`) whose every entry passes `item`."""
    return isinstance(v, (list, tuple)) and (empty or len(v) > 0) and all(item(x) for x in v)


def _numbers_in(value: Any):
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        yield value
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _numbers_in(v)


class Section:
    """One mapping of a model config (`path`, e.g. 'model.head', of the file `source`) being read.

    Every getter takes a key, checks its value and returns it converted (tuples for lists); `finish`
    refuses the keys no getter took.
    """

    def __init__(self, data: Any, path: str, source: str):
        if not isinstance(data, Mapping):
            raise ModelConfigError(f"{source}: {path} must be a section of keys, got {data!r}")
        self.data, self.path, self.source = data, path, source
        self.taken: set[str] = set()

    def dotted(self, key: str) -> str:
        return f"{self.path}.{key}"

    def error(self, key: str, need: str) -> ModelConfigError:
        return ModelConfigError(f"{self.source}: {self.dotted(key)} must be {need}, got {self.data.get(key)!r}")

    def raw(self, key: str) -> Any:
        """The value of `key` as written; ModelConfigError naming the dotted key and the file when missing."""
        if key not in self.data:
            raise ModelConfigError(f"{self.source}: {self.dotted(key)} is missing; every model key is set in "
                                   f"the model's YAML (configs/<model>.yaml), which documents it")
        self.taken.add(key)
        value = self.data[key]
        if any(not math.isfinite(v) for v in _numbers_in(value)):
            raise self.error(key, "finite (no NaN or inf)")
        return value

    def skip(self, *keys: str) -> None:
        """Mark `keys` as known without reading them (e.g. `name`, which the registry reads)."""
        self.taken.update(k for k in keys if k in self.data)

    def check(self, key: str, ok: Callable[[Any], bool], need: str) -> Any:
        value = self.raw(key)
        if not ok(value):
            raise self.error(key, need)
        return value

    def number(self, key: str, need: str = "a number") -> float:
        return float(self.check(key, is_number, need))

    def fraction(self, key: str, what: str = "a fraction") -> float:
        """A share, a probability or an IoU: a number in [0, 1]."""
        return float(self.check(key, lambda v: is_number(v) and 0 <= v <= 1, f"{what} in [0, 1]"))

    def positive(self, key: str, what: str = "a positive number") -> float:
        return float(self.check(key, lambda v: is_number(v) and v > 0, what))

    def non_negative(self, key: str, what: str = "a number >= 0") -> float:
        return float(self.check(key, lambda v: is_number(v) and v >= 0, what))

    def count(self, key: str, low: int = 1, high: int | None = None, what: str = "") -> int:
        need = (f"an integer from {low} to {high}" if high is not None else f"an integer >= {low}") + what
        return int(self.check(key, lambda v: is_count(v, low) and (high is None or v <= high), need))

    def counts(self, key: str, low: int = 1, length: int | None = None, empty: bool = False) -> tuple[int, ...]:
        """A list of integers >= `low`: non-empty unless `empty`, of `length` items when given."""
        need = f"made of integers >= {low}, " + ("a list" if empty else "a non-empty list" if length is None
                                                 else f"a list of {length}")

        def ok(v) -> bool:
            return is_list_of(v, lambda x: is_count(x, low), empty) and (length is None or len(v) == length)

        return tuple(int(x) for x in self.check(key, ok, need))

    def numbers(self, key: str, length: int | None = None, low: float | None = None, need: str = "") -> tuple:
        """A non-empty list of numbers (> `low` when given, of `length` items when given)."""
        need = need or (("a non-empty list" if length is None else f"a list of {length}") + " numbers"
                        + (f" > {low:g}" if low is not None else ""))

        def ok(v) -> bool:
            return is_list_of(v, lambda x: is_number(x) and (low is None or x > low)) and (
                length is None or len(v) == length)

        return tuple(float(x) for x in self.check(key, ok, need))

    def flag(self, key: str) -> bool:
        return bool(self.check(key, lambda v: isinstance(v, bool), "true or false"))

    def choice(self, key: str, options: tuple[str, ...], what: str = "") -> str:
        need = "one of " + ", ".join(repr(o) for o in options) + what
        return str(self.check(key, lambda v: isinstance(v, str) and v in options, need))

    def section(self, key: str, cls: type[T]) -> T:
        """The nested section `key` read by the dataclass `cls` (its keys checked for unknown ones)."""
        sub = Section(self.raw(key), self.dotted(key), self.source)
        value = cls.read(sub)
        sub.finish()
        return value

    def order(self, low: str, high: str) -> None:
        """ModelConfigError when the value of `low` exceeds that of `high` (both read already)."""
        lo, hi = self.data[low], self.data[high]
        if lo > hi:
            raise ModelConfigError(f"{self.source}: {self.dotted(low)} ({lo}) must not exceed {self.dotted(high)} "
                                   f"({hi})")

    def finish(self) -> None:
        """ModelConfigError for a key of this section that no config reads, with the closest known key."""
        unknown = [k for k in self.data if k not in self.taken]
        if unknown:
            key = str(unknown[0])
            close = difflib.get_close_matches(key, [str(k) for k in self.taken], n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f" (known: {', '.join(sorted(self.taken))})"
            raise ModelConfigError(f"{self.source}: unknown key {self.dotted(key)}{hint}")


class StageConfig(ABC):
    """Base of the frozen stage configs: `read(section)` in each, `from_config` for a whole mapping."""

    @classmethod
    @abstractmethod
    def read(cls: type[C], s: Section) -> C:
        """The config from its section, each key read through `s` (so `finish` can name the unread ones)."""

    @classmethod
    def from_config(cls: type[C], section: Any, path: str = "model", source: str = "the model config") -> C:
        """The config of `section` (the mapping at dotted `path` of the file `source`), every key checked."""
        s = Section(section, path, source)
        value = cls.read(s)
        s.finish()
        return value


# ---- readers of nested lists (PointNet++ levels and scales)
def centre_counts(s: Section, key: str) -> tuple[int | None, ...]:
    """A list of centre counts per level: integers >= 1, or -1 for every point (None)."""
    value = s.check(key, lambda v: is_list_of(v, lambda x: is_count(x) or x == -1),
                    "a non-empty list of centre counts (integers >= 1, or -1: every point)")
    return tuple(None if v == -1 else int(v) for v in value)


def ball_radii(s: Section, key: str, depth: int = 2) -> tuple:
    """Ball radii in metres: a list (of lists, with `depth` 2) of positive numbers."""
    ok = _is_positive if depth == 1 else (lambda v: is_list_of(v, _is_positive))
    value = s.check(key, lambda v: is_list_of(v, ok), "a non-empty list of " + (
        "positive radii in metres" if depth == 1 else "non-empty lists of positive radii in metres"))
    return tuple(float(v) for v in value) if depth == 1 else tuple(tuple(float(x) for x in v) for v in value)


def nested_counts(s: Section, key: str, depth: int) -> tuple:
    """Counts or widths nested `depth` lists deep: every list non-empty, every number an integer >= 1."""
    def ok(v, d=depth):
        return is_list_of(v, is_count if d == 1 else (lambda x: ok(x, d - 1)))

    def tup(v, d=depth):
        return tuple(int(x) for x in v) if d == 1 else tuple(tup(x, d - 1) for x in v)

    return tup(s.check(key, ok, "a non-empty list of " + "non-empty lists of " * (depth - 1) + "integers >= 1"))
