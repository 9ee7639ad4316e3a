"""Does a split represent the world? A split's Table IV (all vehicles) held against a reference study's.

A detector is scored on the test split, so the test split should hold the traffic that the
ability study describes: as many vehicles per frame in each range, seen by the LiDAR as often.
`compare_splits(split_report, reference_report)` takes two AbilityStudy reports (the split's,
counted on the dataset's frames, and the reference: the study's ability report, or a dataset's
train split) and returns, per height and range (all vehicles), the split's vehicles per frame and
LDR, the reference's value with its 95 % scene-bootstrap interval, and two verdicts:

- `inside`: the split's value lies within the reference's interval (what a reader of the tables
  expects);
- `resolved`: the difference has a 95 % interval that excludes zero, with both sides' sampling
  noise (normal approximation from the two percentile intervals; a split whose interval is
  missing counts the reference's alone).

A split drawn from the same world falls outside the reference's interval in about 5 % of the
cells by chance (more when the split is small), so `outside` names the cells and the report
says how many a faithful split would show; `resolved` is the stronger sign of a split that
holds other traffic.
"""
from __future__ import annotations

import math

from detbench.data.frame import key_heading, key_order
from detbench.data.regions import RANGE_NAMES

Z95 = 1.959963984540054  # two-sided 95 % normal quantile
METRICS = ("vehicles_per_frame", "ldr")
METRIC_LABELS = {"vehicles_per_frame": "vehicles per frame", "ldr": "LDR"}


def split_figures(report: dict) -> dict:
    """{height: {range: {"vehicles_per_frame": (value, ci95 | None), "ldr": (value, ci95 | None)}}} of the
    all-vehicles cells of an AbilityStudy report (ci95 from its scene bootstrap, None without one)."""
    unc = ((report.get("extras") or {}).get("uncertainty") or {}).get("heights") or {}
    frames = (report.get("extras") or {}).get("frames_per_height") or {}
    out = {}
    for hk, table in report["heights"].items():
        n = frames.get(hk) or report.get("num_frames") or 0
        out[hk] = {}
        for r in RANGE_NAMES:
            cell = table[r]["all"]
            u = ((unc.get(hk) or {}).get(r) or {}).get("all") or {}
            out[hk][r] = {"vehicles_per_frame": (cell["total"] / n if n else None, u.get("vehicles_per_frame_ci95")),
                          "ldr": (cell["ldr"], u.get("ci95"))}
    return out


def _se(ci) -> float | None:
    return None if not ci or ci[0] is None or ci[1] is None else (ci[1] - ci[0]) / (2 * Z95)


def compare_splits(split_report: dict, reference_report: dict) -> dict:
    """The split's all-vehicles cells against the reference's (see the module docstring). Heights the two
    reports do not share are left out and listed under "heights_missing"."""
    split, ref = split_figures(split_report), split_figures(reference_report)
    cells, outside, resolved = [], [], []
    for hk in sorted(set(split) & set(ref), key=key_order):
        for r in RANGE_NAMES:
            for m in METRICS:
                value, own_ci = split[hk][r][m]
                ref_value, ref_ci = ref[hk][r][m]
                row = {"height": hk, "range": r, "metric": m, "value": value, "ci95": own_ci,
                       "reference": ref_value, "reference_ci95": ref_ci, "inside": None, "diff": None,
                       "diff_ci95": None, "resolved": None}
                if value is not None and ref_value is not None and ref_ci and ref_ci[0] is not None:
                    row["inside"] = bool(ref_ci[0] <= value <= ref_ci[1])
                    row["diff"] = value - ref_value
                    se = math.hypot(_se(own_ci) or 0.0, _se(ref_ci) or 0.0)
                    row["diff_ci95"] = [row["diff"] - Z95 * se, row["diff"] + Z95 * se]
                    row["resolved"] = bool(se > 0 and abs(row["diff"]) > Z95 * se)
                    if not row["inside"]:
                        outside.append(row)
                    if row["resolved"]:
                        resolved.append(row)
                cells.append(row)
    judged = sum(1 for c in cells if c["inside"] is not None)
    return {"cells": cells, "judged": judged, "outside": len(outside), "resolved": len(resolved),
            "expected_outside_by_chance": round(0.05 * judged, 1),
            "heights_missing": sorted((set(split) ^ set(ref)), key=key_order)}


def _fmt(v, ci=None, digits=3) -> str:
    if v is None:
        return "-"
    text = f"{v:.{digits}f}"
    if ci and ci[0] is not None:
        text += f" [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"
    return text


def split_check_markdown(result: dict, split_name: str, reference_name: str) -> list[str]:
    """Markdown lines: one table per metric (rows: range; columns: height, split vs reference), then the
    cells outside the reference's interval and those whose difference is resolved."""
    lines = []
    heights = sorted({c["height"] for c in result["cells"]}, key=key_order)
    for m in METRICS:
        lines += [f"**{METRIC_LABELS[m]}**, all vehicles: {split_name} [95 % interval] | {reference_name} "
                  f"[95 % interval]", "",
                  "| range | " + " | ".join(f"{key_heading(h)}: {split_name} | {key_heading(h)}: {reference_name}"
                                         for h in heights) + " |",
                  "|---|" + "---|---|" * len(heights)]
        for r in RANGE_NAMES:
            row = []
            for h in heights:
                c = next(c for c in result["cells"] if c["height"] == h and c["range"] == r and c["metric"] == m)
                mark = "" if c["inside"] in (True, None) else " (outside)"
                row += [_fmt(c["value"], c["ci95"]) + mark, _fmt(c["reference"], c["reference_ci95"])]
            lines.append(f"| {r} | " + " | ".join(row) + " |")
        lines.append("")
    lines.append(f"{result['outside']} of {result['judged']} cells lie outside the {reference_name}'s 95 % interval "
                 f"(a split drawn from the same world shows about {result['expected_outside_by_chance']} by chance, "
                 f"more when it is small); {result['resolved']} differ by more than both sides' sampling noise "
                 f"(95 % interval of the difference excludes 0).")
    for c in result["cells"]:
        if c["resolved"]:
            lines.append(f"- {key_heading(c['height'])}, {c['range']} range, {METRIC_LABELS[c['metric']]}: "
                         f"{split_name} "
                         f"{_fmt(c['value'])}, {reference_name} {_fmt(c['reference'])}, difference "
                         f"{_fmt(c['diff'], c['diff_ci95'])}")
    return lines


def split_check_warnings(result: dict, split_name: str, reference_name: str) -> list[str]:
    """One warning line per cell whose difference from the reference is resolved."""
    return [f"warning: the {split_name}'s {METRIC_LABELS[c['metric']]} at {key_heading(c['height'])}, "
            f"{c['range']} range, "
            f"is {_fmt(c['value'])} against the {reference_name}'s {_fmt(c['reference'], c['reference_ci95'])}: "
            f"the split holds other traffic than the {reference_name} describes"
            for c in result["cells"] if c["resolved"]]


__all__ = ["METRICS", "compare_splits", "split_check_markdown", "split_check_warnings", "split_figures"]
