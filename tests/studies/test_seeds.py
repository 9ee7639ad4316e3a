"""Figures over several training seeds: the seed mean, its interval over test scenes and seeds, the leads.

The reports come from the real evaluator (`detbench.eval.evaluate` with a scene bootstrap) on small
hand-built frames: each "seed" of a "model" finds a random share of the vehicles, so seeds differ as
trainings do while the test split stays the same.
"""
from __future__ import annotations

import copy
import functools
import math
from itertools import combinations

import numpy as np
import pytest

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.evaluate import EvalFrame, evaluate
from detbench.studies.seed_markdown import detector_table, pairwise_markdown, seed_markdown
from detbench.studies.seeds import (
    LEAD_REPLICATES, METRICS, pairwise_leads, pool_seed_spread, seed_combined, seed_height_pairs, seed_height_summary,
    seed_statistics, seed_summary,
)
from detbench.studies.student_t import student_t_quantile
from detbench.studies.study_summary import paired_recall_difference

REPLICATES = 200
# Vehicles of every frame: (x, y, lane); the large range holds all, the small range the first three.
VEHICLES = ((9.0, 0.0, 0), (21.0, 3.5, 1), (34.0, -3.5, -1), (62.0, 0.0, 0), (80.0, 3.5, 1), (110.0, -7.0, -2))
SIZE = (4.5, 1.8, 1.5)


def _box(x: float, y: float) -> list[float]:
    return [x, y, SIZE[2] / 2, *SIZE, 0.0]


@functools.cache
def _report(model: str, skill: float, seed: int, scenes: tuple[str, ...] = tuple(f"s{i}" for i in range(8)),
            height: float = 1.8, hidden: tuple[int, ...] = (), hard: float = 0.0) -> dict:
    """One seed's eval report: each vehicle found with probability `skill` (score in [0.3, 1)), one
    false positive per frame (score in [0.1, 0.6)); 3 frames per scene. The vehicles numbered in
    `hidden` get no LiDAR point (as from a lower mounting height). Every second scene is hard: `skill - hard`
    there (for every model alike, so the models' figures move together over scenes)."""
    rng = np.random.default_rng([int(skill * 1000), seed])
    frames = []
    for i, scene in enumerate(scenes):
        for k in range(3):
            gt = np.array([_box(x, y) for x, y, _ in VEHICLES])
            found = rng.random(len(VEHICLES)) < skill - (hard if i % 2 else 0.0)
            pred = [_box(x, y) for (x, y, _), f in zip(VEHICLES, found) if f] + [_box(45.0, 0.0)]
            scores = np.concatenate([rng.uniform(0.3, 1.0, int(found.sum())), rng.uniform(0.1, 0.6, 1)])
            points = np.array([0 if i in hidden else 20 for i in range(len(VEHICLES))])
            frames.append(EvalFrame(gt, points, np.array([v[2] for v in VEHICLES]),
                                    np.array(pred), scores, frame_id=f"{scene}_{k}", scene_id=scene))
    rep = evaluate(frames, bootstrap=REPLICATES, bootstrap_seed=0)
    rep.update(model=model, height=height, split="test", train_seed=seed)
    return rep


def _seeds(model: str, skills, seeds=None, **kw) -> list[dict]:
    seeds = range(len(skills)) if seeds is None else seeds
    return [copy.deepcopy(_report(model, s, k, **kw)) for s, k in zip(skills, seeds)]


def _width(ci) -> float:
    return ci[1] - ci[0]


def test_student_t_quantiles_match_the_tables():
    for df, t in ((1, 12.7062), (2, 4.3027), (3, 3.1824), (4, 2.7764), (10, 2.2281), (30, 2.0423)):
        assert abs(student_t_quantile(0.975, df) - t) < 1e-4, df
    assert abs(student_t_quantile(0.975, 1e8) - 1.95996) < 1e-4
    assert abs(student_t_quantile(0.025, 3) + 3.1824) < 1e-4
    assert 3.1824 < student_t_quantile(0.975, 2.5) < 4.3027  # Welch's df need not be whole
    with pytest.raises(ValueError, match="degrees of freedom"):
        student_t_quantile(0.975, 0)


