"""Figures over several training seeds: the seed mean with an interval for test scenes AND seeds.

A detector's recall or AP@R40 on the test split varies for two reasons: the test scenes are a
finite sample of traffic (the scene bootstrap of `detbench.eval.bootstrap` measures that), and
training is random (initialisation, data order, augmentation), so a second training seed gives
another figure on the very same frames. One run decides a ranking only to within that second
spread. Here each (model, height) is trained once per seed and every seed is evaluated on the
same test split; the figure reported is the mean over seeds, with a 95 % interval that holds both
sources. All figures are fractions in [0, 1]; leads are differences of fractions.

The combination, and why:

- **Scene term, paired over seeds.** Every seed is evaluated on the same frames, so one bootstrap
  replicate (a draw of test scenes with replacement) applies to every seed at once, and the
  percentile interval of the replicates' seed mean is the scene interval of the seed mean.
  Recall is a ratio of sums over scenes, so this is exact from the per-scene TP and LiDAR-detected
  counts of the report's "uncertainty" block: replicate b gives (w_b . mean_s tp_s) / (w_b . det),
  drawn with `scene_bootstrap_weights` and the report's own scene count, replicates and seed, so
  one seed reproduces the report's interval to the digit. AP@R40 pools the ranked predictions of
  every frame; its scene interval of the seed mean is the mean of the seeds' interval ends: exact
  for one seed and for identical seeds, and otherwise on the wide side (seeds see the same scenes,
  so their replicates move together, and the spread of a mean is at most the mean of the spreads).
- **Seed term.** The seeds' standard deviation s (n - 1 in the denominator) is measured on fixed
  test frames, so it is training randomness alone. The seed mean carries s^2 / n of it; its 95 %
  half-width is q = t(0.975, n - 1) * s / sqrt(n) with Student's t, because s from 2 or 3 values is
  itself rough: t = 12.71 for 2 seeds, 4.30 for 3, 2.78 for 5. A bootstrap over seeds is not used:
  resampling 2 or 3 values has a handful of outcomes and shrinks the spread by (n - 1) / n, the
  opposite of what few seeds call for. One seed measures no spread: q is absent, the interval is
  the scene interval alone, and the output says the seed spread is not measured.
- **Seed term pooled over a model's heights** (`seed_summary`, `seed_height_summary`,
  `seed_markdown`; `pool=False` turns it off). With 2 seeds the t factor is 12.71 and s itself
  rests on one difference, so a cell's own seed term is either huge or, by luck, near zero; with
  the heights of a study trained alike, a model's seed variance is taken as one quantity per
  (range, level, metric) and estimated from every height: s_p^2 = sum (n_h - 1) s_h^2 /
  sum (n_h - 1), with df = sum (n_h - 1) (3 for 2 seeds at 3 heights: t = 3.18; 6 for 3 seeds:
  t = 2.45), the pooled variance of a one-way analysis of variance. The cell then carries
  q = t(df) * s_p / sqrt(n), and its own s stays beside it ("sd_own"). The assumption is that the
  training randomness of one model does not depend on the height it is trained at; it errs where
  one height trains less stably than the others.
- **Both together.** The two errors are independent (which scenes were drawn; which seeds were
  drawn), so the half-widths add in quadrature, each side on its own: lo = m - sqrt((m - lo_s)^2
  + q^2), hi = m + sqrt((hi_s - m)^2 + q^2), with [lo_s, hi_s] the scene interval of the mean.
  This is exact for two normal terms and errs wide otherwise: the scene bootstrap of the mean
  already holds some seed-by-scene noise that s counts again, and a t quantile added in quadrature
  lies above the quantile of the sum. Fractions are clipped to [0, 1], leads to [-1, 1].
  Without a scene interval (reports evaluated without --bootstrap, or a single test scene) there
  is no combined interval: the seed spread alone would claim too much.
- **Leads between models** (`seed_summary`): the difference of the seed means. Its scene term for
  recall is paired over the same scenes (one draw applies to both models' mean per-scene TP);
  with one seed each it is, digit for digit, the lead of
  `detbench.studies.study_summary.paired_recall_difference`. AP@R40 is paired the same way where
  every report of both sides keeps its AP ranking (`uncertainty["ap_ranking"]`,
  detbench.eval.ap_bootstrap): one draw of scenes re-ranks each report's pooled detections with those
  scene weights, and the draw's difference of the two seed means of AP@R40 is one replicate. Reports
  that lack the ranking fall back to the two models' scene half-widths in quadrature, as if the models
  erred independently over scenes: wider than the paired interval, since a hard scene is hard for both.
  The seed term is Welch's: q = t(0.975, df) * sqrt(s_a^2 / n_a + s_b^2 / n_b), df by
  Welch-Satterthwaite; a model with one seed takes the other's seed variance (the df of the one
  measured); with one seed each there is no seed term. A model is called ahead only when the
  combined interval excludes 0; otherwise the lead is "not resolved".
- **Leads between heights** (`seed_height_summary`): one model at two heights, the same way. The
  heights of a study share their test scenes (the same traffic), so recall is still paired over
  scenes, each height over its own LiDAR-detected vehicles: replicate b gives the difference of
  the two heights' resampled ratios (AP@R40: of the two heights' re-ranked AP). The trainings at two
  heights count as independent (Welch), which errs wide where a seed starts both from the same weights.
- **The height answer** (`seed_height_pairs`): every pair of a model's heights, not only the leader
  over the runner-up, for AP@R40 (small range) and recall (large range), each lead as above. A pair is
  "resolved" when its interval excludes 0, else "bounded": the two heights differ by less than
  max(|lo|, |hi|) either way, an equivalence statement at that margin rather than "no difference".

The reports are checked by detbench.studies.seed_checks (one test split, one evaluation setting);
the Student-t quantile is detbench.studies.student_t's. `seed_statistics` computes everything a
study reports of its seeds once: the combined cells per model and height, the leader per height
and per model, every pair of models, every pair of each model's heights, the detector table's rows;
the Markdown of it is detbench.studies.seed_markdown's. The cells are typed (`MetricCell`,
`SeedCombined`, `Lead`, `Leader`); the public functions return their JSON layouts (`to_dict`), as
study.json holds them.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from itertools import combinations

import numpy as np

from detbench.data.frame import key_label, key_order
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.ap_bootstrap import has_ap_ranking, paired_ap_difference
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights
from detbench.eval.paper import paper_recall
from detbench.studies.seed_cells import Lead, Leader, MetricCell, SeedCombined, SeedPool
from detbench.studies.seed_checks import bootstrap_settings, checked_groups, checked_reports, seed_label
from detbench.studies.student_t import student_t_quantile

METRICS: tuple[str, ...] = ("recall", "ap_r40")
CONFIDENCE = 0.95
# The paired lead's scene bootstrap: the replicates and seed of study_summary.paired_recall_difference,
# so one seed per model gives the single-seed lead to the digit.
LEAD_REPLICATES = 2000
LEAD_SEED = 0
# What the summary ranks: recall of the LiDAR-detected vehicles in the large range (as
# detector_summary) and AP@R40 in the small range, both over all vehicles.
RECALL_CELL = ("large", "all")
AP_CELL = ("small", "all")
WHAT = (("recall", RECALL_CELL, "ap_r40"), ("ap_r40", AP_CELL, "recall"))  # (metric, cell, tie-breaker)


# --------------------------------------------------------------------------------------------
# one (model, height): the seed mean with its intervals
# --------------------------------------------------------------------------------------------

def _r6(v: float | None) -> float | None:
    return None if v is None else round(float(v), 6)


def _clip(ci: list | None, lo: float, hi: float) -> list | None:
    return None if ci is None else [round(min(max(ci[0], lo), hi), 6), round(min(max(ci[1], lo), hi), 6)]


def _add_seed_term(m: float, scene_ci: list | None, q: float | None, bounds: tuple[float, float]) -> list | None:
    """The combined interval: the scene interval's two sides and the seed half-width q in quadrature."""
    if scene_ci is None:
        return None
    if q is None:
        return list(scene_ci)
    lo = m - math.hypot(max(m - scene_ci[0], 0.0), q)
    hi = m + math.hypot(max(scene_ci[1] - m, 0.0), q)
    return _clip([lo, hi], *bounds)


