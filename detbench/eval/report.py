"""Evaluation reports as Markdown (laid out like the paper's Table VII), CSV and figures.

A *report* is the dict returned by `detbench.eval.evaluate` (optionally with "model",
"height" and "split" added by tools/eval.py). Counts are numbers of vehicles (TP and FP:
numbers of predictions); LDR, recall and AP@R40 are fractions in [0, 1]; height in metres.

Figures (PNG, matplotlib, drawn on a `matplotlib.figure.Figure` with the Agg canvas so no
interactive backend is touched) take a list of reports, each with "model" and "height":
- `plot_by_height`: numbers detected, recall and AP by model and height (paper Fig. 8);
- `plot_by_range`: recall (or AP) by height for each range (Fig. 9);
- `plot_by_level`: recall (or AP) by height for each importance level (Fig. 10).
Each figure's title names where the frames come from (`data_label`: the simulator calibration and
seed from a report's "data_source", or data on disk).
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from collections.abc import Sequence
from typing import Any

from detbench.data.frame import height_key, height_or_rig, is_rig_key, key_label, key_order
from detbench.data.regions import LEVEL_LABELS, LEVELS, RANGE_LABELS, RANGE_NAMES
from detbench.utils.figures import save_figure

METRIC_FIELDS: tuple[str, ...] = ("total", "lidar_detected", "ldr", "tp", "fp", "recall", "ap_r40")
METRIC_LABELS = {"recall": "Recall", "ap_r40": "AP@R40", "ldr": "LDR"}
MISSING = "n/a"


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

def _frac(v: float | None, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return MISSING
    return f"{v:.{digits}f}"


def _height_str(h: Any) -> str:
    if h is None:
        return "?"
    return key_label(h) if isinstance(h, str) and is_rig_key(h) else f"{height_key(h)} m"


def _x(comb: dict, h: Any) -> float:
    """Where a height (metres) or a rig (its place in the table) sits on a figure's x axis."""
    return comb["heights"].index(h) if _rigs(comb) else h


def _rigs(comb: dict) -> bool:
    return any(isinstance(h, str) for h in comb["heights"])


def _x_label(comb: dict) -> str:
    return "LiDAR rig" if _rigs(comb) else "LiDAR mounting height (m)"


def _check_results(results: Any, where: str) -> dict:
    if not isinstance(results, dict):
        raise ValueError(f"{where}: 'results' must be a dict {{range_name: {{level: metrics}}}}, got "
                         f"{type(results).__name__}")
    for r in RANGE_NAMES:
        if r not in results:
            raise ValueError(f"{where}: results lack range {r!r}; is this a detbench.eval report?")
        for lv in LEVELS:
            cell = results[r].get(lv)
            if not isinstance(cell, dict) or any(k not in cell for k in METRIC_FIELDS):
                raise ValueError(f"{where}: results[{r!r}][{lv!r}] must hold {', '.join(METRIC_FIELDS)}")
    return results


def check_report(report: Any, where: str = "report") -> dict:
    """Raise ValueError (naming `where`) unless `report` has the layout of `evaluate`'s output."""
    if not isinstance(report, dict):
        raise ValueError(f"{where}: a report must be a JSON object, got {type(report).__name__}")
    for key in ("iou_threshold", "score_threshold", "num_frames", "results"):
        if key not in report:
            raise ValueError(f"{where}: missing key {key!r}; is this a report written by tools/eval.py?")
    _check_results(report["results"], where)
    for name, extra in (report.get("extras") or {}).items():
        _check_results(extra.get("results"), f"{where} extras[{name!r}]")
    return report


def _variants(report: dict) -> list[tuple[str, str, float, dict]]:
    """(name, iou_kind, iou_threshold, results) of the main result and of every extra."""
    kind = report.get("iou_kind", "3d")
    out = [("main", kind, float(report["iou_threshold"]), report["results"])]
    for name, extra in (report.get("extras") or {}).items():
        out.append((name, extra["iou_kind"], float(extra["iou_threshold"]), extra["results"]))
    return out


def _header(report: dict) -> list[str]:
    bits = []
    if report.get("model"):
        bits.append(f"model {report['model']}")
    if report.get("height") is not None:
        bits.append(f"height {_height_str(report['height'])}")
    if report.get("split"):
        bits.append(f"split {report['split']}")
    n = report["num_frames"]
    bits.append(f"{n} frame{'' if n == 1 else 's'}")
    if report.get("train_preset"):
        bits.append(f"trained at the {report['train_preset']} preset")
    if isinstance(report.get("data_source"), dict):
        bits.append(data_label([report]))
    return bits


