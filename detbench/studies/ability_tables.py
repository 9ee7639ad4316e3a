"""The Markdown of an ability report (ability.md): tables laid out like the paper's Tables IV-VI and the extras.

`ability_markdown(report)` takes the JSON-ready dict of `AbilityStudy.report()` (detbench.studies.ability)
and lays out one section per part of it; each section reads only the part of the report it shows and
returns its lines, so a report without an extra simply lacks that section.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from detbench.data.frame import key_heading
from detbench.data.regions import DETECTED_BOTTOM_LIFT, LEVELS, RANGE_NAMES, RANGES
from detbench.studies.ability import DECOMPOSITION_PARTS, paper_decomposition

PAPER_HEIGHTS = ("0.5", "1.0", "1.8")  # the heights of the paper's tables
PAPER_FRAMES = 8000  # the frames behind the paper's tables
LEVEL_TABLES = {"all": ("Table IV", "all vehicles"), "top3": ("Table V", "Top3 vehicles"),
                "top6": ("Table VI", "Top6 vehicles")}
PART_NAMES = {"second": "Second-in-lane", "beyond": "Beyond-Top6"}

Cells = Mapping[str, Mapping]  # {height: {"total", "detected", "ldr"}} of one table row


def _fmt_ldr(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"


def _ci(c) -> str:
    return "-" if c is None else f"[{c[0]:.3f}, {c[1]:.3f}]"


def _table_md(rows: list[tuple[str, Cells]], heights: list[str], row_title: str) -> list[str]:
    """rows: (label, {height: {"total","detected","ldr"}}); one Total column when all heights agree."""
    shared = all(len({c[h]["total"] for h in heights}) == 1 for _, c in rows)
    if shared:
        head = f"| {row_title} | Total | " + " | ".join(f"{key_heading(h)} Number / LDR" for h in heights) + " |"
    else:
        head = f"| {row_title} | " + " | ".join(f"{key_heading(h)} Number / Total / LDR" for h in heights) + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for label, cells in rows:
        if shared:
            vals = [f"{cells[h]['detected']} / {_fmt_ldr(cells[h]['ldr'])}" for h in heights]
            lines.append(f"| {label} | {cells[heights[0]]['total']} | " + " | ".join(vals) + " |")
        else:
            vals = [f"{cells[h]['detected']} / {cells[h]['total']} / {_fmt_ldr(cells[h]['ldr'])}" for h in heights]
            lines.append(f"| {label} | " + " | ".join(vals) + " |")
    return lines


def ranges_text(definitions: Mapping) -> str:
    """'small 0<=x<=50, |y|<=5; moderate ...' from a report's `definitions.ranges_m` (detbench.data.regions'
    RANGES for a report without it)."""
    given = definitions.get("ranges_m") or {r: {"x": [x0, x1], "abs_y_max": ym} for r, (x0, x1, ym) in RANGES.items()}
    return "; ".join(f"{r} {v['x'][0]:g}<=x<={v['x'][1]:g}, |y|<={v['abs_y_max']:g}" for r, v in given.items())


def header_lines(title: str, num_frames: int, heights: Sequence[str], extras: Mapping) -> list[str]:
    """The title, the data source (its simple values) and the definitions the tables use."""
    out = [f"# {title}", ""]
    src = extras.get("source")
    if src:
        def simple(v) -> bool:
            return not isinstance(v, dict) and not (isinstance(v, list) and any(isinstance(e, dict) for e in v))

        out += [f"Source: {', '.join(f'{k}={v}' for k, v in src.items() if simple(v))}", ""]
    definitions = extras.get("definitions", {})
    out += [f"{num_frames} frames; heights {', '.join(key_heading(h) for h in heights)}. A vehicle is "
            f"LiDAR-detected when at least one point lies inside its box with the bottom raised by "
            f"{definitions.get('bottom_lift_m', DETECTED_BOTTOM_LIFT)} m; LDR = detected / total. "
            f"Number = detected vehicles summed over frames. Ranges by box centre (metres): "
            f"{ranges_text(definitions)}.", ""]
    return out


def level_tables(table: Mapping, heights: list[str]) -> list[str]:
    """Tables IV-VI: one table per importance level, rows the ranges."""
    out = []
    for lv in LEVELS:
        tab, what = LEVEL_TABLES[lv]
        out += [f"## LiDAR detection results of {what} (as the paper's {tab})", ""]
        rows = [(r.capitalize(), {h: table[h][r][lv] for h in heights}) for r in RANGE_NAMES]
        out += _table_md(rows, heights, "Range") + [""]
    return out


def importance_tables(table: Mapping, heights: list[str]) -> list[str]:
    """One table per range, rows the importance levels."""
    out = ["## By importance level", ""]
    for r in RANGE_NAMES:
        out += [f"{r.capitalize()} range:", ""]
        rows = [(lv if lv == "all" else lv.capitalize(), {h: table[h][r][lv] for h in heights}) for lv in LEVELS]
        out += _table_md(rows, heights, "Level") + [""]
    return out


def min_points_tables(min_points: Mapping, heights: list[str]) -> list[str]:
    """All vehicles per range for each minimum number of points above 1."""
    out = []
    for t, tab in min_points.items():
        if t == "1":
            continue
        out += [f"## All vehicles with at least {t} points inside (extra)", ""]
        rows = [(r.capitalize(), {h: tab[h][r]["all"] for h in heights}) for r in RANGE_NAMES]
        out += _table_md(rows, heights, "Range") + [""]
    return out


def distance_table(dist: Mapping, heights: list[str]) -> list[str]:
    """LDR per x bin (`extras.ldr_vs_distance`)."""
    edges = dist["edges_m"]
    out = [f"## LDR against distance (extra; {dist['region']})", "",
           "| x (m) | " + " | ".join(f"{key_heading(h)} Number / Total / LDR" for h in heights) + " |",
           "|" + "---|" * (len(heights) + 1)]
    for b in range(len(edges) - 1):
        vals = [f"{dist['heights'][h]['detected'][b]} / {dist['heights'][h]['total'][b]} / "
                f"{_fmt_ldr(dist['heights'][h]['ldr'][b])}" for h in heights]
        out.append(f"| {edges[b]:g}-{edges[b + 1]:g} | " + " | ".join(vals) + " |")
    return out + [""]


def per_frame_table(vehicles_per_frame: Mapping, mean_points: Mapping, heights: list[str]) -> list[str]:
    """Vehicles per frame per range and the mean points on a detected vehicle per height."""
    out = ["## Vehicles per frame and points per detected vehicle (extra)", "",
           "| Range | Vehicles per frame | " + " | ".join(f"{key_heading(h)} mean points per detected vehicle"
                                                        for h in heights) + " |",
           "|" + "---|" * (len(heights) + 2)]
    for r in RANGE_NAMES:
        pts = [("-" if mean_points.get(h, {}).get(r) is None or math.isnan(mean_points[h][r])
                else f"{mean_points[h][r]:.0f}") for h in heights]
        out.append(f"| {r.capitalize()} | {vehicles_per_frame[r]:.2f} | " + " | ".join(pts) + " |")
    return out + [""]


def uncertainty_table(unc: Mapping, table: Mapping, heights: list[str]) -> list[str]:
    """The bootstrap intervals and scene std of every LDR (all vehicles) and the paired height differences."""
    pct = f"{100 * unc['confidence']:g} %"
    what = "scenes" if unc["clusters"] == "scene" else "clusters (frames without a scene id count alone)"
    out = [f"## Sampling uncertainty (all vehicles; {pct} intervals, bootstrap over {unc['num_clusters']} {what})",
           "",
           "Frames of one scene are correlated, so whole scenes are resampled. One scene's LDR scatters by "
           "the scene std; a study of n scenes is uncertain by about scene std / sqrt(n). Differences "
           "pair the heights on the same traffic.", "",
           "| Range | " + " | ".join(f"{key_heading(h)} LDR [{pct}] / scene std" for h in heights)
           + "".join(f" | {k} m difference [{pct}]" for k in unc["differences"]) + " |",
           "|" + "---|" * (1 + len(heights) + len(unc["differences"]))]
    for r in RANGE_NAMES:
        vals = []
        for h in heights:
            u = unc["heights"][h][r]["all"]
            std = "-" if u["scene_std"] is None else f"{u['scene_std']:.3f}"
            vals.append(f"{_fmt_ldr(table[h][r]['all']['ldr'])} {_ci(u['ci95'])} / {std}")
        for d in unc["differences"].values():
            dd = d[r]["all"]
            vals.append("-" if dd["diff"] is None else f"{dd['diff']:+.3f} {_ci(dd['ci95'])}")
        out.append(f"| {r.capitalize()} | " + " | ".join(vals) + " |")
    return out + [""]


def decomposition_table(dec: Mapping, heights: list[str], num_frames: int) -> list[str]:
    """Second-in-lane and beyond-Top6 per range, with the paper's own when the report has its three heights."""
    paper_dec = paper_decomposition() if set(heights) >= set(PAPER_HEIGHTS) else None
    out = ["## Per-lane decomposition (extra; from the Top3 / Top6 / All counts)", "",
           "Second-in-lane = Top6 minus Top3: the second-nearest vehicle of each of the ego, left and right "
           "lanes; beyond-Top6 = All minus Top6: every other vehicle of the range."
           + (" Paper: the same differences of its Tables IV-VI." if paper_dec else ""), "",
           "| Part | Range | Total per frame" + (" (paper)" if paper_dec else "") + " | "
           + " | ".join(f"{key_heading(h)} LDR" + (" (paper)" if paper_dec and h in PAPER_HEIGHTS else "")
                        for h in heights) + " |",
           "|" + "---|" * (3 + len(heights))]
    n_frames = max(int(num_frames), 1)
    for part in DECOMPOSITION_PARTS:
        for r in RANGE_NAMES:
            tot = dec[part][heights[0]][r]["total"] / n_frames
            tot_txt = f"{tot:.2f}" + (f" ({paper_dec[part]['0.5'][r]['total'] / PAPER_FRAMES:.2f})"
                                      if paper_dec else "")
            vals = []
            for h in heights:
                v = _fmt_ldr(dec[part][h][r]["ldr"])
                if paper_dec and h in paper_dec[part]:
                    v += f" ({paper_dec[part][h][r]['ldr']:.2f})"
                vals.append(v)
            out.append(f"| {PART_NAMES[part]} | {r.capitalize()} | {tot_txt} | " + " | ".join(vals) + " |")
    return out + [""]


