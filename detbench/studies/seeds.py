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
  every frame, which the report does not keep (only each seed's interval), so its scene interval of
  the seed mean is the mean of the seeds' interval ends: exact for one seed and for identical seeds,
  and otherwise on the wide side (seeds see the same scenes, so their replicates move together,
  and the spread of a mean is at most the mean of the spreads).
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
  `detbench.studies.study_summary.paired_recall_difference`. AP@R40 cannot be resampled in pairs
  from the reports, so the two models' scene half-widths add in quadrature, as if the models erred
  independently over scenes: wider than the paired interval, since a hard scene is hard for both.
  The seed term is Welch's: q = t(0.975, df) * sqrt(s_a^2 / n_a + s_b^2 / n_b), df by
  Welch-Satterthwaite; a model with one seed takes the other's seed variance (the df of the one
  measured); with one seed each there is no seed term. A model is called ahead only when the
  combined interval excludes 0; otherwise the lead is "not resolved".
- **Leads between heights** (`seed_height_summary`): one model at two heights, the same way. The
  heights of a study share their test scenes (the same traffic), so recall is still paired over
  scenes, each height over its own LiDAR-detected vehicles: replicate b gives the difference of
  the two heights' resampled ratios. The trainings at two heights count as independent (Welch),
  which errs wide where a seed starts both from the same weights.

Reports of one group (model, height) and all models at one height must come from the same test
split (same scenes, same LiDAR-detected counts, same IoU and score thresholds, same bootstrap
settings); anything else is refused with an error naming the group and seed. A report's training
seed is read from its "train_seed" key when present (else the seeds are numbered by position).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from itertools import combinations

import numpy as np

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights
from detbench.eval.paper import paper_recall
from detbench.eval.report import check_report

METRICS: tuple[str, ...] = ("recall", "ap_r40")
METRIC_WORDS = {"recall": "Recall", "ap_r40": "AP@R40"}
CONFIDENCE = 0.95
# The paired lead's scene bootstrap: the replicates and seed of study_summary.paired_recall_difference,
# so one seed per model gives today's single-seed lead.
LEAD_REPLICATES = 2000
LEAD_SEED = 0
# What the summary ranks: recall of the LiDAR-detected vehicles in the large range (as
# detector_summary) and AP@R40 in the small range, both over all vehicles.
RECALL_CELL = ("large", "all")
AP_CELL = ("small", "all")


# --------------------------------------------------------------------------------------------
# Student's t quantile (plain math: scipy is not a dependency)
# --------------------------------------------------------------------------------------------

def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 500):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return h


