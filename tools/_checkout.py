"""Imported first by a tool run as a file (`python tools/<name>.py`): when detbench or models is
not importable (a plain checkout, not installed), the checkout's root goes on sys.path, where
both packages live. An installed detbench, or `python -m tools.<name>` from the root, needs nothing."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def add_checkout_root(path: list[str] = sys.path) -> bool:
    """Put the checkout's root first on `path` unless detbench and models import as they are; True when added."""
    if importlib.util.find_spec("detbench") is not None and importlib.util.find_spec("models") is not None:
        return False
    if str(ROOT) not in path:
        path.insert(0, str(ROOT))
    return True


add_checkout_root()