def test_one_seed_reproduces_the_single_seed_report_exactly():
    rep = _report("second", 0.7, 0)
    comb = seed_combined([rep])
    assert comb["num_seeds"] == 1 and comb["seeds"] == [0] and not comb["seed_spread_measured"]
    for r in RANGE_NAMES:
        for lv in LEVELS:
            for m in METRICS:
                c = comb["results"][r][lv][m]
                single = rep["uncertainty"]["results"][r][lv][f"{m}_ci95"]
                assert single is not None
                assert c["mean"] == round(rep["results"][r][lv][m], 6), (r, lv, m)
                assert c["scene_ci95"] == single and c["ci95"] == single, (r, lv, m, c, single)
                assert c["sd"] is None and c["seed_half_width"] is None


def test_one_seed_per_model_gives_the_single_seed_paired_lead():
    a, b = _report("second", 0.8, 0), _report("pillarnet", 0.5, 0)
    s = seed_summary({("second", 1.8): [a], ("pillarnet", 1.8): [b]})[1.8]["recall"]
    today = paired_recall_difference(a, b, "large", "all", replicates=LEAD_REPLICATES)
    assert s["best"] == "second" and s["runner_up"] == "pillarnet"
    assert s["lead"]["diff"] == today["diff"] and s["lead"]["ci95"] == today["ci95"]
    assert s["lead"]["seed_half_width"] is None


def test_identical_seeds_have_no_spread_and_keep_the_single_seed_interval():
    rep = _report("second", 0.7, 0)
    twin = copy.deepcopy(rep)
    twin["train_seed"] = 1
    comb = seed_combined([rep, twin])
    for r in RANGE_NAMES:
        for m in METRICS:
            c = comb["results"][r]["all"][m]
            assert c["sd"] == 0.0 and c["seed_half_width"] == 0.0
            assert abs(c["seed_t"] - 12.706205) < 1e-6  # two seeds: t with 1 degree of freedom
            assert c["ci95"] == rep["uncertainty"]["results"][r]["all"][f"{m}_ci95"], (r, m)


def test_seeds_that_differ_widen_the_interval_around_their_mean():
    reps = _seeds("second", (0.55, 0.7, 0.85))
    comb = seed_combined(reps)
    assert comb["seeds"] == [0, 1, 2] and comb["num_scenes"] == 8
    for r in RANGE_NAMES:
        for m in METRICS:
            c = comb["results"][r]["all"][m]
            values = [rep["results"][r]["all"][m] for rep in reps]
            assert c["per_seed"] == [round(v, 6) for v in values]
            assert abs(c["mean"] - np.mean(values)) < 1e-6
            assert abs(c["sd"] - np.std(values, ddof=1)) < 1e-6 and c["sd"] > 0.02, (r, m, values)
            assert abs(c["seed_half_width"] - student_t_quantile(0.975, 2) * c["sd"] / math.sqrt(3)) < 1e-5
            lo, hi = c["ci95"]
            assert lo <= c["mean"] <= hi
            assert lo <= c["scene_ci95"][0] and hi >= c["scene_ci95"][1]
            assert _width(c["ci95"]) > _width(c["scene_ci95"]) + 0.01, (r, m, c)
            # the seed term is at least as wide as the seed half-width alone on each unclipped side
            if hi < 1.0:
                assert hi - c["mean"] >= c["seed_half_width"] - 1e-6
            assert 0.0 <= lo and hi <= 1.0