def _seed_half_width(values: Sequence[float], confidence: float) -> tuple[float | None, float | None, float | None]:
    """(sd, t factor, half-width t * sd / sqrt(n)) of per-seed values; Nones for one seed."""
    n = len(values)
    if n < 2:
        return None, None, None
    sd = float(np.std(np.asarray(values, dtype=np.float64), ddof=1))
    t = student_t_quantile(0.5 + confidence / 2.0, n - 1)
    return sd, t, t * sd / math.sqrt(n)


def _mean_tp(reports: Sequence[dict], r: str, lv: str) -> np.ndarray:
    return np.mean([np.asarray(rep["uncertainty"]["per_cluster"][r][lv]["tp"], dtype=np.float64) for rep in reports],
                   axis=0)


def _det(rep: dict, r: str, lv: str) -> np.ndarray:
    return np.asarray(rep["uncertainty"]["per_cluster"][r][lv]["lidar_detected"], dtype=np.float64)


def _cell(reports: Sequence[dict], r: str, lv: str, metric: str, weights: np.ndarray | None,
          confidence: float) -> MetricCell:
    values = [rep["results"][r][lv][metric] for rep in reports]
    per_seed = tuple(_r6(v) for v in values)
    if any(v is None for v in values):
        return MetricCell(per_seed=per_seed)  # nothing evaluated in this cell (the same for every seed)
    m = float(np.mean(np.asarray(values, dtype=np.float64)))
    sd, t, q = _seed_half_width(values, confidence)
    scene_ci, method = None, None
    if weights is not None:
        if metric == "recall":
            scene_ci = percentile_interval(bootstrap_ratios(weights, _mean_tp(reports, r, lv), _det(reports[0], r, lv)),
                                           confidence)
            method = "paired scene bootstrap of the seed mean (the same draws for every seed)"
        else:
            cis = [((rep["uncertainty"].get("results") or {}).get(r, {}).get(lv) or {}).get("ap_r40_ci95")
                   for rep in reports]
            if all(cis):
                ends = np.mean(np.asarray(cis, dtype=np.float64), axis=0)
                scene_ci = [round(float(ends[0]), 6), round(float(ends[1]), 6)]
            method = "mean of the seeds' scene-bootstrap interval ends (AP needs per-frame ranks)"
    return MetricCell(mean=_r6(m), sd=_r6(sd), per_seed=per_seed, seed_t=_r6(t), seed_half_width=_r6(q),
                      scene_ci95=scene_ci, scene_method=method, ci95=_add_seed_term(m, scene_ci, q, (0.0, 1.0)))