def _betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta I_x(a, b) for x in [0, 1]."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def _t_cdf(t: float, df: float) -> float:
    tail = 0.5 * _betainc(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t >= 0 else tail


def student_t_quantile(p: float, df: float) -> float:
    """The p quantile of Student's t with df > 0 degrees of freedom (df need not be whole:
    Welch's df is not). E.g. t(0.975, 1) = 12.706, t(0.975, 2) = 4.303, t(0.975, 30) = 2.042."""
    p, df = float(p), float(df)
    if not 0.0 < p < 1.0:
        raise ValueError(f"quantile p must be in (0, 1), got {p}")
    if not df > 0.0 or not math.isfinite(df):
        raise ValueError(f"degrees of freedom must be a finite number > 0, got {df}")
    if p < 0.5:
        return -student_t_quantile(1.0 - p, df)
    lo, hi = 0.0, 1.0
    while _t_cdf(hi, df) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _t_cdf(mid, df) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * max(1.0, hi):
            break
    return 0.5 * (lo + hi)


# --------------------------------------------------------------------------------------------
# checks: one test split, one evaluation setting
# --------------------------------------------------------------------------------------------

def _settings(rep: dict) -> tuple:
    return (rep.get("iou_kind", "3d"), float(rep["iou_threshold"]), float(rep["score_threshold"]))


def _bootstrap_settings(rep: dict) -> tuple | None:
    unc = rep.get("uncertainty")
    if not unc:
        return None
    return (int(unc["num_clusters"]), int(unc["replicates"]), int(unc["seed"]), float(unc.get("confidence", 0.95)))


def _split_signature(rep: dict) -> dict:
    """What two reports on the same test split share: frames, ground truth per range and level,
    and (when bootstrapped) the scenes and their LiDAR-detected counts."""
    sig = {"split": rep.get("split"), "num_frames": int(rep["num_frames"]),
           "ground truth (total, LiDAR detected)": [
               (rep["results"][r][lv]["total"], rep["results"][r][lv]["lidar_detected"])
               for r in RANGE_NAMES for lv in LEVELS]}
    unc = rep.get("uncertainty")
    if unc:
        sig["scenes"] = list(unc["clusters"])
        sig["LiDAR-detected vehicles per scene"] = [
            list(unc["per_cluster"][r][lv]["lidar_detected"]) for r in RANGE_NAMES for lv in LEVELS]
    return sig


def _name(where: str, i: int, rep: dict) -> str:
    return f"{where} seed {_seed_label(rep, i)}"


def _seed_label(rep: dict, i: int):
    s = rep.get("train_seed")
    return s if s is not None else f"#{i + 1}"


def _check_same(reports: Sequence[dict], where: Sequence[str]) -> None:
    """Raise ValueError unless every report shares the first one's evaluation and test split."""
    ref, ref_where = reports[0], where[0]
    ref_set, ref_boot, ref_sig = _settings(ref), _bootstrap_settings(ref), _split_signature(ref)
    for rep, w in zip(reports[1:], where[1:]):
        if _settings(rep) != ref_set:
            raise ValueError(f"{w}: evaluated with (iou_kind, iou_threshold, score_threshold) = {_settings(rep)}, "
                             f"but {ref_where} with {ref_set}; evaluate every seed and model alike")
        boot = _bootstrap_settings(rep)
        if (boot is None) != (ref_boot is None):
            has, lacks = (w, ref_where) if boot else (ref_where, w)
            raise ValueError(f"{lacks}: no scene bootstrap ('uncertainty'), but {has} has one; evaluate every "
                             f"seed and model with the same --bootstrap")
        if boot is not None and boot != ref_boot:
            raise ValueError(f"{w}: scene bootstrap (scenes, replicates, seed, confidence) = {boot}, but "
                             f"{ref_where} has {ref_boot}; evaluate every seed and model with the same settings")
        sig = _split_signature(rep)
        for key, value in ref_sig.items():
            if sig.get(key) != value:
                raise ValueError(f"{w} and {ref_where} are not on the same test split: their {key} differ "
                                 f"({_short(sig.get(key))} vs {_short(value)}); evaluate every seed and model on "
                                 f"the same test split of the same data")


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


def _checked(reports: Sequence[dict], where: str) -> list[dict]:
    if isinstance(reports, Mapping) or not isinstance(reports, Sequence) or not reports:
        raise ValueError(f"{where}: give a non-empty list of eval reports, one per training seed")
    names = []
    for i, rep in enumerate(reports):
        check_report(rep, f"{where} report {i}")
        names.append(_name(where, i, rep))
    labels = [_seed_label(rep, i) for i, rep in enumerate(reports)]
    dup = sorted({str(s) for s in labels if labels.count(s) > 1})
    if dup:
        raise ValueError(f"{where}: training seed(s) {', '.join(dup)} appear more than once; give each seed's "
                         f"report once")
    _check_same(reports, names)
    return list(reports)


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
          confidence: float) -> dict:
    values = [rep["results"][r][lv][metric] for rep in reports]
    out = {"mean": None, "sd": None, "per_seed": [_r6(v) for v in values], "seed_t": None, "seed_half_width": None,
           "scene_ci95": None, "scene_method": None, "ci95": None}
    if any(v is None for v in values):
        return out  # nothing evaluated in this cell (the same for every seed: one test split)
    m = float(np.mean(np.asarray(values, dtype=np.float64)))
    sd, t, q = _seed_half_width(values, confidence)
    scene_ci = None
    if weights is not None:
        if metric == "recall":
            scene_ci = percentile_interval(bootstrap_ratios(weights, _mean_tp(reports, r, lv), _det(reports[0], r, lv)),
                                           confidence)
            out["scene_method"] = "paired scene bootstrap of the seed mean (the same draws for every seed)"
        else:
            cis = [((rep["uncertainty"].get("results") or {}).get(r, {}).get(lv) or {}).get("ap_r40_ci95")
                   for rep in reports]
            if all(cis):
                ends = np.mean(np.asarray(cis, dtype=np.float64), axis=0)
                scene_ci = [round(float(ends[0]), 6), round(float(ends[1]), 6)]
            out["scene_method"] = "mean of the seeds' scene-bootstrap interval ends (AP needs per-frame ranks)"
    out.update(mean=_r6(m), sd=_r6(sd), seed_t=_r6(t), seed_half_width=_r6(q), scene_ci95=scene_ci,
               ci95=_add_seed_term(m, scene_ci, q, (0.0, 1.0)))
    return out


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
    reports = _checked(reports, where)
    unc = reports[0].get("uncertainty")
    boot = _bootstrap_settings(reports[0])
    confidence = boot[3] if boot else CONFIDENCE
    weights = None
    if boot is not None and boot[0] >= 2 and boot[1] > 0:
        weights = scene_bootstrap_weights(boot[0], boot[1], boot[2])
    results = {r: {lv: {m: _cell(reports, r, lv, m, weights, confidence) for m in METRICS} for lv in LEVELS}
               for r in RANGE_NAMES}
    return {"num_seeds": len(reports), "seeds": [_seed_label(rep, i) for i, rep in enumerate(reports)],
            "num_scenes": None if unc is None else int(unc["num_clusters"]),
            "replicates": None if boot is None else boot[1], "confidence": confidence,
            "seed_spread_measured": len(reports) >= 2, "results": results}