def test_the_scene_interval_of_the_mean_is_the_paired_bootstrap_for_recall_and_mean_ends_for_ap():
    reps = _seeds("second", (0.5, 0.9))
    c = seed_combined(reps)["results"]["large"]["all"]
    single = [rep["uncertainty"]["results"]["large"]["all"] for rep in reps]
    ap_ends = np.mean([s["ap_r40_ci95"] for s in single], axis=0)
    assert c["ap_r40"]["scene_ci95"] == [round(float(ap_ends[0]), 6), round(float(ap_ends[1]), 6)]
    rec = c["recall"]["scene_ci95"]
    assert min(s["recall_ci95"][0] for s in single) < rec[0] and rec[1] < max(s["recall_ci95"][1] for s in single)
    assert rec[0] <= c["recall"]["mean"] <= rec[1]

    # the mean of the ends, used for AP@R40, errs wide: for recall, where both exist, it is never the narrower
    reps = _seeds("second", (0.55, 0.7, 0.85))
    comb = seed_combined(reps)
    for r in RANGE_NAMES:
        for lv in LEVELS:
            paired = comb["results"][r][lv]["recall"]["scene_ci95"]
            ends = np.mean([rep["uncertainty"]["results"][r][lv]["recall_ci95"] for rep in reps], axis=0)
            assert _width(paired) <= ends[1] - ends[0] + 1e-9, (r, lv, paired, ends)


def test_a_clear_lead_is_ahead():
    groups = {("second", 1.8): _seeds("second", (0.9, 0.88, 0.92)),
              ("pointpillar", 1.8): _seeds("pointpillar", (0.3, 0.32, 0.28))}
    s = seed_summary(groups)[1.8]
    for metric in METRICS:
        lead = s[metric]["lead"]
        assert s[metric]["best"] == "second", metric
        assert lead["verdict"] == "ahead" and lead["ahead"] and lead["ci95"][0] > 0, (metric, lead)
        assert lead["ci95"][0] <= lead["diff"] <= lead["ci95"][1]
        assert lead["seed_half_width"] > 0


def test_a_lead_within_the_seed_spread_is_not_resolved_though_one_seed_would_call_it():
    a = _seeds("second", (0.9, 0.45))
    b = _seeds("pillarnet", (0.5, 0.55))
    one = seed_summary({("second", 1.8): a[:1], ("pillarnet", 1.8): b[:1]})[1.8]["recall"]
    assert one["best"] == "second" and one["lead"]["verdict"] == "ahead", one["lead"]
    two = seed_summary({("second", 1.8): a, ("pillarnet", 1.8): b})[1.8]["recall"]
    lead = two["lead"]
    assert two["best"] == "second" and lead["diff"] > 0
    assert lead["scene_ci95"][0] > 0, "the scene term alone resolves it: the seeds are what does not"
    assert lead["verdict"] == "not resolved" and not lead["ahead"] and lead["ci95"][0] < 0 < lead["ci95"][1]
    text = "\n".join(seed_markdown({("second", 1.8): a, ("pillarnet", 1.8): b}))
    assert "not resolved" in text and "is ahead" not in text.split("Recall (large range")[1].split("\n")[0]


def test_a_model_with_one_seed_borrows_the_others_seed_spread():
    a = _seeds("second", (0.9, 0.45))
    b = _seeds("pillarnet", (0.5,))
    lead = seed_summary({("second", 1.8): a, ("pillarnet", 1.8): b})[1.8]["recall"]["lead"]
    sd = seed_combined(a)["results"]["large"]["all"]["recall"]["sd"]
    assert abs(lead["seed_half_width"] - student_t_quantile(0.975, 1) * sd * math.sqrt(1 / 2 + 1 / 1)) < 1e-5


def test_the_best_height_of_a_model_is_ahead_only_when_its_paired_lead_excludes_zero():
    low = dict(height=0.5, hidden=(3, 5))  # fewer LiDAR-detected vehicles at the low height
    groups = {("second", 1.8): _seeds("second", (0.9, 0.88, 0.92)),
              ("second", 0.5): _seeds("second", (0.5, 0.52, 0.48), **low),
              ("pillarnet", 1.8): _seeds("pillarnet", (0.6, 0.9)),
              ("pillarnet", 0.5): _seeds("pillarnet", (0.55, 0.85), **low)}
    s = seed_height_summary(groups)
    lead = s["second"]["recall"]["lead"]
    assert s["second"]["recall"]["best"] == 1.8 and s["second"]["recall"]["runner_up"] == 0.5
    assert lead["verdict"] == "ahead" and lead["ci95"][0] > 0 and lead["scene_method"].startswith("paired")
    means = {h: np.mean([rep["results"]["large"]["all"]["recall"] for rep in groups[("second", h)]])
             for h in (1.8, 0.5)}
    assert abs(lead["diff"] - (means[1.8] - means[0.5])) < 1e-6
    assert s["pillarnet"]["recall"]["lead"]["verdict"] == "not resolved"
    text = "\n".join(seed_markdown(groups))
    assert "**Heights, per model**" in text and "For second, Recall (large range, All vehicles): 1.8 m" in text
    assert "**1.8 m is ahead**" in text.split("For second, Recall")[1].split("\n")[0]
    assert "not resolved" in text.split("For pillarnet, Recall")[1].split("\n")[0]