def paper_table(paper: Mapping, table: Mapping, vehicles_per_frame: Mapping) -> list[str]:
    """The paper's Table IV beside this report's all-vehicle LDRs at the paper's three heights."""
    out = ["## Against the paper's Table IV (8000 CARLA frames)", "",
           "| Range | Vehicles per frame (paper) | Vehicles per frame (here) | "
           + " | ".join(f"{h} m LDR paper / here" for h in PAPER_HEIGHTS) + " |",
           "|" + "---|" * 6]
    for r in RANGE_NAMES:
        here = [f"{paper[r]['heights'][h]['ldr']:.2f} / {_fmt_ldr(table[h][r]['all']['ldr'])}" for h in PAPER_HEIGHTS]
        out.append(f"| {r.capitalize()} | {paper[r]['total'] / PAPER_FRAMES:.2f} | "
                   f"{vehicles_per_frame.get(r, float('nan')):.2f} | " + " | ".join(here) + " |")
    return out + [""]


def ability_markdown(report: dict, title: str = "LiDAR detection ability") -> str:
    """Markdown tables laid out like the paper's Tables IV-VI (rows ranges, per height "Number / LDR").

    Also: a table by importance level per range, the min-points extras, LDR against distance, vehicles per
    frame, the sampling uncertainty, the per-lane decomposition and, when the run has the paper's three
    heights, the paper's Table IV beside ours; each only when the report holds it.
    """
    table = report["heights"]
    heights = list(table)
    ex = report.get("extras", {})
    out = header_lines(title, report["num_frames"], heights, ex)
    if not heights:
        return "\n".join(out + ["No frames were analysed.", ""])
    out += level_tables(table, heights) + importance_tables(table, heights)
    out += min_points_tables(ex.get("min_points", {}), heights)
    if ex.get("ldr_vs_distance"):
        out += distance_table(ex["ldr_vs_distance"], heights)
    vpf = ex.get("vehicles_per_frame")
    if vpf:
        out += per_frame_table(vpf, ex.get("mean_points_per_detected", {}), heights)
    unc = ex.get("uncertainty")
    if unc and unc.get("num_clusters", 0) >= 2 and unc.get("replicates", 0) > 0:
        out += uncertainty_table(unc, table, heights)
    if ex.get("decomposition"):
        out += decomposition_table(ex["decomposition"], heights, report.get("num_frames", 0))
    if ex.get("paper_table_iv") and set(heights) >= set(PAPER_HEIGHTS):
        out += paper_table(ex["paper_table_iv"], table, vpf)
    return "\n".join(out)


__all__ = ["ability_markdown", "ranges_text"]