# --------------------------------------------------------------------------------------------
# several models at one height: who leads, and is the lead resolved
# --------------------------------------------------------------------------------------------

def _welch(cell_a: dict, cell_b: dict, n_a: int, n_b: int, confidence: float) -> tuple[float | None, float | None]:
    """(t factor, half-width) of the seed term of mean_a - mean_b (module docstring)."""
    sa, sb = cell_a["sd"], cell_b["sd"]
    if sa is None and sb is None:
        return None, None
    da, db = cell_a.get("seed_df") or n_a - 1, cell_b.get("seed_df") or n_b - 1
    if sa is None:  # one seed of a: assume b's seed variance, the df b measured
        sa, df = sb, db
    elif sb is None:
        sb, df = sa, da
    elif cell_a.get("seed_pool") is not None and cell_a.get("seed_pool") == cell_b.get("seed_pool"):
        df = min(da, db)  # one pooled estimate on both sides (a model at two heights): its own df, not twice it
    else:
        va, vb = sa * sa / n_a, sb * sb / n_b
        df = (va + vb) ** 2 / (va * va / da + vb * vb / db) if va + vb > 0 else da + db
    var = sa * sa / n_a + sb * sb / n_b
    t = student_t_quantile(0.5 + confidence / 2.0, df)
    return t, t * math.sqrt(var)


def _scene_quadrature(diff: float, ca: dict, cb: dict) -> list | None:
    """Unpaired scene interval of mean_a - mean_b: the two scene intervals' sides in quadrature."""
    if not ca["scene_ci95"] or not cb["scene_ci95"]:
        return None
    a_lo, a_hi = ca["mean"] - ca["scene_ci95"][0], ca["scene_ci95"][1] - ca["mean"]
    b_lo, b_hi = cb["mean"] - cb["scene_ci95"][0], cb["scene_ci95"][1] - cb["mean"]
    return [round(diff - math.hypot(max(a_lo, 0.0), max(b_hi, 0.0)), 6),
            round(diff + math.hypot(max(a_hi, 0.0), max(b_lo, 0.0)), 6)]