def test_reports_on_different_test_splits_are_refused():
    a = _report("second", 0.7, 0)
    other = copy.deepcopy(_report("second", 0.7, 1, scenes=tuple(f"s{i}" for i in range(1, 9))))
    with pytest.raises(ValueError, match="not on the same test split: their scenes differ"):
        seed_combined([a, other])
    with pytest.raises(ValueError, match="pillarnet at 1.8 m seed 1 .* not on the same test split"):
        seed_summary({("second", 1.8): [a], ("pillarnet", 1.8): [dict(copy.deepcopy(other), model="pillarnet")]})
    fewer = copy.deepcopy(a)
    fewer["train_seed"] = 1
    fewer["num_frames"] -= 1
    with pytest.raises(ValueError, match="num_frames differ"):
        seed_combined([a, fewer])


def test_mixed_up_groups_are_refused_with_the_fix():
    a, b = _report("second", 0.7, 0), _report("second", 0.7, 1)
    with pytest.raises(ValueError, match="seed\\(s\\) 0 appear more than once"):
        seed_combined([a, a])
    with pytest.raises(ValueError, match="is of model 'second', not 'pillarnet'"):
        seed_summary({("pillarnet", 1.8): [a, b]})
    with pytest.raises(ValueError, match="at height 1.8 m, not 1 m"):
        seed_summary({("second", 1.0): [a, b]})
    unboot = {k: v for k, v in copy.deepcopy(b).items() if k != "uncertainty"}
    with pytest.raises(ValueError, match="no scene bootstrap"):
        seed_combined([a, unboot])
    with pytest.raises(ValueError, match="non-empty list"):
        seed_combined([])


def test_markdown_names_every_model_height_and_seed_with_units():
    groups = {}
    for h in (1.0, 1.8):
        groups[("second", h)] = _seeds("second", (0.8, 0.75), seeds=(0, 1), height=h)
        groups[("pillarnet", h)] = _seeds("pillarnet", (0.6, 0.65), seeds=(0, 1), height=h)
        groups[("ct3d", h)] = _seeds("ct3d", (0.4, 0.45), seeds=(0, 1), height=h)
    lines = seed_markdown(groups)
    text = "\n".join(lines)
    assert "Training seeds: 0, 1" in text and "fractions in [0, 1]" in text
    for h in ("1 m", "1.8 m"):
        assert f"**{h}**" in text and f"At {h}, Recall (large range" in text and f"At {h}, AP@R40 (small range" in text
    rows = [ln for ln in lines if ln.startswith("| ") and not ln.startswith(("| Model", "| Metric", "| Recall large",
                                                                                "| AP@R40 small"))]
    assert len(rows) == 2 * 3 * 3  # heights x models x ranges
    for m in ("second", "pillarnet", "ct3d"):
        assert sum(ln.startswith(f"| {m} | 0, 1 |") for ln in rows) == 6, m
    # each row shows the mean [interval], the seed sd / half-width and the scene-only interval
    assert all(ln.count("[") == 4 and ln.count("+-") == 2 for ln in rows), rows[0]


def test_markdown_of_one_seed_says_the_spread_is_not_measured():
    text = "\n".join(seed_markdown({("second", 1.8): [_report("second", 0.8, 0)],
                                    ("pillarnet", 1.8): [_report("pillarnet", 0.5, 0)]}))
    assert "seed spread is not measured" in text and "one seed each" in text
    # several heights with one seed each: nothing to pool, and the text does not claim it
    text = "\n".join(seed_markdown({("second", 1.8): [_report("second", 0.8, 0)],
                                    ("second", 0.5): [_report("second", 0.6, 0, height=0.5, hidden=(3, 5))]}))
    assert "seed spread is not measured" in text and "pooled over each model's heights" not in text