# --------------------------------------------------------------------------------------------
# one report
# --------------------------------------------------------------------------------------------

def _interval(ci) -> str:
    return f"[{ci[0]:.3f}, {ci[1]:.3f}]" if ci else MISSING


def _results_table(results: dict, uncertainty: dict | None = None) -> list[str]:
    """Rows range x level; with `uncertainty` (the report's bootstrap) two interval columns."""
    ci = (uncertainty or {}).get("results")
    head = "| Range | Level | Total | LiDAR detected | LDR | TP | Recall | FP | AP@R40 |"
    rule = "|---|---|---:|---:|---:|---:|---:|---:|---:|"
    if ci:
        head += " Recall 95 % | AP@R40 95 % |"
        rule += "---:|---:|"
    lines = [head, rule]
    for r in RANGE_NAMES:
        for lv in LEVELS:
            c = results[r][lv]
            row = (f"| {RANGE_LABELS[r]} | {LEVEL_LABELS[lv]} | {c['total']} | {c['lidar_detected']} | "
                   f"{_frac(c['ldr'])} | {c['tp']} | {_frac(c['recall'])} | {c['fp']} | {_frac(c['ap_r40'])} |")
            if ci:
                cell = ci.get(r, {}).get(lv, {})
                row += f" {_interval(cell.get('recall_ci95'))} | {_interval(cell.get('ap_r40_ci95'))} |"
            lines.append(row)
    return lines


def report_to_markdown(report: dict, title: str | None = None) -> str:
    """Markdown of one report: a Table VII-like table per IoU variant (main first).

    Rows are range x level; columns: total vehicles, LiDAR-detected number and LDR, TP number
    and recall, FP number, AP@R40.
    """
    check_report(report)
    out = [f"# {title or 'Detection results'}", ""]
    out.append(", ".join(_header(report)) + ".")
    out.append("")
    for w in report.get("warnings") or []:
        out.append(f"**Warning: {w}**")
        out.append("")
    out.append(f"Predictions with score < {report['score_threshold']:g} dropped. Counts are vehicles "
               f"(TP, FP: predictions); LDR = LiDAR detected / total, recall = TP / LiDAR detected "
               f"(eq. 2), AP@R40 (eq. 3); fractions in [0, 1], {MISSING} where nothing is evaluated.")
    for name, kind, thr, results in _variants(report):
        out.append("")
        label = f"{kind.upper()} IoU >= {thr:g}"
        out.append(f"## {label}" + ("" if name == "main" else " (extra)"))
        out.append("")
        unc = report.get("uncertainty") if name == "main" else None
        out.extend(_results_table(results, unc))
        if unc and unc.get("results"):
            out.append("")
            out.append(f"95 % intervals: {unc['method']}, {unc['num_clusters']} scenes, {unc['replicates']} "
                       f"replicates.")
    return "\n".join(out) + "\n"


def report_rows(report: dict) -> list[dict]:
    """Flat rows (one per variant x range x level) with model/height/split when present."""
    check_report(report)
    rows = []
    for name, kind, thr, results in _variants(report):
        for r in RANGE_NAMES:
            for lv in LEVELS:
                row = {
                    "model": report.get("model") or "",
                    "height_m": "" if report.get("height") is None else height_or_rig(report["height"]),
                    "split": report.get("split") or "",
                    "variant": name,
                    "iou_kind": kind,
                    "iou_threshold": thr,
                    "score_threshold": float(report["score_threshold"]),
                    "range": r,
                    "level": lv,
                }
                for k in METRIC_FIELDS:
                    v = results[r][lv][k]
                    row[k] = "" if v is None else v
                rows.append(row)
    return rows


def _rows_to_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    if rows:
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return buf.getvalue()


def report_to_csv(report: dict) -> str:
    """CSV text of `report_rows(report)`; empty cells where a value is null."""
    return _rows_to_csv(report_rows(report))


