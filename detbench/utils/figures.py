"""Writing a matplotlib figure to disk: one saver for every report and study figure."""
from __future__ import annotations

import os
from pathlib import Path

from detbench.utils.atomic import atomic_save

LEGEND_SMALL = 10  # up to this many series keep the palette and the legend as drawn for a few heights


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


def series_colours(n: int, palette=None, cmap: str = "viridis") -> list[str]:
    """`n` distinct colours, one per series (e.g. per height): the first n of `palette` (default matplotlib's
    colour cycle, 10 colours) when it has enough, else `cmap` sampled evenly at n points (interpolated between
    its colours, so they stay distinct for any n; in order, which suits ordered series such as heights)."""
    import numpy as np
    from matplotlib import colormaps, rcParams
    from matplotlib.colors import to_hex

    if palette is None:
        palette = rcParams["axes.prop_cycle"].by_key().get("color", [])
    palette = list(palette)
    if n <= len(palette):
        return palette[:n]
    table = colormaps[cmap](np.linspace(0.0, 1.0, 256))[:, :3]
    at = np.linspace(0.0, 0.92, n) * 255  # the top of viridis is too pale to read on white
    rgb = np.stack([np.interp(at, np.arange(256), table[:, c]) for c in range(3)], axis=1)
    colours = [to_hex(c) for c in rgb]
    if len(set(colours)) < n:  # more series than 24-bit steps along the map: keep full precision
        return [tuple(float(v) for v in c) for c in rgb]
    return colours


__all__ = ["LEGEND_SMALL", "save_figure", "series_colours"]
