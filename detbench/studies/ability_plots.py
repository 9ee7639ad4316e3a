"""Figures of the LiDAR detection-ability study (PNG, matplotlib Agg, no display needed).

- `plot_ability_by_range`: number of LiDAR-detected vehicles and LDR per height and range (paper Fig. 6);
- `plot_ability_by_level`: the same per importance level within one range (paper Fig. 7);
- `plot_bev`: one instant seen from each height side by side, detected boxes red,
  undetected white, the ego yellow, points drawn (paper Fig. 5);
- `plot_ldr_vs_distance`: LDR against the box centre's x, one line per height.

All take the dict of `AbilityStudy.report()` (or an `ExampleFrames` for the bird's-eye
view) and write the file atomically. Units are in the axis labels.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from detbench.data.frame import key_heading, key_order
from detbench.data.regions import LEVEL_LABELS, LEVELS, RANGE_NAMES, RANGES
from detbench.data.layout import sim_calibration
from detbench.studies.ability import ExampleFrames
from detbench.utils.figures import LEGEND_SMALL, save_figure, series_colours

_PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22"]
_RANGE_COLOURS = {"small": "#f5d800", "moderate": "#2ca02c", "large": "#3b7dd8"}


def _colours(heights: list[str]) -> dict[str, str]:
    """One distinct colour per height: the palette for a few, a sequential colour map for many."""
    return dict(zip(heights, series_colours(len(heights), _PALETTE)))


def _ci(report: dict, h: str, r: str, lv: str):
    """The (lo, hi) 95 % scene-bootstrap interval of one LDR from the report, or None."""
    unc = report.get("extras", {}).get("uncertainty") or {}
    try:
        return unc["heights"][h][r][lv]["ci95"]
    except (KeyError, TypeError):
        return None


def _grouped(report: dict, groups: list[str], cell, ci=None) -> tuple[Figure, list, float]:
    """Two panels, (a) number detected with the total as a grey bar, (b) LDR; `cell(h, g)` -> dict;
    `ci(h, g)` -> (lo, hi) or None draws the LDR's 95 % interval as an error bar. Returns the figure, the
    axes and the top of the area the axes may fill (a fraction of the height; the legend is above it)."""
    heights = list(report["heights"])
    col = _colours(heights)
    n_entries = len(heights) + 1
    if n_entries <= LEGEND_SMALL:  # one row of entries, as drawn for the paper's three heights
        ncol, font, legend_in = n_entries, 9, 0.0
    else:  # many heights: rows of entries in a smaller font, the figure taller by their height
        ncol, font = 10, 7  # 10 columns leave the top right corner to the frame count
        legend_in = math.ceil(n_entries / ncol) * 0.16
    fig = Figure(figsize=(11, 4.4 + legend_in))
    area_top = 0.93 if not legend_in else 1.0 - (0.12 + legend_in) / (4.4 + legend_in)
    ax_n, ax_l = fig.subplots(1, 2)
    nb = len(heights) + 1
    width = 0.8 / nb
    drew_ci = False
    x = np.arange(len(groups))
    totals = [cell(heights[0], g)["total"] for g in groups] if heights else []
    ax_n.bar(x - 0.4 + width / 2, totals, width, color="#bbbbbb", edgecolor="#777777", label="Total")
    for i, h in enumerate(heights):
        det = [cell(h, g)["detected"] for g in groups]
        ax_n.bar(x - 0.4 + width * (i + 1.5), det, width, color=col[h], label=key_heading(h))
        ldrs = [cell(h, g)["ldr"] for g in groups]
        ldrs = [np.nan if v is None else v for v in ldrs]
        bars = ax_l.bar(x - 0.4 + width * (i + 1.5), ldrs, width, color=col[h], label=key_heading(h))
        intervals = [ci(h, g) if ci is not None else None for g in groups]
        for b, v, iv in zip(bars, ldrs, intervals):
            if v is None or math.isnan(v):
                continue
            top = v
            if iv is not None:
                xc = b.get_x() + b.get_width() / 2
                ax_l.errorbar([xc], [v], yerr=[[max(v - iv[0], 0.0)], [max(iv[1] - v, 0.0)]], fmt="none",
                              ecolor="#333333", elinewidth=0.8, capsize=2)
                top = max(v, iv[1])
                drew_ci = True
            ax_l.text(b.get_x() + b.get_width() / 2, top + 0.01, f"{v:.2f}", ha="center", va="bottom", fontsize=7)
    for ax in (ax_n, ax_l):
        ax.set_xticks(x)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    ax_n.set_ylabel("vehicles (count, summed over frames)")
    ax_l.set_ylabel("LDR = detected / total")
    ax_l.set_ylim(0, 1.12)
    if drew_ci:
        ax_l.set_xlabel("error bars: 95 % interval of the LDR, bootstrap over scenes", fontsize=8)
    handles, labels = ax_n.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=ncol, fontsize=font, frameon=False,
               bbox_to_anchor=(0.5, 1.0))
    return fig, [ax_n, ax_l], area_top


def world_label(report: dict) -> str:
    """Where an ability report's counts come from, for figure titles: "simulator calibration v2"
    (streamed), "simulator calibration v2, dataset on disk" (a simulated dataset read back), "data on
    disk", or "data source not recorded"; the words of `detbench.eval.report.data_label`."""
    src = report.get("extras", {}).get("source") or {}
    if src.get("kind") == "simulator":
        return f"simulator calibration {sim_calibration(src)}"
    if src.get("calibration"):
        return f"simulator calibration {src['calibration']}, dataset on disk"
    return "data on disk" if src else "data source not recorded"