def combine_seeds(reports: Sequence[dict], where: str = "reports") -> SeedCombined:
    """The seed mean of one (model, height) with its intervals, typed (`seed_combined` gives its JSON layout)."""
    reports = checked_reports(reports, where)
    unc = reports[0].get("uncertainty")
    boot = bootstrap_settings(reports[0])
    confidence = boot[3] if boot else CONFIDENCE
    weights = None
    if boot is not None and boot[0] >= 2 and boot[1] > 0:
        weights = scene_bootstrap_weights(boot[0], boot[1], boot[2])
    results = {r: {lv: {m: _cell(reports, r, lv, m, weights, confidence) for m in METRICS} for lv in LEVELS}
               for r in RANGE_NAMES}
    return SeedCombined(num_seeds=len(reports), seeds=tuple(seed_label(rep, i) for i, rep in enumerate(reports)),
                        num_scenes=None if unc is None else int(unc["num_clusters"]),
                        replicates=None if boot is None else boot[1], confidence=confidence, results=results)


def seed_combined(reports: Sequence[dict], where: str = "reports") -> dict:
    """The seed mean of one (model, height) with its intervals, from one eval report per training seed.

    reports: `detbench.eval.evaluate` reports (tools/eval.py's report.json), one per seed, all on
    the same test split (else ValueError naming the report). `where` names the group in errors.
    Returns {"num_seeds", "seeds" (the reports' "train_seed", else "#1", "#2", ...), "num_scenes",
    "replicates", "confidence", "seed_spread_measured", "results": {range: {level: {metric: cell}}}}
    with metric in recall / ap_r40 and cell = {"mean", "sd" (seed-to-seed, n - 1), "per_seed",
    "seed_t" (the Student-t factor), "seed_half_width" (t * sd / sqrt(n)), "scene_ci95" (the scene
    bootstrap of the seed mean), "scene_method", "ci95" (scenes and seeds together)}. Fractions in
    [0, 1]; None where nothing is evaluated or no interval exists (sd and the seed terms with one
    seed; the intervals without a scene bootstrap). The module docstring gives the reasoning.
    """
    return combine_seeds(reports, where).to_dict()


# --------------------------------------------------------------------------------------------
# a model's seed spread pooled over its heights
# --------------------------------------------------------------------------------------------