def _count_report(tp: np.ndarray, det: np.ndarray, seed: int, replicates: int = 400) -> dict:
    """A report as evaluate() lays it out, from per-scene TP and LiDAR-detected counts (recall only;
    AP@R40 set equal to recall)."""
    from detbench.eval.bootstrap import bootstrap_ratios, percentile_interval, scene_bootstrap_weights

    ci = percentile_interval(bootstrap_ratios(scene_bootstrap_weights(len(det), replicates, 0), tp, det))
    t, d = int(tp.sum()), int(det.sum())
    cell = {"total": d, "lidar_detected": d, "ldr": 1.0, "tp": t, "fp": 0, "recall": t / d, "ap_r40": t / d}
    return {"iou_threshold": 0.7, "iou_kind": "3d", "score_threshold": 0.1, "num_frames": len(det), "split": "test",
            "train_seed": seed, "results": {r: {lv: dict(cell) for lv in LEVELS} for r in RANGE_NAMES},
            "uncertainty": {"num_clusters": len(det), "replicates": replicates, "seed": 0, "confidence": 0.95,
                            "clusters": [f"s{i}" for i in range(len(det))],
                            "per_cluster": {r: {lv: {"tp": tp.tolist(), "lidar_detected": det.tolist()}
                                                for lv in LEVELS} for r in RANGE_NAMES},
                            "results": {r: {lv: {"recall_ci95": ci, "ap_r40_ci95": ci} for lv in LEVELS}
                                        for r in RANGE_NAMES}}}


def test_the_interval_covers_the_expected_recall_over_scenes_and_seeds_where_one_seed_does_not():
    """Simulated studies: 10 test scenes drawn from a population (scene recall 0.7 +- 0.08), each
    seed's training shifts recall by N(0, 0.05), every vehicle found at random. The 95 % interval of
    3 seeds covers the population's expected recall in >= 93 % of the studies; a single seed's scene
    bootstrap, blind to the seed spread, in far fewer."""
    rng = np.random.default_rng(7)
    truth = float(np.clip(0.7 + rng.normal(0, 0.08, 200_000) + rng.normal(0, 0.05, 200_000), 0, 1).mean())
    trials, hit3, hit1 = 150, 0, 0
    for _ in range(trials):
        det = rng.poisson(20, 10) + 1
        scene = rng.normal(0, 0.08, 10)
        reps = [_count_report(rng.binomial(det, np.clip(0.7 + scene + rng.normal(0, 0.05), 0, 1)), det, s)
                for s in range(3)]
        ci3 = seed_combined(reps)["results"]["large"]["all"]["recall"]["ci95"]
        ci1 = seed_combined(reps[:1])["results"]["large"]["all"]["recall"]["ci95"]
        hit3 += ci3[0] <= truth <= ci3[1]
        hit1 += ci1[0] <= truth <= ci1[1]
    assert hit3 / trials >= 0.93, (hit3, hit1, trials)
    assert hit1 / trials <= 0.85, (hit3, hit1, trials)


def test_without_a_scene_bootstrap_there_is_no_interval_and_no_model_is_called_ahead():
    def bare(rep):
        return {k: v for k, v in copy.deepcopy(rep).items() if k != "uncertainty"}

    a = [bare(r) for r in _seeds("second", (0.9, 0.88))]
    b = [bare(r) for r in _seeds("pillarnet", (0.3, 0.32))]
    c = seed_combined(a)["results"]["large"]["all"]["recall"]
    assert c["sd"] > 0 and c["scene_ci95"] is None and c["ci95"] is None
    lead = seed_summary({("second", 1.8): a, ("pillarnet", 1.8): b})[1.8]["recall"]["lead"]
    assert lead["diff"] > 0.4 and lead["verdict"] == "no interval" and not lead["ahead"]
    assert "no interval (evaluate with --bootstrap)" in "\n".join(seed_markdown({("second", 1.8): a,
                                                                                ("pillarnet", 1.8): b}))


