"""The short summary that opens a study report: which height sees most, which detector finds most.

Two questions a reader acts on, each answered with its uncertainty:

- Which mounting height makes the LiDAR hit the most vehicles, per importance level and range?
  From the ability study (`detbench.studies.ability`): the best height's LDR and its paired
  difference to the runner-up height, with the 95 % interval of the scene bootstrap (the
  heights of one scene see the same traffic, so the difference is paired).
- Which detector finds the most LiDAR-detected vehicles at each height? From the evaluation
  reports (`detbench.eval.evaluate`, run with bootstrap > 0): the best model's recall and
  AP@R40 with their intervals, and its paired recall difference to the runner-up over the
  same resampled test scenes (both models are evaluated on the same frames).

Fractions are in [0, 1]; an interval whose two ends have the same sign is a difference the
sampled scenes support; one that spans 0 is not.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from detbench.data.frame import height_or_rig, key_label, key_order
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights

RANGE_WORDS = {"small": "small", "moderate": "moderate", "large": "large"}
LEVEL_WORDS = {"all": "All", "top3": "Top3", "top6": "Top6"}


def _f(v, digits: int = 3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _ci(ci, signed: bool = False) -> str:
    if not ci:
        return "(no interval)"
    fmt = "+.3f" if signed else ".3f"
    return f"[{ci[0]:{fmt}}, {ci[1]:{fmt}}]"


def _supported(ci) -> bool:
    return bool(ci) and (ci[0] > 0 or ci[1] < 0)


# --------------------------------------------------------------------------------------------
# heights
# --------------------------------------------------------------------------------------------

def _height_diff(unc: dict, hi: str, lo: str, r: str, lv: str):
    """(diff hi - lo, ci) from the ability study's paired differences, whichever way stored."""
    diffs = (unc or {}).get("differences") or {}
    if f"{hi}-{lo}" in diffs:
        cell = diffs[f"{hi}-{lo}"][r][lv]
        return cell.get("diff"), cell.get("ci95")
    if f"{lo}-{hi}" in diffs:
        cell = diffs[f"{lo}-{hi}"][r][lv]
        d, ci = cell.get("diff"), cell.get("ci95")
        return (None if d is None else -d), (None if not ci else [-ci[1], -ci[0]])
    return None, None


def height_summary(ability: dict) -> dict:
    """{range: {level: {"best", "ldr", "runner_up", "diff", "ci95", "supported"}}} (heights as keys)."""
    heights = list(ability["heights"])
    unc = (ability.get("extras") or {}).get("uncertainty") or {}
    out: dict = {}
    for r in RANGE_NAMES:
        out[r] = {}
        for lv in LEVELS:
            ldr = {h: ability["heights"][h][r][lv].get("ldr") for h in heights}
            ranked = sorted((h for h in heights if ldr[h] is not None), key=lambda h: -ldr[h])
            if not ranked:
                out[r][lv] = None
                continue
            cell = {"best": ranked[0], "ldr": ldr[ranked[0]], "runner_up": None, "diff": None, "ci95": None,
                    "supported": False, "tied": [h for h in ranked[1:] if abs(ldr[h] - ldr[ranked[0]]) < 1e-12]}
            if len(ranked) > 1:
                d, ci = _height_diff(unc, ranked[0], ranked[1], r, lv)
                cell.update(runner_up=ranked[1], diff=d if d is not None else ldr[ranked[0]] - ldr[ranked[1]],
                            ci95=ci, supported=_supported(ci))
            out[r][lv] = cell
    return out