def _lead(rep_a: Sequence[dict], rep_b: Sequence[dict], comb_a: dict, comb_b: dict, r: str, lv: str, metric: str,
          confidence: float) -> dict | None:
    """mean_a - mean_b in one cell with its scene term, seed term and combined interval. a and b are
    two models at one height (the same LiDAR-detected vehicles) or one model at two heights (the same
    test scenes, other LiDAR-detected vehicles)."""
    ca, cb = comb_a["results"][r][lv][metric], comb_b["results"][r][lv][metric]
    if ca["mean"] is None or cb["mean"] is None:
        return None
    diff = float(np.mean([x["results"][r][lv][metric] for x in rep_a])
                 - np.mean([x["results"][r][lv][metric] for x in rep_b]))
    ua, ub = rep_a[0].get("uncertainty"), rep_b[0].get("uncertainty")
    paired = bool(ua) and bool(ub) and list(ua["clusters"]) == list(ub["clusters"])
    scene_ci, method = None, None
    if metric == "recall" and paired:
        da, db = _det(rep_a[0], r, lv), _det(rep_b[0], r, lv)
        ta, tb = _mean_tp(rep_a, r, lv), _mean_tp(rep_b, r, lv)
        same_det = np.array_equal(da, db)
        # da.sum(), db.sum() > 0: both recall means exist
        diff = float((ta.sum() - tb.sum()) / da.sum()) if same_det else float(ta.sum() / da.sum() - tb.sum() / db.sum())
        if len(da) >= 2:
            w = scene_bootstrap_weights(len(da), LEAD_REPLICATES, LEAD_SEED)
            boot = (bootstrap_ratios(w, ta - tb, da) if same_det
                    else bootstrap_ratios(w, ta, da) - bootstrap_ratios(w, tb, db))
            scene_ci = percentile_interval(boot, confidence)
            method = "paired scene bootstrap (the same scenes for both and every seed)"
    else:
        scene_ci = _scene_quadrature(diff, ca, cb)
        if scene_ci is not None:
            why = "AP needs per-frame ranks" if metric == "ap_r40" else "the test scenes differ"
            method = f"the two scene intervals in quadrature (unpaired: {why}; errs wide)"
    t, q = _welch(ca, cb, comb_a["num_seeds"], comb_b["num_seeds"], confidence)
    ci = _add_seed_term(diff, scene_ci, q, (-1.0, 1.0))
    ahead = bool(ci) and (ci[0] > 0 or ci[1] < 0)
    return {"diff": _r6(diff), "scene_ci95": scene_ci, "scene_method": method, "seed_t": _r6(t),
            "seed_half_width": _r6(q), "ci95": ci, "ahead": ahead,
            "verdict": "ahead" if ahead else ("not resolved" if ci else "no interval")}


def pool_seed_spread(combined: Mapping[tuple[str, float], dict]) -> None:
    """Pool each model's seed variance over its heights, in place (module docstring).

    combined: {(model, height): seed_combined(...)}. For every model, range, level and metric whose
    groups measured a spread (2 or more seeds), each cell of that model gets sd = the pooled s_p,
    "sd_own" (its own s, None for one seed), "seed_df" (the pooled df), "seed_pool" (the model),
    "seed_t" = t(df), "seed_half_width" = t * s_p / sqrt(n) and "ci95" recombined with its scene
    interval. A model with one height, or with one seed everywhere, is left as it is."""
    by_model: dict[str, list[dict]] = {}
    for (model, _), comb in combined.items():
        by_model.setdefault(str(model), []).append(comb)
    for model, combs in by_model.items():
        if len(combs) < 2:
            continue
        pooled = False
        for r in RANGE_NAMES:
            for lv in LEVELS:
                for metric in METRICS:
                    cells = [(c["results"][r][lv][metric], c["num_seeds"], c["confidence"]) for c in combs]
                    measured = [(cell, n) for cell, n, _ in cells if cell["sd"] is not None and n >= 2]
                    df = sum(n - 1 for _, n in measured)
                    if df < 1 or len(measured) < 2:
                        continue
                    sd = math.sqrt(sum((n - 1) * cell["sd"] ** 2 for cell, n in measured) / df)
                    pooled = True
                    for cell, n, confidence in cells:
                        if cell["mean"] is None:
                            continue
                        t = student_t_quantile(0.5 + confidence / 2.0, df)
                        q = t * sd / math.sqrt(n)
                        cell.update(sd_own=cell["sd"], sd=_r6(sd), seed_df=df, seed_pool=model, seed_t=_r6(t),
                                    seed_half_width=_r6(q),
                                    ci95=_add_seed_term(cell["mean"], cell["scene_ci95"], q, (0.0, 1.0)))
        for c in combs:
            c["seed_spread_pooled_over_heights"] = pooled


def _combined_groups(groups: Mapping, pool: bool) -> dict[float, dict[str, tuple[list[dict], dict]]]:
    """{height: {model: (reports, seed_combined)}} with the seed spread pooled over heights when `pool`."""
    by_height = _groups(groups)
    out = {h: {m: (reps, seed_combined(reps, f"{m} at {h:g} m")) for m, reps in models.items()}
           for h, models in by_height.items()}
    if pool:
        pool_seed_spread({(m, h): comb for h, models in out.items() for m, (_, comb) in models.items()})
    return out