def test_the_seed_spread_is_pooled_over_a_models_heights():
    """Two seeds at three heights: each cell carries the model's pooled sd with df 3 (t 3.18, not 12.71),
    keeps its own sd beside it, and its interval is the scene interval and the pooled seed term together."""
    low, mid = dict(height=0.5, hidden=(3, 5)), dict(height=1.0, hidden=(5,))
    groups = {("second", 1.8): _seeds("second", (0.9, 0.8)), ("second", 1.0): _seeds("second", (0.7, 0.72), **mid),
              ("second", 0.5): _seeds("second", (0.5, 0.6), **low)}
    own = {h: seed_combined(groups[("second", h)]) for h in (1.8, 1.0, 0.5)}
    before = copy.deepcopy(own)
    pooled = {h: c for (_, h), c in pool_seed_spread({("second", h): c for h, c in own.items()}).items()}
    assert own == before  # the cells it pooled are left as they are
    for r in RANGE_NAMES:
        for metric in METRICS:
            sds = [own[h]["results"][r]["all"][metric]["sd"] for h in own]
            sp = math.sqrt(sum(v * v for v in sds) / 3)  # equal n: the mean of the variances
            t3 = student_t_quantile(0.975, 3)
            for h in own:
                c, o = pooled[h]["results"][r]["all"][metric], own[h]["results"][r]["all"][metric]
                assert c["seed_df"] == 3 and c["seed_pool"] == "second" and abs(c["seed_t"] - t3) < 1e-5
                assert abs(c["sd"] - sp) < 1e-5 and c["sd_own"] == o["sd"] and c["mean"] == o["mean"]
                assert abs(c["seed_half_width"] - t3 * sp / math.sqrt(2)) < 1e-5
                m, (lo, hi) = c["mean"], c["scene_ci95"]
                q = c["seed_half_width"]
                assert abs(c["ci95"][0] - max(0.0, m - math.hypot(m - lo, q))) < 2e-6
                assert abs(c["ci95"][1] - min(1.0, m + math.hypot(hi - m, q))) < 2e-6
    # the summaries pool by default; pool=False keeps each cell's own two-seed spread (t = 12.71)
    on = seed_summary(groups)[1.8]["models"]["second"]["results"]["small"]["all"]["recall"]
    off = seed_summary(groups, pool=False)[1.8]["models"]["second"]["results"]["small"]["all"]["recall"]
    assert on["seed_df"] == 3 and "seed_df" not in off and abs(off["seed_t"] - 12.7062) < 1e-3
    assert _width(on["ci95"]) < _width(off["ci95"])
    # a height lead of one model uses its one pooled estimate: df 3, counted once
    lead = seed_height_summary(groups)["second"]["recall"]["lead"]
    assert abs(lead["seed_t"] - student_t_quantile(0.975, 3)) < 1e-5
    assert "pooled over each model's heights" in "\n".join(seed_markdown(groups))
    # one height only: nothing to pool
    single = seed_summary({("second", 1.8): groups[("second", 1.8)]})[1.8]["models"]["second"]
    assert "seed_df" not in single["results"]["small"]["all"]["recall"]


def test_every_pair_is_compared_and_only_the_resolved_leads_are_listed():
    """Three models: two clearly ahead of the third, and within each other's seed spread."""
    groups = {("second", 1.8): _seeds("second", (0.8, 0.7, 0.75)),
              ("ct3d", 1.8): _seeds("ct3d", (0.72, 0.78, 0.76)),
              ("pillarnet", 1.8): _seeds("pillarnet", (0.2, 0.22, 0.21))}
    leads = pairwise_leads(groups)[1.8]
    for r in RANGE_NAMES:
        for metric in METRICS:
            entry = leads[r][metric]
            assert [e["model"] for e in entry["ranking"]][-1] == "pillarnet", (r, metric)
            assert len(entry["pairs"]) == 3  # every pair once, the better-ranked model first
            for p in entry["pairs"]:
                assert p["diff"] >= 0 and p["ahead"] == (p["ci95"][0] > 0), p
            by_pair = {(p["model"], p["over"]): p for p in entry["pairs"]}
            assert by_pair[(entry["ranking"][0]["model"], "pillarnet")]["ahead"], (r, metric)
            top_two = [e["model"] for e in entry["ranking"][:2]]
            assert not by_pair[tuple(top_two)]["ahead"], (r, metric, "within the seed spread")
    text = "\n".join(pairwise_markdown(pairwise_leads(groups)))
    assert "| 1.8 m | large | Recall |" in text and " over pillarnet +0." in text
    assert "second over ct3d" not in text and "ct3d over second" not in text


