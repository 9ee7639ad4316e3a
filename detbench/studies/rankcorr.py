"""Does a training-free placement score rank the heights as trained detectors do? Rank correlations.

Plain numpy (scipy is not a dependency):
- `rankdata`: average ranks (ties share the mean of their ranks);
- `spearman`: Spearman's rho, the Pearson correlation of the average ranks;
- `kendall_tau_b`: Kendall's tau-b, (concordant - discordant) / sqrt((n0 - tx) (n0 - ty)) with n0
  the number of pairs and tx, ty the pairs tied in x and in y;
- `permutation_pvalue`: two-sided p of "no association": the share of the n! orderings (all of
  them for n <= 8, else a seeded sample) whose |statistic| is at least the observed one;
- `bootstrap_interval`: percentile interval from resampling the (height, score, figure) pairs
  with replacement; replicates where x or y is constant (the statistic is undefined) are dropped
  and their share reported.

With the six heights a study can afford to train, these are coarse: the smallest two-sided
permutation p of rho is 2 / 720 = 0.0028 (a perfect order), rho must reach 0.886 for p < 0.05,
and the pairs bootstrap of six points gives wide intervals. `rank_agreement` therefore also
says which pairs of heights the score puts in the wrong order and whether it picks the best
height, so a failure is named, not only measured.

`load_detector_reports` reads tools/eval.py report.json files (model, height, recall and
AP@R40 per range and level); `correlate_sweep` correlates every score of a height sweep
(detbench.studies.sweep) with every detector figure; `correlation_markdown` lays it out.
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from detbench.data.frame import height_key
from detbench.data.regions import LEVELS, RANGE_NAMES

METRICS: tuple[str, ...] = ("recall", "ap_r40")
EXACT_MAX_N = 8  # all n! orderings up to this n (40320), a seeded sample beyond
DEFAULT_REPLICATES = 2000


# ---------------------------------------------------------------------------- statistics
def rankdata(x: Sequence[float]) -> np.ndarray:
    """Average ranks, 1-based: rankdata([10, 20, 20, 5]) = [2, 3.5, 3.5, 1]."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(x.size, np.float64)
    ranks[order] = np.arange(1, x.size + 1, dtype=np.float64)
    xs = x[order]
    start = 0
    for i in range(1, x.size + 1):
        if i == x.size or xs[i] != xs[start]:
            if i - start > 1:
                ranks[order[start:i]] = 0.5 * (start + 1 + i)
            start = i
    return ranks


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else float("nan")