def _groups(groups: Mapping) -> dict[float, dict[str, list[dict]]]:
    if not isinstance(groups, Mapping) or not groups:
        raise ValueError("groups: give a non-empty dict {(model, height): [report of each training seed]}")
    by_height: dict[float, dict[str, list[dict]]] = {}
    first = None
    for key, reports in groups.items():
        try:
            model, height = key
            model, height = str(model), float(height)
        except (TypeError, ValueError):
            raise ValueError(f"groups: key {key!r} must be a (model, height in metres) pair") from None
        where = f"{model} at {height:g} m"
        reports = _checked(reports, where)
        for i, rep in enumerate(reports):
            if rep.get("model") is not None and str(rep["model"]) != model:
                raise ValueError(f"{_name(where, i, rep)}: the report is of model {rep['model']!r}, not {model!r}; "
                                 f"group each model's reports under its own name")
            if rep.get("height") is not None and abs(float(rep["height"]) - height) > 1e-9:
                raise ValueError(f"{_name(where, i, rep)}: the report is at height {float(rep['height']):g} m, not "
                                 f"{height:g} m; group each height's reports under its own height")
        if first is None:
            first = (where, _settings(reports[0]))
        elif _settings(reports[0]) != first[1]:
            raise ValueError(f"{where}: evaluated with (iou_kind, iou_threshold, score_threshold) = "
                             f"{_settings(reports[0])}, but {first[0]} with {first[1]}; evaluate every model and "
                             f"height alike")
        if model in by_height.setdefault(height, {}):
            raise ValueError(f"groups: {where} is given twice; give each (model, height) once")
        by_height[height][model] = reports
    for h, models in by_height.items():
        names = list(models)
        firsts = [models[m][0] for m in names]
        _check_same(firsts, [_name(f"{m} at {h:g} m", 0, models[m][0]) for m in names])
    return dict(sorted(by_height.items()))


def _leader(name: str, items: dict, cell: tuple[str, str], metric: str, other: str) -> dict:
    """Ranking of `items` ({key: (reports, seed_combined)}) by the seed mean of `metric` in `cell` (ties:
    `other`), with the lead of the first over the second."""
    r, lv = cell

    def mean(k, m):
        return items[k][1]["results"][r][lv][m]["mean"]

    ranked = sorted((k for k in items if mean(k, metric) is not None),
                    key=lambda k: (-mean(k, metric), -(mean(k, other) or 0.0)))
    entry = {"range": r, "level": lv,
             "ranking": [{name: k, "mean": mean(k, metric), "ci95": items[k][1]["results"][r][lv][metric]["ci95"],
                          "num_seeds": items[k][1]["num_seeds"]} for k in ranked],
             "best": ranked[0] if ranked else None, "runner_up": ranked[1] if len(ranked) > 1 else None, "lead": None}
    if len(ranked) > 1:
        (ra, ca), (rb, cb) = items[ranked[0]], items[ranked[1]]
        entry["lead"] = _lead(ra, rb, ca, cb, r, lv, metric, ca["confidence"])
    return entry


WHAT = (("recall", RECALL_CELL, "ap_r40"), ("ap_r40", AP_CELL, "recall"))


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
    model's seed spread pooled over its heights (`pool_seed_spread`).
    """
    out = {}
    for h, items in _combined_groups(groups, pool).items():
        out[h] = {"models": {m: c for m, (_, c) in items.items()},
                  **{metric: _leader("model", items, cell, metric, other) for metric, cell, other in WHAT}}
    return out


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
    by_model: dict[str, dict[float, tuple]] = {}
    for h, items in _combined_groups(groups, pool).items():
        for m, pair in items.items():
            by_model.setdefault(m, {})[h] = pair
    return {m: {metric: _leader("height", items, cell, metric, other) for metric, cell, other in WHAT}
            for m, items in by_model.items() if len(items) > 1}


def pairwise_leads(groups: Mapping, pool: bool = True) -> dict:
    """Every pair of models at each height, in every range, for recall and AP@R40 (All vehicles).

    groups as in `seed_summary`. Returns {height: {range: {metric: {"ranking": [{"model", "mean",
    "ci95", "num_seeds"}] (by seed mean, best first), "pairs": [{"model", "over", **lead}]}}}}: one entry per pair,
    the better-ranked model first, with lead as in `seed_summary` ("diff", "ci95", "ahead", "verdict",
    ...). A pair counts as resolved ("ahead") only where the 95 % interval of the lead, scenes and both
    models' seed spread together, excludes 0. Fractions in [0, 1], leads in [-1, 1]."""
    out: dict[float, dict] = {}
    for h, items in _combined_groups(groups, pool).items():
        by_range: dict[str, dict] = {}
        for r in RANGE_NAMES:
            for metric in METRICS:
                # ranked as `seed_summary` ranks (ties broken on the other metric)
                ranking = _leader("model", items, (r, "all"), metric,
                                  "ap_r40" if metric == "recall" else "recall")["ranking"]
                pairs = []
                for a, b in combinations([e["model"] for e in ranking], 2):
                    lead = _lead(items[a][0], items[b][0], items[a][1], items[b][1], r, "all", metric,
                                 items[a][1]["confidence"])
                    if lead is not None:
                        pairs.append({"model": a, "over": b, **lead})
                by_range.setdefault(r, {})[metric] = {"ranking": ranking, "pairs": pairs}
        out[h] = by_range
    return out


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
                lines.append(f"| {h:g} m | {r} | {METRIC_WORDS[metric]} | {ranking} | {resolved} |")
    return lines


