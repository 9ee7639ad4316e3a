"""The cross-height matrix: each detector trained at one height and tested at each height.

Rows are training heights, columns test heights, one matrix per model; the diagonal is the
study's own figure (trained and tested at the same height). Built from evaluation reports
(`tools/eval.py --ckpt CKPT --test-height H`), which carry "trained_height" and "height".
Values are fractions in [0, 1] (recall or AP@R40 at the reports' IoU), None where missing.
"""
from __future__ import annotations

import math
from pathlib import Path
from collections.abc import Sequence

from detbench.data.frame import height_or_rig, key_label, key_order, key_text
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.report import source_label
from detbench.utils.figures import save_figure

METRICS = {"ap_r40": "AP@R40", "recall": "Recall"}  # report key -> the name printed


def cross_height_matrix(reports: Sequence[dict], metric: str = "ap_r40", range_name: str = "small",
                        level: str = "all") -> dict:
    """{"heights": sorted, "models": [...], "values": {model: [[v(train i, test j)]]}, "data": the checkpoints'
    training preset and where the frames come from (`detbench.eval.report.source_label`, the figure's title
    names it), ...}.

    Every report needs "model", "height" (tested) and "trained_height"; two reports for the
    same (model, trained, tested) triple are an error.
    """
    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
    if range_name not in RANGE_NAMES or level not in LEVELS:
        raise ValueError(f"unknown range/level {range_name!r}/{level!r}")
    cells: dict[tuple[str, float | str, float | str], float | None] = {}
    heights: set[float | str] = set()
    models: list[str] = []
    for i, rep in enumerate(reports):
        if rep.get("trained_height") is None:
            raise ValueError(f"report {i} ({rep.get('model')!r} at {rep.get('height')}) has no trained_height; "
                             f"cross-height reports come from tools/eval.py --ckpt")
        m, tr, te = str(rep["model"]), height_or_rig(rep["trained_height"]), height_or_rig(rep["height"])
        if (m, tr, te) in cells:
            raise ValueError(f"two reports for {m} trained at {key_label(tr)} and tested at {key_label(te)}")
        cells[(m, tr, te)] = rep["results"][range_name][level][metric]
        heights.update((tr, te))
        if m not in models:
            models.append(m)
    hs = sorted(heights, key=key_order)
    values = {m: [[cells.get((m, tr, te)) for te in hs] for tr in hs] for m in models}
    return {"metric": metric, "range": range_name, "level": level, "heights": hs, "models": models,
            "values": values, "data": source_label(reports)}


def cross_height_markdown(mat: dict) -> list[str]:
    """One table per model: rows trained at, columns tested at; the diagonal in bold."""
    hs = mat["heights"]
    name = METRICS[mat["metric"]]
    out = []
    for m in mat["models"]:
        out += [f"{name} of {m} ({mat['range']} range, {mat['level']} level); rows: trained at, columns: tested at "
                f"(bold: the same height).", "",
                "| trained \\ tested | " + " | ".join(key_label(h) for h in hs) + " |",
                "|---|" + "---:|" * len(hs)]
        for i, tr in enumerate(hs):
            row = []
            for j, _ in enumerate(hs):
                v = mat["values"][m][i][j]
                s = "-" if v is None else f"{v:.3f}"
                row.append(f"**{s}**" if i == j else s)
            out.append(f"| {key_label(tr)} | " + " | ".join(row) + " |")
        out.append("")
    return out


def plot_cross_height(mat: dict, path: str | Path) -> Path:
    """A heat map per model (rows trained at, columns tested at), values written in, diagonal boxed."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle


    hs, models = mat["heights"], mat["models"]
    fig = Figure(figsize=(3.2 * len(models) + 0.6, 3.2))
    name = METRICS[mat["metric"]]
    for k, m in enumerate(models):
        ax = fig.add_subplot(1, len(models), k + 1)
        grid = [[math.nan if v is None else v for v in row] for row in mat["values"][m]]
        im = ax.imshow(grid, vmin=0.0, vmax=1.0, cmap="viridis", origin="upper")
        for i in range(len(hs)):
            for j in range(len(hs)):
                v = grid[i][j]
                ax.text(j, i, "-" if math.isnan(v) else f"{v:.2f}", ha="center", va="center",
                        color="white" if (math.isnan(v) or v < 0.5) else "black", fontsize=8)
            ax.add_patch(Rectangle((i - 0.5, i - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=1.5))
        ax.set_xticks(range(len(hs)), [key_text(h) for h in hs])
        ax.set_yticks(range(len(hs)), [key_text(h) for h in hs])
        unit = "" if any(isinstance(h, str) for h in hs) else " (m)"
        ax.set_xlabel(f"tested at{unit}")
        if k == 0:
            ax.set_ylabel(f"trained at{unit}")
        ax.set_title(m, fontsize=9)
    data = f"; {mat['data']}" if mat.get("data") else ""
    fig.suptitle(f"{name}, {mat['range']} range, {mat['level']} level (red: same height{data})", fontsize=9)
    fig.colorbar(im, ax=fig.axes, shrink=0.8)
    return save_figure(fig, path)


__all__ = ["cross_height_matrix", "cross_height_markdown", "plot_cross_height"]