def summary_lines(report: dict) -> list[str]:
    """A few lines for the terminal: per range, All level: LiDAR detected, recall, AP."""
    check_report(report)
    kind = report.get("iou_kind", "3d")
    lines = [f"{', '.join(_header(report))}; {kind.upper()} IoU >= {report['iou_threshold']:g}, "
             f"score >= {report['score_threshold']:g}"]
    for r in RANGE_NAMES:
        c = report["results"][r]["all"]
        t3 = report["results"][r]["top3"]
        lines.append(
            f"  {r:<8} all: LiDAR detected {c['lidar_detected']}/{c['total']} (LDR {_frac(c['ldr'])}), "
            f"TP {c['tp']}, FP {c['fp']}, recall {_frac(c['recall'])}, AP@R40 {_frac(c['ap_r40'])}; "
            f"top3 recall {_frac(t3['recall'])}"
        )
    return lines


# --------------------------------------------------------------------------------------------
# several reports (models x heights)
# --------------------------------------------------------------------------------------------

def report_variant(report: dict) -> str | None:
    """What sets a report apart from a model tested at its own training height with its whole pipeline: "trained
    at H m" (a cross-height evaluation), "first stage alone" (a two-stage model's proposals), both joined by "; ",
    or None. Read from the report's "trained_height", "height" and "stage" (tools/eval.py --ckpt writes them)."""
    bits = []
    trained = report.get("trained_height")
    if isinstance(trained, str) or isinstance(report.get("height"), str):  # a rig on either side
        if trained is not None and report.get("height") is not None and trained != report["height"]:
            bits.append(f"trained at {key_label(trained)}")
    elif trained is not None and report.get("height") is not None and not math.isnan(float(trained)) \
            and abs(float(trained) - float(report["height"])) > 1e-6:
        bits.append(f"trained at {float(trained):g} m")
    if report.get("stage", "refined") != "refined":
        bits.append("first stage alone")
    return "; ".join(bits) or None


def label_variants(reports: Sequence[dict]) -> list[dict]:
    """Copies of `reports` in which each variant (`report_variant`) is a model of its own: "second [trained at
    0.5 m]", "ct3d [first stage alone]", so a combined table shows it as a separately labelled column."""
    out = []
    for rep in reports:
        variant = report_variant(rep)
        if variant is None:
            out.append(rep)
            continue
        labelled = {k: v for k, v in rep.items() if k not in ("trained_height", "stage")}
        labelled["model"] = f"{rep.get('model')} [{variant}]"
        labelled["variant_of"] = {"model": rep.get("model"), "trained_height": rep.get("trained_height"),
                                  "stage": rep.get("stage", "refined")}
        out.append(labelled)
    return out


def _entries(reports: Sequence[dict], sources: Sequence[str] | None = None) -> list[dict]:
    if not reports:
        raise ValueError("no reports to combine; give at least one report")
    if sources is not None and len(sources) != len(reports):
        raise ValueError(f"{len(sources)} source names for {len(reports)} reports")
    names = [str(sources[i]) if sources is not None else f"report {i}" for i in range(len(reports))]
    variants = [f"{where} ({v})" for where, rep in zip(names, reports)
                if isinstance(rep, dict) and (v := report_variant(rep))]
    if variants:
        raise ValueError(
            f"{len(variants)} of the {len(reports)} reports are not a model tested at its training height with its "
            f"whole pipeline, so they do not belong in the paper's Table VII: {'; '.join(variants)}. Leave them out "
            f"(e.g. combine runs/*/eval_h<H>_test/report.json of each run's own height), or give --with-variants "
            f"(tools/eval.py --combine) to show each as a separately labelled column")
    entries = []
    seen = {}
    first = None
    for i, rep in enumerate(reports):
        where = str(sources[i]) if sources is not None else f"report {i}"
        check_report(rep, where)
        if rep.get("height") is None:
            raise ValueError(f"{where}: no 'height'; reports to combine need the mounting height "
                             f"(tools/eval.py writes it)")
        if not rep.get("model"):
            raise ValueError(f"{where}: no 'model' name; set it (tools/eval.py --model NAME) before "
                             f"combining")
        key = (str(rep["model"]), height_or_rig(rep["height"]))
        if key in seen:
            seeds = (seen[key][1], rep.get("train_seed"))
            why = ""
            if None not in seeds and seeds[0] != seeds[1]:
                why = (f" (training seeds {seeds[0]} and {seeds[1]}: combine one seed's reports, the run folders of "
                       f"one seed; a study's study.md combines its seeds itself)")
            raise ValueError(f"{where}: model {key[0]!r} at {key_label(key[1])} is also in {seen[key][0]}; "
                             f"combine each model and height once{why}")
        seen[key] = (where, rep.get("train_seed"))
        settings = (rep.get("iou_kind", "3d"), float(rep["iou_threshold"]), float(rep["score_threshold"]))
        if first is None:
            first = (settings, where)
        elif settings != first[0]:
            raise ValueError(f"{where}: evaluated with (iou_kind, iou_threshold, score_threshold) = "
                             f"{settings}, but {first[1]} with {first[0]}; combine like with like")
        entries.append({"model": key[0], "height": key[1], "split": rep.get("split"),
                        "num_frames": rep["num_frames"], "results": rep["results"], "where": where})
    by_height: dict[float, dict] = {}
    for e in entries:
        ref = by_height.setdefault(e["height"], e)
        for r in RANGE_NAMES:
            for lv in LEVELS:
                a, b = ref["results"][r][lv], e["results"][r][lv]
                if (a["total"], a["lidar_detected"]) != (b["total"], b["lidar_detected"]):
                    raise ValueError(
                        f"{e['where']} and {ref['where']} ({key_label(e['height'])}) disagree on the "
                        f"ground truth of {r}/{lv} (total, LiDAR detected) = {(b['total'], b['lidar_detected'])} "
                        f"vs {(a['total'], a['lidar_detected'])}; they were evaluated on different data")
    return entries