def detector_table(groups: Mapping, train_minutes: Mapping | None = None, pool: bool = True) -> list[str]:
    """The one-table answer to "which detector": per model and height the seed mean of AP@R40 (small range)
    and of recall (small with its interval, moderate, large), All vehicles, with intervals over test scenes
    and seeds; the recall of the Top3 and Top6 vehicles of the large range (the importance levels); the
    paper's Table VII recall for the same cells and the mean training minutes.

    groups as in `seed_summary`; train_minutes: {(model, height): minutes per training} or None."""
    lines = ["| Detector | Height | Seeds | AP@R40 small [95 %] | Recall small [95 %] / moderate / large | "
             "Recall large, Top3 / Top6 | The paper's recall (Table VII) | Training min |",
             "|---|---|---:|---|---|---|---|---:|"]
    by_model: dict[str, list[tuple[float, dict]]] = {}
    for h, items in _combined_groups(groups, pool).items():
        for m, (_, comb) in items.items():
            by_model.setdefault(m, []).append((h, comb))
    for m, cells in by_model.items():
        for h, comb in sorted(cells, key=lambda x: x[0]):
            res = comb["results"]
            ap, rs = res["small"]["all"]["ap_r40"], res["small"]["all"]["recall"]
            paper = paper_recall(m, h)
            minutes = (train_minutes or {}).get((m, h))
            lines.append(
                f"| {m} | {h:g} m | {comb['num_seeds']} | {_with_ci(ap)} | "
                f"{_with_ci(rs)} / {_f(res['moderate']['all']['recall']['mean'], 2)} / "
                f"{_f(res['large']['all']['recall']['mean'], 2)} | "
                f"{_f(res['large']['top3']['recall']['mean'], 2)} / {_f(res['large']['top6']['recall']['mean'], 2)} | "
                f"{' / '.join(f'{v:.2f}' for v in paper) if paper else '-'} | "
                f"{'-' if minutes is None else f'{minutes:.1f}'} |")
    return lines


# --------------------------------------------------------------------------------------------
# Markdown for study.md
# --------------------------------------------------------------------------------------------

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
        return f"{e[key]:g} m" if key == "height" else str(e[key])

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


def seed_markdown(groups: Mapping, pool: bool = True) -> list[str]:
    """Markdown lines for study.md: per height a table of every model's seed mean per range (All
    vehicles) for recall and AP@R40 with the interval of scenes and seeds, the seed spread and the
    scene-only interval beside it, then the sentences of `seed_summary` and, for models tested at
    two or more heights, of `seed_height_summary`."""
    summary = seed_summary(groups, pool)
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
        lines += [f"**{h:g} m**", "",
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
            lines.append(_lead_sentence(f"At {h:g} m", "model", metric, cell[metric]))
        lines.append("")
    by_model = seed_height_summary(groups, pool)
    if by_model:
        lines += ["**Heights, per model**", ""]
        for m, cell in by_model.items():
            lines += [_lead_sentence(f"For {m}", "height", metric, cell[metric]) for metric in METRICS]
        lines.append("")
    lines.append("A model (or height) is called ahead only where the 95 % interval of its lead excludes 0: the "
                 "scene term (paired over the same test scenes for recall; for AP@R40 the two scene intervals in "
                 "quadrature) plus both sides' seed spread with a Student-t factor.")
    return lines


__all__ = ["seed_combined", "pool_seed_spread", "seed_summary", "seed_height_summary", "seed_markdown",
           "pairwise_leads", "pairwise_markdown", "detector_table",
           "student_t_quantile", "METRICS",
           "CONFIDENCE", "LEAD_REPLICATES", "LEAD_SEED", "RECALL_CELL", "AP_CELL"]