def height_summary_lines(ability: dict) -> list[str]:
    s = height_summary(ability)
    lines = ["| Level | Range | Most vehicles hit at | LDR | Lead over the next height (paired, 95 % interval) |",
             "|---|---|---|---:|---|"]
    supported = total = 0
    bests = []
    for lv in LEVELS:
        for r in RANGE_NAMES:
            c = s[r][lv]
            if c is None:
                lines.append(f"| {LEVEL_WORDS[lv]} | {RANGE_WORDS[r]} | - | - | - |")
                continue
            if c["tied"]:
                names = " = ".join(key_label(h) for h in [c["best"], *c["tied"]])
                lines.append(f"| {LEVEL_WORDS[lv]} | {RANGE_WORDS[r]} | {names} (tied) | {_f(c['ldr'])} | 0 |")
                bests.append(None)
                continue
            bests.append(c["best"])
            if c["runner_up"] is None:
                lead = "-"
            else:
                total += 1
                supported += c["supported"]
                lead = (f"{c['diff']:+.3f} over {key_label(c['runner_up'])} {_ci(c['ci95'], True)}"
                        + ("" if c["supported"] or not c["ci95"] else " (not resolved)"))
            lines.append(f"| {LEVEL_WORDS[lv]} | {RANGE_WORDS[r]} | {key_label(c['best'])} | {_f(c['ldr'])} | {lead} |")
    words = []
    if bests and len(set(bests)) == 1 and bests[0] is not None:
        words.append(f"The LiDAR at {key_label(bests[0])} hits the most vehicles at every level and range.")
    elif bests:
        counts = {h: bests.count(h) for h in dict.fromkeys(bests)}
        words.append("The height that hits the most vehicles depends on the cell: "
                     + ", ".join((f"{key_label(h)} in {n}" if h is not None else f"a tie in {n}")
                                 + f" of {len(bests)}" for h, n in counts.items()) + ".")
    if total:
        words.append(f"Its lead over the next height is resolved (the 95 % interval excludes 0) in {supported} "
                     f"of {total} cells.")
    return [" ".join(words), "", *lines]


# --------------------------------------------------------------------------------------------
# detectors
# --------------------------------------------------------------------------------------------

def paired_recall_difference(rep_a: dict, rep_b: dict, r: str, lv: str, replicates: int = 2000,
                             seed: int = 0, confidence: float = 0.95) -> dict | None:
    """Recall(a) - recall(b) on the same test frames, with a paired scene-bootstrap interval.

    Needs both reports' "uncertainty" (evaluate(..., bootstrap=B)) over the same scenes; the
    same resampled scenes are applied to both. Returns {"diff", "ci95"} or None.
    """
    ua, ub = rep_a.get("uncertainty"), rep_b.get("uncertainty")
    if not ua or not ub or ua.get("clusters") != ub.get("clusters"):
        return None
    pa, pb = ua["per_cluster"][r][lv], ub["per_cluster"][r][lv]
    det = np.asarray(pa["lidar_detected"], dtype=np.float64)
    if not np.array_equal(det, np.asarray(pb["lidar_detected"], dtype=np.float64)) or det.sum() == 0:
        return None
    ta, tb = np.asarray(pa["tp"], dtype=np.float64), np.asarray(pb["tp"], dtype=np.float64)
    diff = float((ta.sum() - tb.sum()) / det.sum())
    n = len(det)
    ci = None
    if n >= 2 and replicates > 0:
        boot = bootstrap_ratios(scene_bootstrap_weights(n, replicates, seed), ta - tb, det)
        ci = percentile_interval(boot, confidence)
    return {"diff": round(diff, 6), "ci95": ci}


def detector_summary(reports: Sequence[dict], range_name: str = "large", level: str = "all") -> dict:
    """{height: {"ranking": [(model, recall, ap)], "best", "runner_up", "lead": {"diff", "ci95"}}}."""
    by_height: dict[float | str, list[dict]] = {}
    for rep in reports:
        by_height.setdefault(height_or_rig(rep["height"]), []).append(rep)
    out = {}
    for h in sorted(by_height, key=key_order):
        reps = by_height[h]
        scored = [(rep, rep["results"][range_name][level]) for rep in reps]
        scored = [(rep, c) for rep, c in scored if c.get("recall") is not None]
        scored.sort(key=lambda rc: (-rc[1]["recall"], -(rc[1]["ap_r40"] or 0.0)))
        cell = {"ranking": [], "best": None, "runner_up": None, "lead": None}
        for rep, c in scored:
            ci = ((rep.get("uncertainty") or {}).get("results") or {}).get(range_name, {}).get(level, {})
            cell["ranking"].append({"model": rep.get("model"), "recall": c["recall"], "ap_r40": c["ap_r40"],
                                    "recall_ci95": ci.get("recall_ci95"), "ap_r40_ci95": ci.get("ap_r40_ci95")})
        if scored:
            cell["best"] = scored[0][0].get("model")
        if len(scored) > 1:
            cell["runner_up"] = scored[1][0].get("model")
            cell["lead"] = paired_recall_difference(scored[0][0], scored[1][0], range_name, level)
        out[h] = cell
    return out