def combine_reports(reports: Sequence[dict], sources: Sequence[str] | None = None) -> dict:
    """One JSON-able dict of several reports (each with "model" and "height").

    Checks that they share IoU kind, IoU and score thresholds and that reports at the same
    height agree on the ground truth. Returns {"iou_kind", "iou_threshold", "score_threshold",
    "heights": sorted metres, "models": in first-seen order, "data": where the frames come from
    (`data_label`), "entries": [{"model", "height", "split", "num_frames", "results"}]}. `sources`
    (e.g. file names) name the reports in errors.
    """
    entries = _entries(reports, sources)
    rep0 = reports[0]
    models = list(dict.fromkeys(e["model"] for e in entries))
    return {
        "iou_kind": rep0.get("iou_kind", "3d"),
        "iou_threshold": float(rep0["iou_threshold"]),
        "score_threshold": float(rep0["score_threshold"]),
        "heights": sorted({e["height"] for e in entries}, key=key_order),
        "models": models,
        "data": data_label(reports),
        "entries": [{k: e[k] for k in ("model", "height", "split", "num_frames", "results")} for e in entries],
    }


def combined_markdown(reports: Sequence[dict], levels: Sequence[str] = LEVELS,
                      title: str | None = None, sources: Sequence[str] | None = None) -> str:
    """Markdown table of several reports laid out like the paper's Table VII.

    Rows: range x level, each with three lines: Number (LiDAR detected, then TP per model),
    LDR / Recall, and AP@R40. Columns: Total, then for each height the LiDAR-detected column
    and one column per model.
    """
    comb = combine_reports(reports, sources)
    cell = {(e["model"], e["height"]): e["results"] for e in comb["entries"]}
    heights, models = comb["heights"], comb["models"]
    ref = {h: next(e["results"] for e in comb["entries"] if e["height"] == h) for h in heights}
    cols = []
    for h in heights:
        cols.append((h, None))
        cols.extend((h, m) for m in models if (m, h) in cell)
    head = ["Range", "Level", "Row", "Total"] + [
        f"{_height_str(h)} {'LiDAR detected' if m is None else m}" for h, m in cols]
    lines = [
        f"# {title or 'Detection results by model and height'}",
        "",
        f"{comb['iou_kind'].upper()} IoU >= {comb['iou_threshold']:g}, score >= {comb['score_threshold']:g}. "
        f"Number: LiDAR-detected vehicles, or TP of each model; LDR / Recall: fractions in [0, 1]; "
        f"AP@R40 per model; {MISSING} where nothing is evaluated. Frames: {comb['data']}.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * 3 + "---:|" * (1 + len(cols)),
    ]
    for r in RANGE_NAMES:
        for lv in levels:
            totals = [ref[h][r][lv]["total"] for h in heights]
            total = str(totals[0]) if len(set(totals)) == 1 else " / ".join(str(t) for t in totals)
            num, frac, ap = [], [], []
            for h, m in cols:
                if m is None:
                    c = ref[h][r][lv]
                    num.append(str(c["lidar_detected"]))
                    frac.append(_frac(c["ldr"], 2))
                    ap.append("")
                else:
                    c = cell[(m, h)][r][lv]
                    num.append(str(c["tp"]))
                    frac.append(_frac(c["recall"], 2))
                    ap.append(_frac(c["ap_r40"], 2))
            lines.append(f"| {RANGE_LABELS[r]} | {LEVEL_LABELS[lv]} | Number | {total} | " + " | ".join(num) + " |")
            lines.append("|  |  | LDR / Recall |  | " + " | ".join(frac) + " |")
            lines.append("|  |  | AP@R40 |  | " + " | ".join(ap) + " |")
    return "\n".join(lines) + "\n"


