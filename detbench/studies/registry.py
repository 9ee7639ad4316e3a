"""What the studies need of the detector registry, which lives above detbench (the `models` package).

detbench never imports models: a tool passes the registry in (`import models; run(..., registry=models)`),
and a child process that needs it imports it by the module name it is given (`registry.__name__`).
"""
from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any, Protocol


class ModelRegistry(Protocol):
    """The detector registry's functions the studies call (the `models` module provides them)."""

    __name__: str
    REGISTRY: Mapping[str, type]

    def get_model_class(self, name: str) -> type:
        """The class registered as `name`; ValueError naming the registered ones when there is none."""

    def prepare_model_config(self, name: str, model_cfg: dict, train_boxes: Any) -> dict:
        """The model's config completed from the training boxes (anchor sizes and the like)."""

    def build_model(self, name: str, model_cfg: dict) -> Any:
        """The detector `name` built from its config."""

    def upgrade_stored_model_config(self, name: str, model_cfg: dict) -> dict:
        """A checkpoint's stored `model:` section in today's keys (one stored by an earlier version lacks keys
        that had values in code then)."""


def import_registry(module: str) -> ModelRegistry:
    """The registry module named `module` (in a child process started by a study)."""
    return importlib.import_module(module)


__all__ = ["ModelRegistry", "import_registry"]