def _pool_cells(model: str, combs: list[SeedCombined], r: str, lv: str, metric: str) -> list[MetricCell] | None:
    """The cells of one (range, level, metric) of `model`'s heights with the pooled spread, or None when fewer
    than two of them measured a spread."""
    cells = [c.cell(r, lv, metric) for c in combs]
    measured = [(cell, c.num_seeds) for cell, c in zip(cells, combs) if cell.sd is not None and c.num_seeds >= 2]
    df = sum(n - 1 for _, n in measured)
    if df < 1 or len(measured) < 2:
        return None
    sd = math.sqrt(sum((n - 1) * cell.sd ** 2 for cell, n in measured) / df)
    out = []
    for cell, c in zip(cells, combs):
        if cell.mean is None:
            out.append(cell)
            continue
        t = student_t_quantile(0.5 + c.confidence / 2.0, df)
        q = t * sd / math.sqrt(c.num_seeds)
        out.append(replace(cell, sd=_r6(sd), seed_t=_r6(t), seed_half_width=_r6(q),
                           ci95=_add_seed_term(cell.mean, cell.scene_ci95, q, (0.0, 1.0)),
                           pool=SeedPool(sd_own=cell.sd, df=df, model=model)))
    return out


def pooled(combined: Mapping[tuple[str, float], SeedCombined]) -> dict[tuple[str, float], SeedCombined]:
    """`combined` with each model's seed variance pooled over its heights (module docstring): for every
    range, level and metric whose groups measured a spread (2 or more seeds), each cell of the model carries
    the pooled sd, its own sd, the pooled df and t, and its interval recombined. A model with one height, or
    with one seed everywhere, is returned as it is."""
    by_model: dict[str, list[tuple[str, float]]] = {}
    for key in combined:
        by_model.setdefault(str(key[0]), []).append(key)
    out = dict(combined)
    for model, keys in by_model.items():
        if len(keys) < 2:
            continue
        combs = [combined[k] for k in keys]
        results = [{r: {lv: dict(c.results[r][lv]) for lv in LEVELS} for r in RANGE_NAMES} for c in combs]
        any_pooled = False
        for r in RANGE_NAMES:
            for lv in LEVELS:
                for metric in METRICS:
                    cells = _pool_cells(model, combs, r, lv, metric)
                    if cells is None:
                        continue
                    any_pooled = True
                    for res, cell in zip(results, cells):
                        res[r][lv][metric] = cell
        for k, c, res in zip(keys, combs, results):
            out[k] = replace(c, results=res, pooled_over_heights=any_pooled)
    return out


def pool_seed_spread(combined: Mapping[tuple[str, float], dict]) -> dict[tuple[str, float], dict]:
    """{(model, height): seed_combined(...)} with each model's seed spread pooled over its heights (`pooled`):
    each pooled cell gets sd = the pooled s_p, "sd_own" (its own s, None for one seed), "seed_df" (the pooled
    df), "seed_pool" (the model), "seed_t" = t(df), "seed_half_width" = t * s_p / sqrt(n) and "ci95"
    recombined with its scene interval. The input is left as it is."""
    typed = {k: SeedCombined.from_dict(c) for k, c in combined.items()}
    return {k: c.to_dict() for k, c in pooled(typed).items()}


# --------------------------------------------------------------------------------------------
# leads: two models at one height, or one model at two heights
# --------------------------------------------------------------------------------------------

def _welch(ca: MetricCell, cb: MetricCell, n_a: int, n_b: int, confidence: float) -> tuple[float | None, float | None]:
    """(t factor, half-width) of the seed term of mean_a - mean_b (module docstring)."""
    sa, sb = ca.sd, cb.sd
    if sa is None and sb is None:
        return None, None
    da = (ca.pool.df if ca.pool else None) or n_a - 1
    db = (cb.pool.df if cb.pool else None) or n_b - 1
    if sa is None:  # one seed of a: assume b's seed variance, the df b measured
        sa, df = sb, db
    elif sb is None:
        sb, df = sa, da
    elif ca.pool is not None and cb.pool is not None and ca.pool.model == cb.pool.model:
        df = min(da, db)  # one pooled estimate on both sides (a model at two heights): its own df, not twice it
    else:
        va, vb = sa * sa / n_a, sb * sb / n_b
        df = (va + vb) ** 2 / (va * va / da + vb * vb / db) if va + vb > 0 else da + db
    var = sa * sa / n_a + sb * sb / n_b
    t = student_t_quantile(0.5 + confidence / 2.0, df)
    return t, t * math.sqrt(var)