def plot_ability_by_range(report: dict, path: str | os.PathLike, level: str = "all") -> Path:
    """Paper Fig. 6: detected vehicles (a) and LDR (b) per height in each range, at `level`."""
    groups = list(RANGE_NAMES)
    fig, (ax_n, ax_l), top = _grouped(report, groups, lambda h, r: report["heights"][h][r][level],
                                 lambda h, r: _ci(report, h, r, level))
    labels = [f"{r}\n0-{RANGES[r][1]:g} m, |y|<={RANGES[r][2]:g} m" for r in groups]
    for ax in (ax_n, ax_l):
        ax.set_xticklabels(labels, fontsize=8)
    what = LEVEL_LABELS[level] + " vehicles"
    ax_n.set_title(f"(a) LiDAR-detected vehicles by range ({what})", fontsize=10)
    ax_l.set_title(f"(b) LiDAR detection rate by range ({what})", fontsize=10)
    fig.text(0.99, 0.99, f"{report['num_frames']} frames; {world_label(report)}", fontsize=9, ha="right", va="top")
    fig.tight_layout(rect=(0, 0, 1, top))
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def plot_ability_by_level(report: dict, path: str | os.PathLike, range_name: str = "large") -> Path:
    """Paper Fig. 7: detected vehicles (a) and LDR (b) per height and importance level in one range."""
    groups = list(LEVELS)
    fig, (ax_n, ax_l), top = _grouped(report, groups, lambda h, lv: report["heights"][h][range_name][lv],
                                 lambda h, lv: _ci(report, h, range_name, lv))
    for ax in (ax_n, ax_l):
        ax.set_xticklabels([LEVEL_LABELS[g] for g in groups])
    ax_n.set_title(f"(a) LiDAR-detected vehicles by importance ({range_name} range)", fontsize=10)
    ax_l.set_title(f"(b) LiDAR detection rate by importance ({range_name} range)", fontsize=10)
    fig.text(0.99, 0.99, f"{report['num_frames']} frames; {world_label(report)}", fontsize=9, ha="right", va="top")
    fig.tight_layout(rect=(0, 0, 1, top))
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def plot_ldr_vs_distance(report: dict, path: str | os.PathLike) -> Path:
    """LDR against the box centre's distance along x (one line per height), with vehicle counts below."""
    dist = report["extras"]["ldr_vs_distance"]
    edges = np.asarray(dist["edges_m"], dtype=float)
    centres = 0.5 * (edges[:-1] + edges[1:])
    heights = list(dist["heights"])
    col = _colours(heights)
    fig = Figure(figsize=(8, 6))
    ax, ax_c = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.2]})
    for h in heights:
        v = np.array([np.nan if x is None else x for x in dist["heights"][h]["ldr"]], dtype=float)
        ax.plot(centres, v, "o-", color=col[h], label=key_heading(h), ms=4)
    ax.set_ylabel("LDR = detected / total")
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    if len(heights) <= LEGEND_SMALL:
        ax.legend(fontsize=9)
    else:  # many heights: columns of entries beside the axes, inside the figure after tight_layout
        ax.legend(fontsize=7, ncol=math.ceil(len(heights) / 18), loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  borderaxespad=0.0)
        fig.set_figwidth(8 + 1.1 * math.ceil(len(heights) / 18))
    ax.set_title(f"LiDAR detection rate against distance ({report['num_frames']} frames, {world_label(report)}; "
                 f"{dist['region']})",
                 fontsize=9)
    if heights:
        ax_c.bar(centres, dist["heights"][heights[0]]["total"], width=0.9 * (edges[1] - edges[0]), color="#bbbbbb")
    ax_c.set_ylabel("vehicles\n(count)")
    ax_c.set_xlabel(f"box centre x (m), {dist['bin_m']:g} m bins")
    ax_c.grid(axis="y", alpha=0.3)
    ax_c.set_xticks(edges)
    ax_c.tick_params(axis="x", labelsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=120, fmt="png", tight=False)


