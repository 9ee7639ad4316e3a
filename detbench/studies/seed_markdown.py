"""study.md's sections on training seeds, rendered from the statistics of detbench.studies.seeds.

The renderers take the JSON layouts that study.json holds (`seed_statistics`: "by_height",
"by_model", "pairs", "height_pairs", "table"; heights as keys in metres or as their text), so the
report renders from study.json alone; `seed_markdown`, `pairwise_markdown` and `detector_table` also
take a study's {(model, height): [eval report of each seed]} directly. Fractions to three decimals, or two where
the README's tables give two.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

from detbench.data.frame import key_label
from detbench.data.regions import RANGE_NAMES
from detbench.studies.seeds import METRICS, seed_statistics

METRIC_WORDS = {"recall": "Recall", "ap_r40": "AP@R40"}



def _f(v, digits: int = 3, signed: bool = False) -> str:
    if v is None:
        return "-"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def _ci(ci, signed: bool = False) -> str:
    if not ci:
        return "(no interval)"
    return f"[{_f(ci[0], signed=signed)}, {_f(ci[1], signed=signed)}]"


def _ci2(ci, signed: bool = False) -> str:
    """An interval to two decimals, as the README's tables give it."""
    if not ci:
        return "(no interval)"
    return f"[{_f(ci[0], 2, signed)}, {_f(ci[1], 2, signed)}]"


def _with_ci(cell: dict) -> str:
    """A cell's seed mean with its interval, to two decimals; "-" where nothing is evaluated."""
    return "-" if cell["mean"] is None else f"{_f(cell['mean'], 2)} {_ci2(cell['ci95'])}"


def _seeds_text(seeds: Sequence) -> str:
    return ", ".join(str(s) for s in seeds)


def _lead_sentence(prefix: str, key: str, metric: str, entry: dict) -> str:
    """One sentence on a ranking of models (key "model") or heights (key "height")."""
    r, lv = entry["range"], entry["level"]
    what = f"{METRIC_WORDS[metric]} ({r} range, {'All' if lv == 'all' else lv.capitalize()} vehicles)"

    def name(e: dict) -> str:
        return key_label(e[key]) if key == "height" else str(e[key])

    if not entry["ranking"]:
        return f"{prefix}, {what}: nothing is evaluated in that range."
    best = entry["ranking"][0]
    if entry["runner_up"] is None:
        return f"{prefix}, {what}: only {name(best)} has a figure, {_f(best['mean'])} {_ci(best['ci95'])}."
    lead = entry["lead"]
    runner = entry["ranking"][1]
    head = (f"{prefix}, {what}: {name(best)} {_f(best['mean'])} against {name(runner)} {_f(runner['mean'])}, "
            f"lead {_f(lead['diff'], signed=True)} {_ci(lead['ci95'], signed=True)}")
    terms = f"scene term {_ci(lead['scene_ci95'], signed=True)}"
    if lead["seed_half_width"] is not None:
        terms += f", seed term +-{_f(lead['seed_half_width'])}"
    else:
        terms += ", seed spread not measured (one seed each)"
    if lead["verdict"] == "ahead":
        return f"{head} ({terms}): **{name(best)} is ahead**."
    if lead["verdict"] == "not resolved":
        return f"{head} ({terms}): not resolved, the interval includes 0."
    return f"{head}: no interval (evaluate with --bootstrap), so none is called ahead."


def pairwise_markdown(leads: Mapping) -> list[str]:
    """study.md's table of `pairwise_leads`: per height, range and metric the ranking and the resolved pairs."""
    lines = ["Every pair of models at each height (All vehicles): the ranking by seed mean, then each lead whose "
             "95 % interval (test scenes and both models' seed spread) excludes 0; a pair not listed is not "
             "resolved. Leads are differences of fractions.", "",
             "| Height | Range | Metric | Ranking (seed mean) | Resolved leads [95 %] |", "|---|---|---|---|---|"]
    for h, by_range in leads.items():
        for r, by_metric in by_range.items():
            for metric, entry in by_metric.items():
                ranking = " > ".join(f"{e['model']} {_f(e['mean'], 2)}" for e in entry["ranking"]) or "-"
                resolved = "; ".join(f"{p['model']} over {p['over']} {_f(p['diff'], 2, signed=True)} "
                                     f"{_ci2(p['ci95'], signed=True)}" for p in entry["pairs"] if p["ahead"]) or "none"
                lines.append(f"| {key_label(h)} | {r} | {METRIC_WORDS[metric]} | {ranking} | {resolved} |")
    return lines