def test_the_detector_table_sets_the_papers_table_vii_beside_each_cell():
    groups = {("second", h): _seeds("second", (0.8, 0.7), height=h, hidden=hidden)
              for h, hidden in ((0.5, (3, 5)), (1.8, ()))}
    groups[("mymodel", 1.8)] = _seeds("mymodel", (0.6, 0.65))
    for rep in groups[("second", 0.5)]:  # Top6 apart from Top3, so the column's order shows
        rep["results"]["large"]["top6"]["recall"] = 0.11
    lines = detector_table(groups, {("second", 0.5): 4.25, ("second", 1.8): 5.0})
    rows = {tuple(c.strip() for c in ln.split("|")[1:3]): ln for ln in lines[2:]}
    assert set(rows) == {("second", "0.5 m"), ("second", "1.8 m"), ("mymodel", "1.8 m")}
    comb = seed_combined(groups[("second", 0.5)])["results"]
    ap = comb["small"]["all"]["ap_r40"]["mean"]
    assert f"| {ap:.2f} [" in rows[("second", "0.5 m")]
    top3 = comb["large"]["top3"]["recall"]["mean"]
    assert top3 > 0.5 and f"| {top3:.2f} / 0.11 | 0.97" in rows[("second", "0.5 m")]  # importance levels, large
    assert "| 0.97 / 0.90 / 0.85 | 4.2 |" in rows[("second", "0.5 m")]  # Table VII: SECOND at 0.5 m
    assert "| 0.97 / 0.91 / 0.85 | 5.0 |" in rows[("second", "1.8 m")]
    assert rows[("mymodel", "1.8 m")].endswith("| - | - |")  # not in the paper, no training time given


def _without_ranking(reps: list[dict]) -> list[dict]:
    """The reports as an evaluation without the AP ranking lays them out."""
    out = copy.deepcopy(reps)
    for rep in out:
        del rep["uncertainty"]["ap_ranking"]
    return out


def test_the_ap_lead_is_paired_over_scenes_and_narrower_than_the_quadrature_on_correlated_scenes():
    """Hard scenes are hard for both models: the paired bootstrap sees the two APs move together, the two
    separate intervals in quadrature do not. Reports without the AP ranking keep the quadrature, as it was."""
    from detbench.eval.ap_bootstrap import paired_ap_difference
    from detbench.eval.bootstrap import percentile_interval

    a = _seeds("second", (0.95, 0.9), hard=0.6)
    b = _seeds("pillarnet", (0.85, 0.8), hard=0.6)
    paired = seed_summary({("second", 1.8): a, ("pillarnet", 1.8): b})[1.8]["ap_r40"]
    old = seed_summary({("second", 1.8): _without_ranking(a), ("pillarnet", 1.8): _without_ranking(b)})[1.8]["ap_r40"]
    lead, quad = paired["lead"], old["lead"]
    assert paired["best"] == old["best"] == "second"
    assert lead["scene_method"].startswith("paired scene bootstrap") and "re-ranked" in lead["scene_method"]
    assert quad["scene_method"].startswith("the two scene intervals in quadrature")
    assert lead["diff"] == quad["diff"] and lead["seed_half_width"] == quad["seed_half_width"] > 0
    assert lead["scene_ci95"] == percentile_interval(paired_ap_difference(a, b, "small", "all", LEAD_REPLICATES, 0))
    assert _width(lead["scene_ci95"]) < 0.6 * _width(quad["scene_ci95"]), (lead["scene_ci95"], quad["scene_ci95"])
    # the quadrature of the two models' scene intervals of the seed mean, unchanged for reports without the ranking
    ca, cb = (seed_combined(x)["results"]["small"]["all"]["ap_r40"] for x in (a, b))
    lo = quad["diff"] - math.hypot(ca["mean"] - ca["scene_ci95"][0], cb["scene_ci95"][1] - cb["mean"])
    hi = quad["diff"] + math.hypot(ca["scene_ci95"][1] - ca["mean"], cb["mean"] - cb["scene_ci95"][0])
    assert quad["scene_ci95"] == pytest.approx([lo, hi], abs=2e-6)
    # one side without the ranking: the quadrature too
    mixed = seed_summary({("second", 1.8): a, ("pillarnet", 1.8): _without_ranking(b)})[1.8]["ap_r40"]["lead"]
    assert mixed["scene_ci95"] == quad["scene_ci95"]