def _bev_corners(boxes: np.ndarray) -> np.ndarray:
    """(M, 4, 2) bird's-eye corners (x, y) in metres of (M, 7) boxes."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    hx, hy = b[:, 3] / 2, b[:, 4] / 2
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=np.float64)  # (4, 2)
    u = local[None, :, 0] * hx[:, None]
    v = local[None, :, 1] * hy[:, None]
    x = b[:, None, 0] + u * c[:, None] - v * s[:, None]
    y = b[:, None, 1] + u * s[:, None] + v * c[:, None]
    return np.stack([x, y], axis=-1)


def ego_box(ego: dict) -> np.ndarray:
    """(7,) ego box in the ground frame (metres, radians): `ego["box"]` when the data gives one, otherwise a
    car of `ego["length_m"]` x `ego["width_m"]` (default 4.8 x 1.9 m) whose front is at the LiDAR (x = 0),
    as in the simulator."""
    ego = ego if isinstance(ego, dict) else {}
    if "box" in ego and len(ego["box"]) == 7:
        return np.asarray(ego["box"], dtype=np.float64)
    length = float(ego.get("length_m", ego.get("length", 4.8)))
    width = float(ego.get("width_m", ego.get("width", 1.9)))
    height = float(ego.get("height_m", ego.get("height", 1.5)))
    return np.array([-length / 2, 0.0, height / 2, length, width, height, 0.0])


def plot_bev(example: ExampleFrames, path: str | os.PathLike, x_range=(-8.0, 152.0), y_half: float = 18.0,
             max_points: int = 120_000, seed: int = 0) -> Path:
    """Paper Fig. 5: the instant `example` at each height side by side (x forward = up, left = left).

    Boxes with at least one point inside (bottom raised 0.05 m) are red, the others white,
    the ego yellow; points above 0.15 m are cyan, road points dim grey; the small, moderate
    and large ranges are outlined. At most `max_points` points per panel are drawn (a
    seeded subsample) so the file stays small.
    """
    heights = sorted(example.frames, key=key_order)
    fig = Figure(figsize=(3.6 * len(heights) + 0.6, 13), facecolor="black")
    axes = np.atleast_1d(fig.subplots(1, len(heights), sharey=True))
    rng = np.random.default_rng(seed)
    for ax, h in zip(axes, heights):
        frame = example.frames[h]
        counts = np.asarray(example.counts[h])
        ax.set_facecolor("black")
        p = frame.points
        if len(p) > max_points:
            p = p[np.sort(rng.choice(len(p), max_points, replace=False))]
        keep = (p[:, 0] >= x_range[0]) & (p[:, 0] <= x_range[1]) & (np.abs(p[:, 1]) <= y_half)
        p = p[keep]
        road = p[:, 2] < 0.15
        ax.scatter(p[road, 1], p[road, 0], s=0.2, c="#5a5a5a", linewidths=0, rasterized=True)
        ax.scatter(p[~road, 1], p[~road, 0], s=1.5, c="#31d0e0", linewidths=0, rasterized=True)
        for r in RANGE_NAMES:
            x0, x1, ym = RANGES[r]
            ax.add_patch(Rectangle((-ym, x0), 2 * ym, x1 - x0, fill=False, ec=_RANGE_COLOURS[r], lw=0.8, ls="--"))
        corners = _bev_corners(frame.boxes)[:, :, ::-1]  # (y, x) for the plot
        det = counts >= 1
        if (~det).any():
            ax.add_collection(PolyCollection(corners[~det], facecolors="none", edgecolors="white", linewidths=0.9))
        if det.any():
            ax.add_collection(PolyCollection(corners[det], facecolors="none", edgecolors="#ff2a2a", linewidths=1.1))
        ego = _bev_corners(ego_box(frame.ego)[None])[:, :, ::-1]
        ax.add_collection(PolyCollection(ego, facecolors="#ffd700", edgecolors="#ffd700", linewidths=1.0))
        in_view = (frame.boxes[:, 0] >= x_range[0]) & (frame.boxes[:, 0] <= x_range[1]) \
            & (np.abs(frame.boxes[:, 1]) <= y_half)
        ax.set_title(f"{key_heading(h)}: {int((det & in_view).sum())} of {int(in_view.sum())} vehicles hit",
                     color="white", fontsize=10)
        ax.set_xlim(y_half, -y_half)  # +y (left) on the left
        ax.set_ylim(*x_range)
        ax.set_aspect("equal")
        ax.tick_params(colors="#bbbbbb", labelsize=8)
        for sp in ax.spines.values():
            sp.set_color("#666666")
        ax.set_xlabel("y (m, left +)", color="#bbbbbb", fontsize=9)
    axes[0].set_ylabel("x (m, forward)", color="#bbbbbb", fontsize=9)
    fig.suptitle(f"Frame {example.frame_id}\nred: LiDAR-detected (>= 1 point in the box, bottom +0.05 m)\n"
                 f"white: not hit; yellow: ego; dashed: small / moderate / large range",
                 color="white", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.965))
    return save_figure(fig, path, dpi=110, fmt="png", tight=False)


def save_ability_figures(report: dict, out_dir: str | os.PathLike, example: ExampleFrames | None = None
                         ) -> dict[str, Path]:
    """Write every figure of the study into `out_dir`; returns {name: path}."""
    out = Path(out_dir)
    paths = {
        "by_range": plot_ability_by_range(report, out / "ability_by_range.png"),
        "by_level": plot_ability_by_level(report, out / "ability_by_level.png"),
        "ldr_vs_distance": plot_ldr_vs_distance(report, out / "ldr_vs_distance.png"),
    }
    for r in ("small", "moderate"):
        paths[f"by_level_{r}"] = plot_ability_by_level(report, out / f"ability_by_level_{r}.png", range_name=r)
    if example is not None and example.frames:
        paths["bev"] = plot_bev(example, out / "bev_example.png")
    return paths


__all__ = ["plot_ability_by_range", "plot_ability_by_level", "plot_ldr_vs_distance", "plot_bev",
           "save_ability_figures", "ego_box"]