def _answer(p: Mapping) -> str:
    """A height pair's verdict in words."""
    if p["answer"] == "resolved":
        return f"resolved: {key_label(p['leader'])} leads"
    if p["answer"] == "bounded":
        return f"bounded: the two differ by less than {_f(p['margin'])}"
    return "no interval (evaluate with --bootstrap)"


def height_pairs_markdown(height_pairs: Mapping) -> list[str]:
    """study.md's height answer per detector (`seed_height_pairs`): per model a table of every pair of its heights,
    the difference of the seed means with its 95 % interval and the verdict. Nothing without such a model."""
    if not height_pairs:
        return []
    lines = ["**The height answer, per model**: every pair of a model's heights, the difference of the seed means "
             "(the higher first; All vehicles) with its 95 % interval (test scenes paired, both heights' seed spread). "
             "Resolved: the interval excludes 0, so that height leads. Bounded: the interval holds 0, so the two "
             "heights differ by less than its larger end, in either direction (not: they are equal).", ""]
    for m, by_metric in height_pairs.items():
        lines += [f"*{m}*", "", "| Metric | Pair | Difference [95 %] | Verdict |", "|---|---|---|---|"]
        for metric, entry in by_metric.items():
            what = f"{METRIC_WORDS[metric]} {entry['range']}"
            for p in entry["pairs"]:
                lines.append(f"| {what} | {key_label(p['height'])} - {key_label(p['over'])} | "
                             f"{_f(p['diff'], signed=True)} {_ci(p['ci95'], signed=True)} | {_answer(p)} |")
        lines.append("")
    return lines


def detector_table(groups: Mapping, train_minutes: Mapping | None = None, pool: bool = True) -> list[str]:
    """`detector_table_markdown` of {(model, height): [eval report of each seed]} (detbench.studies.seeds)
    with train_minutes: {(model, height): minutes per training} or None."""
    return detector_table_markdown(seed_statistics(groups, train_minutes, pool)["table"])


def detector_table_markdown(rows: Sequence[Mapping]) -> list[str]:
    """The one-table answer to "which detector": per model and height the seed mean of AP@R40 (small range)
    and of recall (small with its interval, moderate, large), All vehicles, with intervals over test scenes
    and seeds; the recall of the Top3 and Top6 vehicles of the large range (the importance levels); the
    paper's Table VII recall for the same cells and the mean training minutes. rows: `seed_statistics`'s
    "table"."""
    lines = ["| Detector | Height | Seeds | AP@R40 small [95 %] | Recall small [95 %] / moderate / large | "
             "Recall large, Top3 / Top6 | The paper's recall (Table VII) | Training min |",
             "|---|---|---:|---|---|---|---|---:|"]
    for row in rows:
        paper, minutes = row["paper_recall"], row["train_minutes"]
        lines.append(
            f"| {row['model']} | {key_label(row['height'])} | {row['num_seeds']} | {_with_ci(row['ap_r40_small'])} | "
            f"{_with_ci(row['recall_small'])} / {_f(row['recall_moderate'], 2)} / {_f(row['recall_large'], 2)} | "
            f"{_f(row['recall_large_top3'], 2)} / {_f(row['recall_large_top6'], 2)} | "
            f"{' / '.join(f'{v:.2f}' for v in paper) if paper else '-'} | "
            f"{'-' if minutes is None else f'{minutes:.1f}'} |")
    return lines


def seed_markdown(groups: Mapping, pool: bool = True) -> list[str]:
    """`seed_markdown_lines` of {(model, height): [eval report of each seed]} (detbench.studies.seeds)."""
    stats = seed_statistics(groups, pool=pool)
    return seed_markdown_lines(stats["by_height"], stats["by_model"], stats["height_pairs"])