def _scene_quadrature(diff: float, ca: MetricCell, cb: MetricCell) -> list | None:
    """Unpaired scene interval of mean_a - mean_b: the two scene intervals' sides in quadrature."""
    if not ca.scene_ci95 or not cb.scene_ci95:
        return None
    a_lo, a_hi = ca.mean - ca.scene_ci95[0], ca.scene_ci95[1] - ca.mean
    b_lo, b_hi = cb.mean - cb.scene_ci95[0], cb.scene_ci95[1] - cb.mean
    return [round(diff - math.hypot(max(a_lo, 0.0), max(b_hi, 0.0)), 6),
            round(diff + math.hypot(max(a_hi, 0.0), max(b_lo, 0.0)), 6)]


def _paired_recall(rep_a: Sequence[dict], rep_b: Sequence[dict], r: str, lv: str,
                   confidence: float) -> tuple[float, list | None, str | None]:
    """(diff, scene interval, method) of the recall lead over the same scenes, each side over its own
    LiDAR-detected vehicles (the same ones for two models at one height)."""
    da, db = _det(rep_a[0], r, lv), _det(rep_b[0], r, lv)
    ta, tb = _mean_tp(rep_a, r, lv), _mean_tp(rep_b, r, lv)
    same_det = np.array_equal(da, db)
    # da.sum(), db.sum() > 0: both recall means exist
    diff = float((ta.sum() - tb.sum()) / da.sum()) if same_det else float(ta.sum() / da.sum() - tb.sum() / db.sum())
    if len(da) < 2:
        return diff, None, None
    w = scene_bootstrap_weights(len(da), LEAD_REPLICATES, LEAD_SEED)
    boot = (bootstrap_ratios(w, ta - tb, da) if same_det
            else bootstrap_ratios(w, ta, da) - bootstrap_ratios(w, tb, db))
    method = "paired scene bootstrap (the same scenes for both and every seed)"
    return diff, percentile_interval(boot, confidence), method


def _paired_ap(rep_a: Sequence[dict], rep_b: Sequence[dict], r: str, lv: str,
               confidence: float) -> tuple[list | None, str | None]:
    """(scene interval, method) of the AP@R40 lead over the same scenes: every report of both sides re-ranked in
    each draw (detbench.eval.ap_bootstrap), each side's seed mean per draw."""
    if len(rep_a[0]["uncertainty"]["clusters"]) < 2:
        return None, None
    boot = paired_ap_difference(rep_a, rep_b, r, lv, LEAD_REPLICATES, LEAD_SEED)
    return (percentile_interval(boot, confidence),
            "paired scene bootstrap (the same scenes for both and every seed; AP@R40 re-ranked in each draw)")


def _lead(rep_a: Sequence[dict], rep_b: Sequence[dict], comb_a: SeedCombined, comb_b: SeedCombined, r: str, lv: str,
          metric: str) -> Lead | None:
    """mean_a - mean_b in one cell with its scene term, seed term and combined interval. a and b are
    two models at one height (the same LiDAR-detected vehicles) or one model at two heights (the same
    test scenes, other LiDAR-detected vehicles)."""
    ca, cb = comb_a.cell(r, lv, metric), comb_b.cell(r, lv, metric)
    if ca.mean is None or cb.mean is None:
        return None
    confidence = comb_a.confidence
    diff = float(np.mean([x["results"][r][lv][metric] for x in rep_a])
                 - np.mean([x["results"][r][lv][metric] for x in rep_b]))
    ua, ub = rep_a[0].get("uncertainty"), rep_b[0].get("uncertainty")
    paired = bool(ua) and bool(ub) and list(ua["clusters"]) == list(ub["clusters"])
    if metric == "recall" and paired:
        diff, scene_ci, method = _paired_recall(rep_a, rep_b, r, lv, confidence)
    elif metric == "ap_r40" and paired and all(has_ap_ranking(x) for x in (*rep_a, *rep_b)):
        scene_ci, method = _paired_ap(rep_a, rep_b, r, lv, confidence)
    else:
        scene_ci, method = _scene_quadrature(diff, ca, cb), None
        if scene_ci is not None:
            why = "the reports keep no AP ranking" if metric == "ap_r40" and paired else "the test scenes differ"
            method = f"the two scene intervals in quadrature (unpaired: {why}; errs wide)"
    t, q = _welch(ca, cb, comb_a.num_seeds, comb_b.num_seeds, confidence)
    ci = _add_seed_term(diff, scene_ci, q, (-1.0, 1.0))
    ahead = bool(ci) and (ci[0] > 0 or ci[1] < 0)
    return Lead(diff=_r6(diff), scene_ci95=scene_ci, scene_method=method, seed_t=_r6(t), seed_half_width=_r6(q),
                ci95=ci, ahead=ahead, verdict="ahead" if ahead else ("not resolved" if ci else "no interval"))