def combined_csv(reports: Sequence[dict], sources: Sequence[str] | None = None) -> str:
    """CSV of the main results of several reports (one row per model x height x range x level)."""
    _entries(reports, sources)
    rows = []
    for rep in reports:
        rows.extend(row for row in report_rows(rep) if row["variant"] == "main")
    return _rows_to_csv(rows)


# --------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------

def data_labels(reports: Sequence[dict]) -> list[str]:
    """Where the reports' frames come from, each distinct source once, in first-seen order:
    "simulator calibration v2, seed 0" (with ", preset P" for a simulator preset other than paper and
    ", --set overrides" when the simulation had some), "data on disk", or "data source not recorded"
    (reports written before the field)."""
    labels = []
    for rep in reports:
        src = rep.get("data_source")
        if not isinstance(src, dict):
            lab = "data source not recorded"
        elif src.get("kind") == "simulator":
            lab = f"simulator calibration {src.get('calibration', '?')}"
            if src.get("seed") is not None:
                lab += f", seed {src['seed']}"
            if src.get("preset") not in (None, "paper"):
                lab += f", preset {src['preset']}"
            if src.get("overrides"):
                lab += ", --set overrides"
        else:
            lab = "data on disk"
        if lab not in labels:
            labels.append(lab)
    return labels


def data_label(reports: Sequence[dict]) -> str:
    """`data_labels` for figure titles: distinct sources joined with " + "."""
    return " + ".join(data_labels(reports)) or "no reports"


def source_label(reports: Sequence[dict]) -> str:
    """What a figure of detector reports shows: the training presets of the checkpoints (reports that record
    `train_preset`), then `data_label`: "cpu preset; simulator calibration v2, seed 0"."""
    presets = list(dict.fromkeys(str(r["train_preset"]) for r in reports if r.get("train_preset")))
    words = f"{' + '.join(presets)} preset{'s' if len(presets) > 1 else ''}; " if presets else ""
    return words + data_label(reports)


def _grid(reports: Sequence[dict]):
    comb = combine_reports(reports)
    cell = {(e["model"], e["height"]): e["results"] for e in comb["entries"]}
    ref = {h: next(e["results"] for e in comb["entries"] if e["height"] == h) for h in comb["heights"]}
    return comb, cell, ref


def _series(comb, cell, model: str, metric: str, r: str, lv: str) -> tuple[list[float], list[float]]:
    xs, ys = [], []
    for h in comb["heights"]:
        res = cell.get((model, h))
        if res is None:
            continue
        v = res[r][lv][metric]
        xs.append(_x(comb, h))
        ys.append(math.nan if v is None else float(v))
    return xs, ys


def _line_axes(ax, comb, cell, metric: str, r: str, lv: str, title: str) -> None:
    for m in comb["models"]:
        xs, ys = _series(comb, cell, m, metric, r, lv)
        ax.plot(xs, ys, marker="o", label=m)
    ax.set_xticks([_x(comb, h) for h in comb["heights"]])
    ax.set_xticklabels([_height_str(h) for h in comb["heights"]])
    ax.set_xlabel(_x_label(comb))
    ax.set_ylabel(f"{METRIC_LABELS[metric]} (fraction)")
    ax.set_title(title)
    ax.set_ylim(-0.02, 1.05)
    ax.grid(True, alpha=0.3)


def _check_metric(metric: str) -> str:
    if metric not in ("recall", "ap_r40"):
        raise ValueError(f"metric must be 'recall' or 'ap_r40', got {metric!r}")
    return metric