def seed_markdown_lines(summary: Mapping, by_model: Mapping, height_pairs: Mapping | None = None) -> list[str]:
    """Markdown lines for study.md: per height a table of every model's seed mean per range (All
    vehicles) for recall and AP@R40 with the interval of scenes and seeds, the seed spread and the
    scene-only interval beside it, then the sentences of `seed_summary` (`summary`, keyed by height) and,
    for models tested at two or more heights, of `seed_height_summary` (`by_model`) and the height answer
    of `seed_height_pairs` (`height_pairs`, when given)."""
    seeds_used = sorted({s for h in summary.values() for c in h["models"].values() for s in c["seeds"]},
                        key=lambda s: (not isinstance(s, int), s if isinstance(s, int) else 0, str(s)))
    counts = sorted({c["num_seeds"] for h in summary.values() for c in h["models"].values()})
    seeds_text = ", ".join(str(s) for s in seeds_used)
    lines = [
        f"Training seeds: {seeds_text} ({' or '.join(str(n) for n in counts)} per model and height); "
        "every seed is tested on the same test split. Recall and AP@R40 are fractions in [0, 1], All vehicles; "
        "each figure is the mean over seeds with its 95 % interval over test scenes AND seeds; beside it the seed "
        "spread (sd: standard deviation between seeds; +-: its Student-t half-width on the mean) and the "
        "scene-only interval (the scene bootstrap of the seed mean), so one sees which term dominates.",
        "",
    ]
    if counts == [1]:
        lines += ["With one seed per model the seed spread is not measured: the intervals are the scene bootstrap "
                  "alone, as in a single-seed study.", ""]
    pooled = any(c.get("seed_spread_pooled_over_heights") for h in summary.values() for c in h["models"].values())
    if pooled:
        lines += ["The seed spread is pooled over each model's heights (its training randomness taken as one quantity "
                  "per range and metric, estimated from every height: sd is the pooled one, with its degrees of "
                  "freedom in the t factor; each height's own sd in brackets), because 2 or 3 seeds alone give a t "
                  "factor of 12.7 or 4.3 on an sd that rests on one or two differences.", ""]
    for h, cell in summary.items():
        lines += [f"**{key_label(h)}**", "",
                  "| Model | Seeds | Range | Recall (95 %, scenes + seeds) | Recall seed sd / +- | Recall scene-only "
                  "95 % | AP@R40 (95 %, scenes + seeds) | AP@R40 seed sd / +- | AP@R40 scene-only 95 % |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for m, comb in cell["models"].items():
            for r in RANGE_NAMES:
                row = [m, _seeds_text(comb["seeds"]), r]
                for metric in METRICS:
                    c = comb["results"][r]["all"][metric]
                    row.append(f"{_f(c['mean'])} {_ci(c['ci95'])}" if c["mean"] is not None else "-")
                    own = f" ({_f(c['sd_own'])})" if c.get("seed_pool") is not None else ""
                    row.append("-" if c["sd"] is None else f"{_f(c['sd'])}{own} / +-{_f(c['seed_half_width'])}")
                    row.append(_ci(c["scene_ci95"]) if c["mean"] is not None else "-")
                lines.append("| " + " | ".join(row) + " |")
        lines.append("")
        for metric in METRICS:
            lines.append(_lead_sentence(f"At {key_label(h)}", "model", metric, cell[metric]))
        lines.append("")
    if by_model:
        lines += ["**Heights, per model**", ""]
        for m, cell in by_model.items():
            lines += [_lead_sentence(f"For {m}", "height", metric, cell[metric]) for metric in METRICS]
        lines.append("")
    lines += height_pairs_markdown(height_pairs or {})
    lines.append("A model (or height) is called ahead only where the 95 % interval of its lead excludes 0: the "
                 "scene term (paired over the same test scenes: recall from each scene's counts, AP@R40 re-ranked "
                 "in each draw where the reports keep their AP ranking, else the two scene intervals in quadrature) "
                 "plus both sides' seed spread with a Student-t factor.")
    return lines


__all__ = ["METRIC_WORDS", "detector_table", "detector_table_markdown", "height_pairs_markdown", "pairwise_markdown",
           "seed_markdown", "seed_markdown_lines"]