def _ranking(key: str, items: Mapping, cell: tuple[str, str], metric: str, other: str) -> tuple[dict, ...]:
    """`items` ({model or height: (reports of each seed, SeedCombined)}) ranked by the seed mean of `metric` in
    `cell`, ties broken on `other`: ({key: name, "mean", "ci95", "num_seeds"}, ...), best first."""
    r, lv = cell

    def mean(k, m):
        return items[k][1].cell(r, lv, m).mean

    ranked = sorted((k for k in items if mean(k, metric) is not None),
                    key=lambda k: (-mean(k, metric), -(mean(k, other) or 0.0)))
    return tuple({key: k, "mean": mean(k, metric), "ci95": items[k][1].cell(r, lv, metric).ci95,
                  "num_seeds": items[k][1].num_seeds} for k in ranked)


def _leader(key: str, items: Mapping, cell: tuple[str, str], metric: str, other: str) -> Leader:
    """`_ranking` with the lead of the first over the second."""
    ranking = _ranking(key, items, cell, metric, other)
    lead = None
    if len(ranking) > 1:
        (ra, ca), (rb, cb) = items[ranking[0][key]], items[ranking[1][key]]
        lead = _lead(ra, rb, ca, cb, *cell, metric)
    return Leader(key=key, range=cell[0], level=cell[1], ranking=ranking, lead=lead)


# --------------------------------------------------------------------------------------------
# a study's seeds: every figure computed once
# --------------------------------------------------------------------------------------------

def combined_groups(groups: Mapping, pool: bool = True) -> dict[float, dict[str, tuple[list[dict], SeedCombined]]]:
    """{height: {model: (reports, SeedCombined)}} of {(model, height): [report of each seed]} (checked by
    detbench.studies.seed_checks), with the seed spread pooled over each model's heights when `pool`."""
    by_height = checked_groups(groups)
    combs = {(m, h): combine_seeds(reps, f"{m} at {key_label(h)}") for h, models in by_height.items()
             for m, reps in models.items()}
    if pool:
        combs = pooled(combs)
    return {h: {m: (reps, combs[(m, h)]) for m, reps in models.items()} for h, models in by_height.items()}


def _height_leaders(combined: Mapping) -> dict:
    """{height: {"models": {model: seed_combined}, "recall": leader, "ap_r40": leader}} (`seed_summary`)."""
    return {h: {"models": {m: c.to_dict() for m, (_, c) in items.items()},
                **{metric: _leader("model", items, cell, metric, other).to_dict() for metric, cell, other in WHAT}}
            for h, items in combined.items()}


def _by_model(combined: Mapping) -> dict[str, dict[float, tuple]]:
    """{model: {height: (reports, SeedCombined)}} of the models tested at two or more heights."""
    by_model: dict[str, dict[float, tuple]] = {}
    for h, items in combined.items():
        for m, pair in items.items():
            by_model.setdefault(m, {})[h] = pair
    return {m: items for m, items in by_model.items() if len(items) > 1}


def _model_leaders(combined: Mapping) -> dict:
    """{model: {"recall": leader, "ap_r40": leader}} over its heights (`seed_height_summary`)."""
    return {m: {metric: _leader("height", items, cell, metric, other).to_dict() for metric, cell, other in WHAT}
            for m, items in _by_model(combined).items()}


def _height_answer(lead: Lead, a: float, b: float) -> dict:
    """"resolved" (the interval excludes 0: "leader" is the height ahead) or "bounded" (it holds 0: the heights
    differ by less than "margin" = max(|lo|, |hi|) either way), or "no interval"."""
    if lead.ci95 is None:
        return {"answer": "no interval", "leader": None, "margin": None}
    lo, hi = lead.ci95
    if lo > 0 or hi < 0:
        return {"answer": "resolved", "leader": a if lo > 0 else b, "margin": None}
    return {"answer": "bounded", "leader": None, "margin": _r6(max(abs(lo), abs(hi)))}