def plot_by_height(reports: Sequence[dict], path: str | Path, range_name: str = "large",
                   level: str = "all") -> Path:
    """Paper Fig. 8: (a) LiDAR-detected vehicles and TP of each model per height (bars,
    numbers of vehicles), (b) recall and (c) AP@R40 (fractions) against height per model,
    for one range and level. Writes a PNG (or the format of `path`'s suffix); returns path."""
    from matplotlib.figure import Figure

    comb, cell, ref = _grid(reports)
    if range_name not in RANGE_NAMES or level not in LEVELS:
        raise ValueError(f"range_name must be one of {RANGE_NAMES} and level one of {LEVELS}")
    heights, models = comb["heights"], comb["models"]
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = fig.subplots(1, 3)
    width = 0.8 / (len(models) + 1)
    for k, name in enumerate([None, *models]):
        xs, ys = [], []
        for i, h in enumerate(heights):
            if name is None:
                xs.append(i)
                ys.append(ref[h][range_name][level]["lidar_detected"])
            elif (name, h) in cell:
                xs.append(i)
                ys.append(cell[(name, h)][range_name][level]["tp"])
        axes[0].bar([x - 0.4 + width * (k + 0.5) for x in xs], ys, width=width,
                    label="LiDAR detected" if name is None else name)
    axes[0].set_xticks(range(len(heights)))
    axes[0].set_xticklabels([_height_str(h) for h in heights])
    axes[0].set_xlabel(_x_label(comb))
    axes[0].set_ylabel("vehicles (count)")
    axes[0].set_title("(a) detected vehicles")
    top = max((p.get_height() for p in axes[0].patches), default=1.0)
    axes[0].set_ylim(0, max(top, 1.0) * 1.3)  # room for the legend above the bars
    axes[0].legend(fontsize=8, loc="upper left", ncol=2)
    _line_axes(axes[1], comb, cell, "recall", range_name, level, "(b) recall")
    _line_axes(axes[2], comb, cell, "ap_r40", range_name, level, "(c) AP@R40")
    axes[1].legend(fontsize=8)
    fig.suptitle(f"{RANGE_LABELS[range_name]} range, {LEVEL_LABELS[level]} vehicles, "
                 f"{comb['iou_kind'].upper()} IoU >= {comb['iou_threshold']:g} ({source_label(reports)})")
    return save_figure(fig, path)


def plot_by_range(reports: Sequence[dict], path: str | Path, level: str = "all",
                  metric: str = "recall") -> Path:
    """Paper Fig. 9: `metric` ("recall" or "ap_r40", fraction) against height per model, one
    panel per range (small, moderate, large) at `level`. Returns path."""
    from matplotlib.figure import Figure

    _check_metric(metric)
    comb, cell, _ = _grid(reports)
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = fig.subplots(1, len(RANGE_NAMES), sharey=True)
    for ax, r in zip(axes, RANGE_NAMES):
        _line_axes(ax, comb, cell, metric, r, level, f"{RANGE_LABELS[r]} range")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{METRIC_LABELS[metric]} by range, {LEVEL_LABELS[level]} vehicles ({source_label(reports)})")
    return save_figure(fig, path)


def plot_by_level(reports: Sequence[dict], path: str | Path, range_name: str = "large",
                  metric: str = "recall") -> Path:
    """Paper Fig. 10: `metric` ("recall" or "ap_r40", fraction) against height per model, one
    panel per level (Top3, Top6, All) in `range_name`. Returns path."""
    from matplotlib.figure import Figure

    _check_metric(metric)
    comb, cell, _ = _grid(reports)
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = fig.subplots(1, len(LEVELS), sharey=True)
    for ax, lv in zip(axes, ("top3", "top6", "all")):
        _line_axes(ax, comb, cell, metric, range_name, lv, f"{LEVEL_LABELS[lv]} vehicles")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{METRIC_LABELS[metric]} by importance level, {RANGE_LABELS[range_name]} range "
                 f"({source_label(reports)})")
    return save_figure(fig, path)


__all__ = [
    "check_report", "source_label", "report_to_markdown", "report_to_csv", "report_rows", "summary_lines",
    "combine_reports", "combined_markdown", "combined_csv", "label_variants", "report_variant",
    "plot_by_height", "plot_by_range", "plot_by_level", "data_label", "data_labels", "METRIC_FIELDS",
]
