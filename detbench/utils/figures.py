"""Writing a matplotlib figure to disk: one saver for every report and study figure."""
from __future__ import annotations

import os
from pathlib import Path

from detbench.utils.io import atomic_save


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 150, fmt: str | None = None, tight: bool = True,
                facecolor=None) -> Path:
    """Save `fig` to `path` atomically (written to a temporary file, then renamed) and return the path.

    fmt: the file format, by default the suffix of `path` (png when it has none); tight: crop to
    the drawn area (bbox_inches="tight"); facecolor: the background, matplotlib's default when None.
    """
    path = Path(path)
    kwargs = {"format": fmt or path.suffix.lstrip(".").lower() or "png", "dpi": dpi}
    if tight:
        kwargs["bbox_inches"] = "tight"
    if facecolor is not None:
        kwargs["facecolor"] = facecolor
    atomic_save(path, lambda tmp: fig.savefig(tmp, **kwargs))
    return path


__all__ = ["save_figure"]