def _height_pairs(combined: Mapping) -> dict:
    """{model: {metric: {"range", "level", "pairs"}}} (`seed_height_pairs`)."""
    out: dict[str, dict] = {}
    for m, items in _by_model(combined).items():
        out[m] = {}
        for metric, cell, other in WHAT:
            ranking = _ranking("height", items, cell, metric, other)
            pairs = []
            for a, b in combinations([e["height"] for e in ranking], 2):
                lead = _lead(items[a][0], items[b][0], items[a][1], items[b][1], *cell, metric)
                if lead is not None:
                    pairs.append({"height": a, "over": b, **lead.to_dict(), **_height_answer(lead, a, b)})
            out[m][metric] = {"range": cell[0], "level": cell[1], "pairs": pairs}
    return out


def _pairs(combined: Mapping) -> dict:
    """{height: {range: {metric: {"ranking", "pairs"}}}} (`pairwise_leads`)."""
    out: dict[float, dict] = {}
    for h, items in combined.items():
        by_range: dict[str, dict] = {}
        for r in RANGE_NAMES:
            for metric in METRICS:
                # ranked as `seed_summary` ranks (ties broken on the other metric)
                ranking = [dict(e) for e in _ranking("model", items, (r, "all"), metric,
                                                     "ap_r40" if metric == "recall" else "recall")]
                pairs = []
                for a, b in combinations([e["model"] for e in ranking], 2):
                    lead = _lead(items[a][0], items[b][0], items[a][1], items[b][1], r, "all", metric)
                    if lead is not None:
                        pairs.append({"model": a, "over": b, **lead.to_dict()})
                by_range.setdefault(r, {})[metric] = {"ranking": ranking, "pairs": pairs}
        out[h] = by_range
    return out


def _table(combined: Mapping, train_minutes: Mapping | None) -> list[dict]:
    """The detector table's rows (`detector_table`), per model and then height."""
    by_model: dict[str, list[tuple[float, SeedCombined]]] = {}
    for h, items in combined.items():
        for m, (_, comb) in items.items():
            by_model.setdefault(m, []).append((h, comb))
    rows = []
    for m, cells in by_model.items():
        for h, comb in sorted(cells, key=lambda x: key_order(x[0])):
            recall = {(r, lv): comb.cell(r, lv, "recall").mean for r in RANGE_NAMES for lv in LEVELS}
            ap, rs = comb.cell("small", "all", "ap_r40"), comb.cell("small", "all", "recall")
            paper = None if isinstance(h, str) else paper_recall(m, h)  # Table VII has heights, no rigs
            rows.append({"model": m, "height": h, "num_seeds": comb.num_seeds,
                         "ap_r40_small": {"mean": ap.mean, "ci95": ap.ci95},
                         "recall_small": {"mean": rs.mean, "ci95": rs.ci95},
                         "recall_moderate": recall[("moderate", "all")], "recall_large": recall[("large", "all")],
                         "recall_large_top3": recall[("large", "top3")],
                         "recall_large_top6": recall[("large", "top6")],
                         "paper_recall": list(paper) if paper else None,
                         "train_minutes": (train_minutes or {}).get((m, h))})
    return rows


def seed_statistics(groups: Mapping, train_minutes: Mapping | None = None, pool: bool = True) -> dict:
    """Everything a study reports of its training seeds, computed once from {(model, height): [eval report of
    each seed]}: {"by_height": `seed_summary`'s layout, "by_model": `seed_height_summary`'s, "pairs":
    `pairwise_leads`'s, "height_pairs": `seed_height_pairs`'s, "table": the detector table's rows [{"model",
    "height", "num_seeds", "ap_r40_small": {"mean", "ci95"}, "recall_small": {"mean", "ci95"}, "recall_moderate",
    "recall_large", "recall_large_top3", "recall_large_top6" (seed means), "paper_recall" (Table VII: small /
    moderate / large, or None), "train_minutes" (from `train_minutes`: {(model, height): minutes per training}, or
    None)}]}. Heights as keys in metres."""
    combined = combined_groups(groups, pool)
    return {"by_height": _height_leaders(combined), "by_model": _model_leaders(combined), "pairs": _pairs(combined),
            "height_pairs": _height_pairs(combined), "table": _table(combined, train_minutes)}