def _check_pair(x, y) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if x.size != y.size:
        raise ValueError(f"x and y must have the same length, got {x.size} and {y.size}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("x and y must be finite (drop the missing heights first)")
    return x, y


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rho (ties: average ranks); NaN when x or y is constant or n < 2."""
    x, y = _check_pair(x, y)
    if x.size < 2:
        return float("nan")
    return _pearson(rankdata(x), rankdata(y))


def _signs(v: np.ndarray) -> np.ndarray:
    return np.sign(v[:, None] - v[None, :])


def kendall_tau_b(x: Sequence[float], y: Sequence[float]) -> float:
    """Kendall's tau-b; NaN when every pair is tied in x or in y, or n < 2."""
    x, y = _check_pair(x, y)
    n = x.size
    if n < 2:
        return float("nan")
    iu = np.triu_indices(n, 1)
    sx, sy = _signs(x)[iu], _signs(y)[iu]
    n0 = sx.size
    den = math.sqrt(float(n0 - (sx == 0).sum()) * float(n0 - (sy == 0).sum()))
    return float((sx * sy).sum()) / den if den > 0 else float("nan")


STATISTICS: dict[str, Callable[[Sequence[float], Sequence[float]], float]] = {
    "spearman": spearman, "kendall": kendall_tau_b}


def _permutations(n: int, limit: int, seed: int) -> np.ndarray:
    if n <= EXACT_MAX_N:
        return np.array(list(itertools.permutations(range(n))), dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.argsort(rng.random((limit, n)), axis=1)


def permutation_pvalue(x: Sequence[float], y: Sequence[float], statistic: str = "spearman",
                       permutations: int = 20000, seed: int = 0) -> float:
    """Two-sided p of no association: share of orderings of y with |statistic| >= the observed one.

    Exact (all n! orderings) for n <= 8; otherwise `permutations` seeded random orderings (the
    observed ordering counted as one of them). NaN when the statistic is undefined."""
    x, y = _check_pair(x, y)
    obs = STATISTICS[statistic](x, y)
    if math.isnan(obs):
        return float("nan")
    perms = _permutations(x.size, permutations, seed)
    if statistic == "spearman":
        rx, ry = rankdata(x), rankdata(y)
        rx = rx - rx.mean()
        ry = ry - ry.mean()
        den = math.sqrt(float((rx * rx).sum()) * float((ry * ry).sum()))
        stats = (ry[perms] @ rx) / den
    else:
        n = x.size
        iu = np.triu_indices(n, 1)
        sx = _signs(x)[iu]
        sy_full = _signs(y)
        n0 = sx.size
        den = math.sqrt(float(n0 - (sx == 0).sum()) * float(n0 - (sy_full[iu] == 0).sum()))
        stats = (sy_full[perms[:, iu[0]], perms[:, iu[1]]] @ sx) / den
    hits = int((np.abs(stats) >= abs(obs) - 1e-12).sum())
    if x.size > EXACT_MAX_N:
        return (hits + 1) / (len(perms) + 1)
    return hits / len(perms)


def bootstrap_interval(x: Sequence[float], y: Sequence[float], statistic: str = "spearman",
                       replicates: int = DEFAULT_REPLICATES, seed: int = 0, confidence: float = 0.95) -> dict:
    """Percentile interval of the statistic from resampling the pairs: {"ci95": [lo, hi] or None,
    "undefined_share": share of replicates where x or y came out constant (dropped)}."""
    x, y = _check_pair(x, y)
    n = x.size
    if n < 3 or replicates < 1:
        return {"ci95": None, "undefined_share": None}
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(int(replicates), n))
    f = STATISTICS[statistic]
    vals = np.array([f(x[i], y[i]) for i in idx])
    good = vals[np.isfinite(vals)]
    share = round(1.0 - good.size / vals.size, 4)
    if good.size < max(2, vals.size // 2):
        return {"ci95": None, "undefined_share": share}
    lo, hi = np.percentile(good, (100 * (1 - confidence) / 2, 100 * (1 + confidence) / 2))
    return {"ci95": [round(float(lo), 4), round(float(hi), 4)], "undefined_share": share}


def rank_agreement(heights: Sequence[str], score: Sequence[float], figure: Sequence[float],
                   replicates: int = DEFAULT_REPLICATES, seed: int = 0, confidence: float = 0.95) -> dict:
    """How well `score` orders the heights as `figure` does (both (n,), larger = better).

    Returns {"n", "spearman", "kendall", "spearman_ci95", "kendall_ci95", "undefined_share",
    "p_spearman", "p_kendall", "best_by_score", "best_observed", "discordant_pairs": [[lower h,
    higher h]] the score orders opposite to the figure, "verdict": "predicts" (the interval of rho
    lies above 0 and the permutation p is below 1 - confidence), "inverted" (the same, below 0),
    "no evidence" (otherwise) or "too few heights" (n < 3)}. Both conditions, because the pairs
    bootstrap of very few heights is overconfident (four near-monotone triples rarely resample
    to a positive rho), while the exact permutation p cannot go below 2 / n! (0.083 at n = 4).
    """
    heights = [str(h) for h in heights]
    x, y = _check_pair(score, figure)
    if len(heights) != x.size:
        raise ValueError(f"{len(heights)} heights for {x.size} values")
    out = {"n": int(x.size), "heights": heights}
    rho, tau = spearman(x, y), kendall_tau_b(x, y)
    out["spearman"] = None if math.isnan(rho) else round(rho, 4)
    out["kendall"] = None if math.isnan(tau) else round(tau, 4)
    bs = bootstrap_interval(x, y, "spearman", replicates, seed, confidence)
    bk = bootstrap_interval(x, y, "kendall", replicates, seed, confidence)
    out["spearman_ci95"], out["kendall_ci95"] = bs["ci95"], bk["ci95"]
    out["undefined_share"] = bs["undefined_share"]
    out["p_spearman"] = None if math.isnan(rho) else round(permutation_pvalue(x, y, "spearman", seed=seed), 5)
    out["p_kendall"] = None if math.isnan(tau) else round(permutation_pvalue(x, y, "kendall", seed=seed), 5)
    out["best_by_score"] = heights[int(np.argmax(x))] if x.size else None
    out["best_observed"] = heights[int(np.argmax(y))] if y.size else None
    pairs = []
    for a in range(x.size):
        for b in range(a + 1, x.size):
            if (x[a] - x[b]) * (y[a] - y[b]) < 0:
                lo, hi = sorted((heights[a], heights[b]), key=float)
                pairs.append([lo, hi])
    out["discordant_pairs"] = pairs
    ci = out["spearman_ci95"]
    significant = out["p_spearman"] is not None and out["p_spearman"] < 1.0 - confidence
    if x.size < 3 or out["spearman"] is None:
        out["verdict"] = "too few heights" if x.size < 3 else "undefined (constant score or figure)"
    elif ci is not None and ci[0] > 0 and significant:
        out["verdict"] = "predicts"
    elif ci is not None and ci[1] < 0 and significant:
        out["verdict"] = "inverted"
    else:
        out["verdict"] = "no evidence"
    return out


# ---------------------------------------------------------------------------- detector reports
def load_detector_reports(paths: Sequence[str | Path]) -> tuple[dict, list[dict]]:
    """Read tools/eval.py report.json files into {model: {height key: {"results", "source"}}}.

    A report tested at another height than it was trained at ("trained_height" differs: a
    cross-height cell) is skipped and listed, as it says nothing about the height it was
    trained for; so is a two-stage model's first stage alone ("stage": "proposals"). Raises
    ValueError naming the file for anything that is not such a report, or for a model and
    height given twice. Returns (figures, skipped [{"source", "reason"}])."""
    from detbench.eval.report import check_report
    from detbench.utils.atomic import read_json

    figures: dict[str, dict[str, dict]] = {}
    skipped: list[dict] = []
    for p in paths:
        p = Path(p)
        if not p.is_file():
            raise ValueError(f"{p}: no such detector report; give report.json files written by tools/eval.py "
                             f"(e.g. runs/second_1.8/eval_h1.8_test/report.json)")
        try:
            rep = read_json(p)
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"{p}: not a JSON report ({e}); give report.json files written by tools/eval.py") from None
        check_report(rep, str(p))
        if rep.get("height") is None or not rep.get("model"):
            raise ValueError(f"{p}: the report has no 'height' or no 'model'; evaluate with tools/eval.py --ckpt "
                             f"(which writes both) or add --model NAME")
        hk = height_key(float(rep["height"]))
        th = rep.get("trained_height")
        if th is not None and height_key(float(th)) != hk:
            skipped.append({"source": str(p), "reason": f"cross-height: trained at {height_key(float(th))} m, "
                                                         f"tested at {hk} m"})
            continue
        if rep.get("stage", "refined") != "refined":
            skipped.append({"source": str(p), "reason": f"first stage alone (--stage {rep['stage']}): not the "
                                                         f"detector's output"})
            continue
        model = str(rep["model"])
        if hk in figures.get(model, {}):
            raise ValueError(f"{p}: model {model!r} at {hk} m is also in {figures[model][hk]['source']}; give each "
                             f"model and height once")
        figures.setdefault(model, {})[hk] = {"results": rep["results"], "source": str(p),
                                             "split": rep.get("split"), "num_frames": rep.get("num_frames")}
    return figures, skipped


def correlate_sweep(sweep: dict, figures: dict, scores: Sequence[str] | None = None,
                    metrics: Sequence[str] = METRICS, replicates: int = DEFAULT_REPLICATES, seed: int = 0,
                    confidence: float = 0.95) -> dict:
    """Rank correlation of every score of a sweep report with every detector figure.

    For each model, the heights it was trained and tested at that the sweep also holds are
    used; a score of range r is compared with the figure of range r at every level (the
    scores are per range). Rows: {"model", "metric", "range_name", "level", "score", **
    rank_agreement}. "summary": per score, the rows that predict / show no evidence / are
    inverted and the median rho; "statements": plain sentences on where each score fails.
    """
    sc = sweep["scores"]["heights"]
    swept = set(sweep["heights"])
    available = [s for s in (scores or list(sweep["scores"]["units"])) if
                 all(s in sc[hk][r] for hk in sweep["heights"] for r in RANGE_NAMES)]
    rows: list[dict] = []
    models: dict[str, dict] = {}
    notes: list[str] = []
    for model, by_h in figures.items():
        hs = sorted((h for h in by_h if h in swept), key=float)
        missing = sorted((h for h in by_h if h not in swept), key=float)
        models[model] = {"heights": hs, "not_in_sweep": missing,
                         "sources": {h: by_h[h]["source"] for h in hs}}
        if missing:
            notes.append(f"{model}: heights {', '.join(missing)} m are not in the sweep and were left out")
        if len(hs) < 3:
            notes.append(f"{model}: {len(hs)} height(s) in common with the sweep; a rank correlation needs at least "
                         f"3 (6 or more give it a chance to resolve)")
            continue
        for metric in metrics:
            for r in RANGE_NAMES:
                for lv in LEVELS:
                    ys = [by_h[h]["results"][r][lv].get(metric) for h in hs]
                    for s in available:
                        xs = [sc[h][r][s]["value"] for h in hs]
                        keep = [i for i in range(len(hs)) if ys[i] is not None and xs[i] is not None
                                and math.isfinite(float(ys[i])) and math.isfinite(float(xs[i]))]
                        if len(keep) < 3:
                            continue
                        agr = rank_agreement([hs[i] for i in keep], [float(xs[i]) for i in keep],
                                             [float(ys[i]) for i in keep], replicates, seed, confidence)
                        rows.append({"model": model, "metric": metric, "range_name": r, "level": lv, "score": s,
                                     **agr})
    summary = {}
    for s in available:
        mine = [row for row in rows if row["score"] == s]
        rhos = [row["spearman"] for row in mine if row["spearman"] is not None]
        summary[s] = {"rows": len(mine),
                      **{v: sum(row["verdict"] == v for row in mine) for v in ("predicts", "no evidence", "inverted")},
                      "median_spearman": round(float(np.median(rhos)), 4) if rhos else None,
                      "best_height_agrees": sum(row["best_by_score"] == row["best_observed"] for row in mine)}
    return {"method": f"Spearman rho and Kendall tau-b over heights; {int(confidence * 100)} % percentile "
                      f"bootstrap over (height, score, figure) triples ({replicates} replicates, seed {seed}); "
                      f"two-sided permutation p (exact up to {EXACT_MAX_N} heights)",
            "metrics": list(metrics), "scores": available, "models": models, "rows": rows, "summary": summary,
            "statements": _statements(rows, available), "notes": notes}


def _statements(rows: list[dict], scores: Sequence[str]) -> list[str]:
    """Plain sentences: per model, metric and score, where the score fails to predict the figure."""
    out = []
    keys = sorted({(r["model"], r["metric"], r["score"]) for r in rows},
                  key=lambda k: (k[0], k[1], list(scores).index(k[2])))
    for model, metric, s in keys:
        mine = [r for r in rows if (r["model"], r["metric"], r["score"]) == (model, metric, s)]
        bad = [r for r in mine if r["verdict"] != "predicts"]
        label = {"recall": "recall", "ap_r40": "AP@R40"}.get(metric, metric)
        if not bad:
            out.append(f"{s} predicts {model}'s {label} order in all {len(mine)} range/level cells "
                       f"(every 95 % interval of rho above 0, permutation p < 0.05).")
            continue
        parts = []
        for r in bad:
            where = f"{r['range_name']}/{r['level']}"
            what = (f"rho {r['spearman']:+.2f}" if r["spearman"] is not None else "rho undefined")
            swaps = ""
            if r["discordant_pairs"]:
                swaps = "; wrong order for " + ", ".join(f"{a}<->{b} m" for a, b in r["discordant_pairs"][:4]) \
                    + (" ..." if len(r["discordant_pairs"]) > 4 else "")
            best = "" if r["best_by_score"] == r["best_observed"] else \
                f"; picks {r['best_by_score']} m, best is {r['best_observed']} m"
            parts.append(f"{where} ({r['verdict']}, {what}{swaps}{best})")
        out.append(f"{s} fails to predict {model}'s {label} in {len(bad)} of {len(mine)} cells: " + "; ".join(parts))
    return out


def _fmt(v, d=2) -> str:
    return "-" if v is None else f"{v:+.{d}f}"


def _ci(c) -> str:
    return "" if c is None else f" [{c[0]:+.2f}, {c[1]:+.2f}]"


def correlation_markdown(corr: dict, primary: str | None = None) -> str:
    """Markdown of `correlate_sweep`'s result: the summary per score, the primary score's rows per
    model, and the plain statements of where each score fails."""
    lines = ["## Placement score against trained detectors (rank correlation over heights)", "", corr["method"] + ".",
             ""]
    for n in corr.get("notes", []):
        lines.append(f"- {n}")
    if corr.get("notes"):
        lines.append("")
    if not corr["rows"]:
        return "\n".join(lines + ["No model had 3 or more heights in common with the sweep: nothing to correlate.", ""])
    lines += ["| score | cells | predicts | no evidence | inverted | median rho | best height agrees |",
              "|---|---|---|---|---|---|---|"]
    for s, v in corr["summary"].items():
        lines.append(f"| {s} | {v['rows']} | {v['predicts']} | {v['no evidence']} | {v['inverted']} | "
                     f"{_fmt(v['median_spearman'])} | {v['best_height_agrees']} |")
    lines.append("")
    primary = primary or (corr["scores"][0] if corr["scores"] else None)
    for model, info in corr["models"].items():
        mine = [r for r in corr["rows"] if r["model"] == model and r["score"] == primary]
        if not mine:
            continue
        lines += [f"### {model}, score `{primary}` (heights {', '.join(info['heights'])} m)", "",
                  "| metric | range | level | n | Spearman rho [95 %] | Kendall tau [95 %] | p (rho) | best: score / "
                  "detector | verdict |", "|---|---|---|---|---|---|---|---|---|"]
        for r in mine:
            p = "-" if r["p_spearman"] is None else f"{r['p_spearman']:.3f}"
            lines.append(f"| {r['metric']} | {r['range_name']} | {r['level']} | {r['n']} | "
                         f"{_fmt(r['spearman'])}{_ci(r['spearman_ci95'])} | "
                         f"{_fmt(r['kendall'])}{_ci(r['kendall_ci95'])}"
                         f" | {p} | {r['best_by_score']} / {r['best_observed']} m | {r['verdict']} |")
        lines.append("")
    lines += ["### Where the scores fail", ""] + [f"- {s}" for s in corr["statements"]] + [""]
    return "\n".join(lines)


__all__ = ["rankdata", "spearman", "kendall_tau_b", "permutation_pvalue", "bootstrap_interval", "rank_agreement",
           "load_detector_reports", "correlate_sweep", "correlation_markdown", "METRICS", "STATISTICS"]