def detector_summary_lines(reports: Sequence[dict], range_name: str = "large", level: str = "all") -> list[str]:
    """`detector_summary_markdown` of the reports."""
    return detector_summary_markdown(detector_summary(reports, range_name, level))


def detector_summary_markdown(summary: Mapping) -> list[str]:
    """The table of `detector_summary` (heights as keys in metres or as their text, as study.json holds them)."""
    lines = ["| Height | Finds the most LiDAR-detected vehicles | Recall (95 % interval) | AP@R40 (95 % interval) "
             "| Lead in recall over the next model (paired) | Every model: recall / AP@R40 |",
             "|---|---|---|---|---|---|"]
    for h, c in summary.items():
        if not c["ranking"]:
            lines.append(f"| {key_label(h)} | - | - | - | - | - |")
            continue
        b = c["ranking"][0]
        lead = "-"
        if c["lead"] is not None:
            lead = (f"{c['lead']['diff']:+.3f} over {c['runner_up']} {_ci(c['lead']['ci95'], True)}"
                    + ("" if _supported(c["lead"]["ci95"]) or not c["lead"]["ci95"] else " (not resolved)"))
        elif c["runner_up"] is not None:
            lead = f"over {c['runner_up']} (no paired interval: evaluate with --bootstrap)"
        every = "; ".join(f"{e['model']} {_f(e['recall'], 2)} / {_f(e['ap_r40'], 2)}" for e in c["ranking"])
        lines.append(f"| {key_label(h)} | {b['model']} | {_f(b['recall'])} {_ci(b['recall_ci95'])} | "
                     f"{_f(b['ap_r40'])} {_ci(b['ap_r40_ci95'])} | {lead} | {every} |")
    return lines


# Below this AP@R40 (small range, all vehicles) at every height, a detector is reported as not
# having learned: well below what the detectors that learn reach at the cpu preset (docs/results.md).
NOT_LEARNED_AP = 0.1


def unlearned_models(reports: Sequence[dict], threshold: float = NOT_LEARNED_AP, range_name: str = "small",
                     level: str = "all") -> dict[str, list[float]]:
    """{model: its AP@R40 per height (in height order)} for every model whose AP@R40 in
    `range_name` / `level` stays below `threshold` at every height it was tested at: figures
    that say nothing about the model or the heights, which the summary must say."""
    aps: dict[str, list[tuple[float, float]]] = {}
    for rep in reports:
        ap = rep["results"][range_name][level].get("ap_r40")
        if ap is not None:  # no AP (no LiDAR-detected vehicle in the range) says nothing about learning
            aps.setdefault(str(rep.get("model")), []).append((height_or_rig(rep["height"]), float(ap)))
    return {m: [a for _, a in sorted(v, key=lambda ha: (key_order(ha[0]), ha[1]))]
            for m, v in sorted(aps.items()) if v and all(a < threshold for _, a in v)}


def unlearned_lines(reports: Sequence[dict], threshold: float = NOT_LEARNED_AP) -> list[str]:
    """A warning paragraph naming the models that have not learned (empty when every model has)."""
    return unlearned_markdown(unlearned_models(reports, threshold), threshold)


def unlearned_markdown(bad: Mapping[str, Sequence[float]], threshold: float = NOT_LEARNED_AP) -> list[str]:
    """The paragraph of `unlearned_lines` from `unlearned_models`'s result."""
    if not bad:
        return []
    parts = [f"{m} (AP@R40 small {min(v):.3f}-{max(v):.3f})" for m, v in bad.items()]
    return [f"**Not learned at this preset:** {', '.join(parts)}: below {threshold:g} at every height, so "
            "its recall and AP say nothing about the model or the heights; rank the others without it "
            "(a larger preset, or more epochs with `--set train.epochs=N`, trains it further).", ""]


__all__ = ["height_summary", "height_summary_lines", "paired_recall_difference", "detector_summary",
           "detector_summary_lines", "detector_summary_markdown", "NOT_LEARNED_AP", "unlearned_models",
           "unlearned_lines", "unlearned_markdown"]