def test_the_height_answer_holds_every_pair_of_a_models_heights_resolved_or_bounded():
    """second: 1.8 m and 1 m alike, 0.5 m far behind (fewer vehicles found and two of them hidden)."""
    mid, low = dict(height=1.0, hidden=(5,)), dict(height=0.5, hidden=(3, 5))
    groups = {("second", 1.8): _seeds("second", (0.9, 0.88)), ("second", 1.0): _seeds("second", (0.89, 0.9), **mid),
              ("second", 0.5): _seeds("second", (0.3, 0.32), **low),
              ("pillarnet", 1.8): _seeds("pillarnet", (0.6, 0.62))}
    answer = seed_height_pairs(groups)
    assert set(answer) == {"second"}  # pillarnet has one height: no pair
    summary = seed_height_summary(groups)["second"]
    for metric, (r, lv) in (("recall", ("large", "all")), ("ap_r40", ("small", "all"))):
        entry = answer["second"][metric]
        assert (entry["range"], entry["level"]) == (r, lv)
        pairs = {(p["height"], p["over"]): p for p in entry["pairs"]}
        ranking = [e["height"] for e in summary[metric]["ranking"]]
        assert list(pairs) == list(combinations(ranking, 2)), metric  # every pair once, the higher mean first
        # the leader over the runner-up is the lead seed_height_summary reports
        top = pairs[tuple(ranking[:2])]
        assert {k: top[k] for k in summary[metric]["lead"]} == summary[metric]["lead"]
        for p in entry["pairs"]:
            lo, hi = p["ci95"]
            assert p["scene_method"].startswith("paired scene bootstrap"), (metric, p)
            if lo > 0 or hi < 0:
                assert p["answer"] == "resolved" and p["leader"] == (p["height"] if lo > 0 else p["over"])
                assert p["margin"] is None and p["ahead"]
            else:
                assert p["answer"] == "bounded" and p["leader"] is None and not p["ahead"]
                assert p["margin"] == round(max(abs(lo), abs(hi)), 6) > 0
        far = pairs[(1.8, 0.5)] if (1.8, 0.5) in pairs else pairs[(1.0, 0.5)]
        assert far["answer"] == "resolved" and far["leader"] != 0.5, (metric, far)
        near = pairs[(1.8, 1.0)] if (1.8, 1.0) in pairs else pairs[(1.0, 1.8)]
        assert near["answer"] == "bounded" and near["margin"] < 0.5, (metric, near)
    stats = seed_statistics(groups)
    assert stats["height_pairs"] == answer  # computed once, with the rest of a study's seed figures
    text = "\n".join(seed_markdown(groups))
    assert "**The height answer, per model**" in text and "*second*" in text and "*pillarnet*" not in text
    rows = [ln for ln in text.splitlines() if ln.startswith(("| Recall large |", "| AP@R40 small |"))]
    assert len(rows) == 6
    p = answer["second"]["recall"]["pairs"][0]
    assert (f"| Recall large | {p['height']:g} m - {p['over']:g} m | {p['diff']:+.3f} [{p['ci95'][0]:+.3f}, "
            f"{p['ci95'][1]:+.3f}] |") in text
    assert any(ln.endswith("| resolved: 1.8 m leads |") or ln.endswith("| resolved: 1 m leads |") for ln in rows)
    bounded = [q for e in answer["second"].values() for q in e["pairs"] if q["answer"] == "bounded"]
    assert all(f"| bounded: the two differ by less than {q['margin']:.3f} |" in text for q in bounded)