def seed_summary(groups: Mapping, pool: bool = True) -> dict:
    """Per height, the model that leads in recall (large range, all vehicles, as detector_summary) and
    in AP@R40 (small range, all vehicles), with its lead over the runner-up.

    groups: {(model, height): [eval report of each training seed]}; at each height every report is
    on the same test split (else ValueError). Returns {height: {"models": {model: seed_combined(...)},
    "recall": lead, "ap_r40": lead}} with lead = {"range", "level", "ranking": [{"model", "mean", "ci95",
    "num_seeds"}], "best", "runner_up", "lead": {"diff", "scene_ci95", "scene_method", "seed_t",
    "seed_half_width", "ci95", "ahead", "verdict"} or None}. "ahead" is True only when the lead's
    interval (scene bootstrap plus both models' seed spread) excludes 0; verdict "ahead",
    "not resolved", or "no interval" (no scene bootstrap). Fractions in [0, 1]. `pool`: each
    model's seed spread pooled over its heights (`pooled`).
    """
    return _height_leaders(combined_groups(groups, pool))


def seed_height_summary(groups: Mapping, pool: bool = True) -> dict:
    """Per model tested at two or more heights, the height at which it leads in recall (large range)
    and AP@R40 (small range), all vehicles, with the lead over the runner-up height.

    The heights of a study share their test scenes (the same traffic), so the recall lead is paired
    over those scenes (each height with its own LiDAR-detected vehicles); the trainings at two heights
    count as independent, so the seed term is Welch's as between models. Scenes that differ between
    the heights fall back to the two scene intervals in quadrature. Returns {model: {"recall": lead,
    "ap_r40": lead}} laid out as in `seed_summary`, with "height" (metres) in place of "model".
    `pool` as in `seed_summary`; the two heights then share one seed estimate, so its df is counted once.
    """
    return _model_leaders(combined_groups(groups, pool))


def seed_height_pairs(groups: Mapping, pool: bool = True) -> dict:
    """The height answer per detector: for each model tested at two or more heights, EVERY pair of its heights in
    AP@R40 (small range) and recall (large range), All vehicles, each a lead as in `seed_height_summary` (scenes
    paired: recall from each scene's counts, AP@R40 re-ranked in each draw where the reports keep their AP
    ranking; both heights' seed spread, Welch's) with its answer.

    Returns {model: {metric: {"range", "level", "pairs": [{"height", "over", "diff", "scene_ci95", "scene_method",
    "seed_t", "seed_half_width", "ci95", "ahead", "verdict", "answer", "leader", "margin"}]}}}: one entry per pair,
    the height with the higher seed mean first (ranked as `seed_height_summary` ranks). "answer" is "resolved"
    when the 95 % interval excludes 0 ("leader": the height ahead), "bounded" when it holds 0 (the two heights
    differ by less than "margin" = max(|lo|, |hi|), either way: an equivalence statement at that margin), or "no
    interval" (no scene bootstrap). Heights in metres, differences of fractions."""
    return _height_pairs(combined_groups(groups, pool))


def pairwise_leads(groups: Mapping, pool: bool = True) -> dict:
    """Every pair of models at each height, in every range, for recall and AP@R40 (All vehicles).

    groups as in `seed_summary`. Returns {height: {range: {metric: {"ranking": [{"model", "mean",
    "ci95", "num_seeds"}] (by seed mean, best first), "pairs": [{"model", "over", **lead}]}}}}: one entry per pair,
    the better-ranked model first, with lead as in `seed_summary` ("diff", "ci95", "ahead", "verdict",
    ...). A pair counts as resolved ("ahead") only where the 95 % interval of the lead, scenes and both
    models' seed spread together, excludes 0. Fractions in [0, 1], leads in [-1, 1]."""
    return _pairs(combined_groups(groups, pool))


__all__ = ["AP_CELL", "CONFIDENCE", "LEAD_REPLICATES", "LEAD_SEED", "Lead", "Leader", "METRICS", "MetricCell",
           "RECALL_CELL", "SeedCombined", "SeedPool", "combine_seeds", "combined_groups", "pairwise_leads",
           "pool_seed_spread", "pooled", "seed_combined", "seed_height_pairs", "seed_height_summary", "seed_statistics",
           "seed_summary", "student_t_quantile"]
