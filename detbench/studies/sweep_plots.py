"""Figures of the height sweep (PNG, matplotlib Agg; units in the axis labels).

- `plot_ldr_vs_height`: LDR against mounting height, one panel per range, one line per importance
  level, the 95 % scene-bootstrap interval as a band;
- `plot_scores_vs_height`: each placement score against height, one line per range, with bands;
- `plot_ldr_distance_map`: LDR by height (rows) and distance bin (columns) as a heat map.

All take the dict of `HeightSweep.report()`.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from detbench.data.regions import LEVELS, RANGE_NAMES, RANGES
from detbench.studies.ability_plots import world_label
from detbench.studies.placement import SCORE_NAMES
from detbench.utils.figures import save_figure

_LEVEL_STYLE = {"all": ("All", "#1f77b4", "o-"), "top3": ("Top3", "#d62728", "s-"), "top6": ("Top6", "#2ca02c", "^-")}
_RANGE_STYLE = {"small": "#e0b000", "moderate": "#2ca02c", "large": "#3b7dd8"}


def _nan(v) -> float:
    return float("nan") if v is None else float(v)


def _world(report: dict) -> str:
    """Where the sweep's figures come from, for the titles (`world_label` of its ability report)."""
    return world_label(report["ability"])


def _band(ax, x, cis, colour):
    lo = np.array([np.nan if c is None else c[0] for c in cis], dtype=float)
    hi = np.array([np.nan if c is None else c[1] for c in cis], dtype=float)
    if np.isfinite(lo).any():
        ax.fill_between(x, lo, hi, color=colour, alpha=0.18, linewidth=0)


def plot_ldr_vs_height(report: dict, path: str | os.PathLike) -> Path:
    """LDR (fraction) against mounting height (m) per range and level, with 95 % bands."""
    heights = report["heights"]
    x = np.array([float(h) for h in heights])
    ab = report["ability"]
    unc = ab["extras"]["uncertainty"]["heights"]
    fig = Figure(figsize=(13, 4.3))
    axes = fig.subplots(1, len(RANGE_NAMES), sharey=True)
    for ax, r in zip(axes, RANGE_NAMES):
        for lv in LEVELS:
            name, colour, style = _LEVEL_STYLE[lv]
            y = np.array([_nan(ab["heights"][h][r][lv]["ldr"]) for h in heights])
            _band(ax, x, [unc[h][r][lv]["ci95"] for h in heights], colour)
            ax.plot(x, y, style, color=colour, ms=3.5, lw=1.3, label=name)
        x0, x1, ym = RANGES[r]
        ax.set_title(f"{r} range (0-{x1:g} m, |y|<={ym:g} m)", fontsize=10)
        ax.set_xlabel("LiDAR mounting height (m)")
        ax.grid(alpha=0.3)
        ax.set_ylim(0, 1.02)
    axes[0].set_ylabel("LDR = LiDAR-detected / total")
    axes[0].legend(fontsize=9, loc="lower right")
    src = ab["extras"].get("source") or {}
    sensor = (src.get("sensor") or {}).get("preset", "")
    fig.suptitle(f"LiDAR detection rate against mounting height ({_world(report)}, {report['num_frames']} frames, "
                 f"{report['num_scenes']} scenes, same traffic at every height"
                 f"{', sensor ' + sensor if sensor else ''}; "
                 f"bands: 95 % bootstrap over scenes)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def plot_scores_vs_height(report: dict, path: str | os.PathLike) -> Path:
    """Each placement score against height (m), one line per range, 95 % bands where there are intervals."""
    heights = report["heights"]
    x = np.array([float(h) for h in heights])
    sc = report["scores"]
    names = [s for s in SCORE_NAMES if all(s in sc["heights"][h][r] for h in heights for r in RANGE_NAMES)]
    fig = Figure(figsize=(3.6 * len(names), 3.8))
    axes = np.atleast_1d(fig.subplots(1, len(names)))
    for ax, s in zip(axes, names):
        for r in RANGE_NAMES:
            cells = [sc["heights"][h][r][s] for h in heights]
            if s == "smig":
                y = np.array([_nan(c["fraction"]) for c in cells])
            else:
                y = np.array([_nan(c["value"]) for c in cells])
                _band(ax, x, [c["ci95"] for c in cells], _RANGE_STYLE[r])
            ax.plot(x, y, "o-", color=_RANGE_STYLE[r], ms=3, lw=1.2, label=r)
        unit = "fraction of the region's entropy" if s == "smig" else sc["units"][s]
        ax.set_title(("S-MIG (Hu et al.)" if s == "smig" else s) + (" *" if s == sc["primary"] else ""), fontsize=10)
        ax.set_ylabel(unit, fontsize=8)
        ax.set_xlabel("mounting height (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Training-free placement scores against height ({_world(report)}; * primary score; "
                 f"definitions in the report)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def plot_ldr_distance_map(report: dict, path: str | os.PathLike) -> Path:
    """Heat map of LDR (colour, fraction) by mounting height (rows, m) and box-centre x bin (columns, m)."""
    heights = report["heights"]
    dist = report["ldr_vs_distance"]
    edges = np.asarray(dist["edges_m"], dtype=float)
    z = np.array([[_nan(v) for v in dist["heights"][h]["ldr"]] for h in heights], dtype=float)
    fig = Figure(figsize=(9, 0.28 * len(heights) + 2.2))
    ax = fig.subplots()
    y = np.array([float(h) for h in heights])
    if len(y) > 1:
        step = np.diff(y)
        yb = np.concatenate([[y[0] - step[0] / 2], y[:-1] + step / 2, [y[-1] + step[-1] / 2]])
    else:
        yb = np.array([y[0] - 0.05, y[0] + 0.05])
    mesh = ax.pcolormesh(edges, yb, z, cmap="viridis", vmin=0.0, vmax=1.0, shading="flat")
    cb = fig.colorbar(mesh, ax=ax)
    cb.set_label("LDR = detected / total")
    ax.set_xlabel(f"box centre x (m), {dist['bin_m']:g} m bins; |y| <= 15 m")
    ax.set_ylabel("LiDAR mounting height (m)")
    ax.set_title(f"LDR against distance and height ({_world(report)}, {report['num_frames']} frames)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def save_sweep_figures(report: dict, out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write every sweep figure into `out_dir`; returns {name: path}."""
    out = Path(out_dir)
    return {"ldr_vs_height": plot_ldr_vs_height(report, out / "ldr_vs_height.png"),
            "scores_vs_height": plot_scores_vs_height(report, out / "scores_vs_height.png"),
            "ldr_distance_map": plot_ldr_distance_map(report, out / "ldr_distance_map.png")}


__all__ = ["plot_ldr_vs_height", "plot_scores_vs_height", "plot_ldr_distance_map", "save_sweep_figures"]
