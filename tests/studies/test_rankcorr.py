"""Rank correlations of placement scores with detector figures (detbench.studies.rankcorr): known answers."""
import itertools
import json

import numpy as np
import pytest

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies.rankcorr import (
    bootstrap_interval, correlate_sweep, correlation_markdown, kendall_tau_b, load_detector_reports,
    permutation_pvalue, rank_agreement, rankdata, spearman,
)
from detbench.eval.report import METRIC_FIELDS


def test_rankdata_averages_ties():
    np.testing.assert_array_equal(rankdata([10, 20, 20, 5]), [2, 3.5, 3.5, 1])
    np.testing.assert_array_equal(rankdata([3, 3, 3]), [2, 2, 2])
    np.testing.assert_array_equal(rankdata([0.5, -1.0]), [2, 1])


def test_hand_computed_values():
    # two swapped neighbours: sum d^2 = 4 -> rho = 1 - 6*4/(5*24) = 0.8; 8 concordant, 2 discordant -> tau 0.6
    assert spearman([1, 2, 3, 4, 5], [2, 1, 4, 3, 5]) == pytest.approx(0.8)
    assert kendall_tau_b([1, 2, 3, 4, 5], [2, 1, 4, 3, 5]) == pytest.approx(0.6)
    # a tie in x: S = 5 of 6 pairs, one pair tied in x -> tau_b = 5 / sqrt(5 * 6);
    # rho from average ranks 4.5 / sqrt(22.5)
    assert kendall_tau_b([1, 2, 2, 3], [1, 3, 2, 4]) == pytest.approx(5 / np.sqrt(30))
    assert spearman([1, 2, 2, 3], [1, 3, 2, 4]) == pytest.approx(4.5 / np.sqrt(22.5))
    assert spearman(range(6), range(6)[::-1]) == pytest.approx(-1.0)
    assert kendall_tau_b(range(6), range(6)[::-1]) == pytest.approx(-1.0)
    assert np.isnan(spearman([1, 1, 1], [1, 2, 3])) and np.isnan(kendall_tau_b([1, 2, 3], [4, 4, 4]))
    with pytest.raises(ValueError, match="same length"):
        spearman([1, 2], [1, 2, 3])


def test_against_scipy_when_installed():
    st = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = rng.integers(0, 5, 9).astype(float)  # with ties
        y = rng.integers(0, 4, 9).astype(float)
        if len(set(x)) < 2 or len(set(y)) < 2:
            continue
        assert spearman(x, y) == pytest.approx(st.spearmanr(x, y)[0])
        assert kendall_tau_b(x, y) == pytest.approx(st.kendalltau(x, y)[0])
    x, y = rng.normal(size=7), rng.normal(size=7)
    assert permutation_pvalue(x, y, "kendall") == pytest.approx(st.kendalltau(x, y, method="exact").pvalue)


def test_exact_permutation_p_values():
    # a perfect order of six heights: only the identity and the reversal reach |rho| = 1 -> p = 2 / 720
    assert permutation_pvalue(range(6), range(6)) == pytest.approx(2 / 720)
    assert permutation_pvalue(range(6), range(6)[::-1], "kendall") == pytest.approx(2 / 720)
    # n = 4: the share of the 24 orderings at least as extreme, counted directly
    x = np.arange(4)
    rhos = np.array([spearman(x, p) for p in itertools.permutations(range(4))])
    y = np.array([0, 2, 1, 3])
    assert permutation_pvalue(x, y) == pytest.approx((np.abs(rhos) >= abs(spearman(x, y)) - 1e-12).mean())
    # beyond 8 heights a seeded sample: an unrelated pair is far from significant, a perfect one is not
    rng = np.random.default_rng(0)
    assert permutation_pvalue(np.arange(12), np.arange(12), permutations=2000) < 0.002
    assert permutation_pvalue(rng.normal(size=12), rng.normal(size=12), permutations=2000) > 0.01


def test_bootstrap_interval_known_cases():
    perfect = bootstrap_interval(range(6), [0.1, 0.2, 0.25, 0.4, 0.5, 0.9], "spearman", replicates=500)
    assert perfect["ci95"] == [1.0, 1.0]
    inverted = bootstrap_interval(range(6), range(6)[::-1], "kendall", replicates=500)
    assert inverted["ci95"] == [-1.0, -1.0]
    # unrelated: 60 independent pairs -> the interval holds 0 and is narrow-ish; a strong relation excludes 0
    rng = np.random.default_rng(1)
    x = rng.normal(size=60)
    none = bootstrap_interval(x, rng.normal(size=60), "spearman", replicates=500)
    assert none["ci95"][0] < 0 < none["ci95"][1] and none["ci95"][1] - none["ci95"][0] < 0.7
    strong = bootstrap_interval(x, x + 0.3 * rng.normal(size=60), "spearman", replicates=500)
    assert strong["ci95"][0] > 0.7
    assert bootstrap_interval([1, 2], [1, 2])["ci95"] is None  # two points: no interval


def test_rank_agreement_names_the_failure():
    hs = ["0.3", "0.5", "1.0", "1.5", "1.8", "2.2"]
    good = rank_agreement(hs, [1, 2, 3, 4, 5, 6], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], replicates=300)
    assert good["spearman"] == 1.0 and good["verdict"] == "predicts" and good["discordant_pairs"] == []
    assert good["best_by_score"] == good["best_observed"] == "2.2"
    swap = rank_agreement(hs, [1, 2, 3, 4, 5, 6], [0.1, 0.2, 0.3, 0.4, 0.6, 0.5], replicates=300)
    assert swap["discordant_pairs"] == [["1.8", "2.2"]]
    assert swap["best_by_score"] == "2.2" and swap["best_observed"] == "1.8"
    assert swap["spearman"] == pytest.approx(1 - 6 * 2 / (6 * 35), abs=1e-4)
    inv = rank_agreement(hs, [6, 5, 4, 3, 2, 1], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], replicates=300)
    assert inv["verdict"] == "inverted" and len(inv["discordant_pairs"]) == 15
    flat = rank_agreement(hs, [1, 2, 3, 4, 5, 6], [0.3, 0.1, 0.6, 0.2, 0.5, 0.4], replicates=300)
    assert flat["verdict"] == "no evidence"
    assert rank_agreement(hs[:2], [1, 2], [1, 2])["verdict"] == "too few heights"


# ---------------------------------------------------------------------------- reports and sweeps
def _eval_report(model, height, value, trained=None):
    cell = {k: 0 for k in METRIC_FIELDS} | {"total": 10, "lidar_detected": 8, "ldr": 0.8, "recall": value,
                                             "ap_r40": value / 2}
    rep = {"model": model, "height": height, "split": "test", "iou_threshold": 0.7, "score_threshold": 0.1,
           "num_frames": 5, "results": {r: {lv: dict(cell) for lv in LEVELS} for r in RANGE_NAMES}}
    if trained is not None:
        rep["trained_height"] = trained
    return rep


def _sweep(values: dict[str, float]) -> dict:
    """A sweep report reduced to what correlate_sweep reads: per height, range and score, a value."""
    heights = sorted(values, key=float)
    units = {"evidence": "", "ldr_w": ""}
    return {"heights": heights, "scores": {"units": units, "heights": {
        h: {r: {"evidence": {"value": values[h]}, "ldr_w": {"value": -values[h]}} for r in RANGE_NAMES}
        for h in heights}}}


def test_correlate_sweep_with_detector_reports(tmp_path):
    hs = {"0.5": 0.2, "0.8": 0.3, "1.0": 0.5, "1.3": 0.55, "1.5": 0.7, "1.8": 0.9}
    paths = []
    for h, v in hs.items():
        p = tmp_path / f"second_{h}.json"
        p.write_text(json.dumps(_eval_report("second", float(h), v)))  # recall rises with the score
        paths.append(p)
    cross = tmp_path / "cross.json"
    cross.write_text(json.dumps(_eval_report("second", 0.5, 0.1, trained=1.8)))
    other = tmp_path / "pillar_2.5.json"
    other.write_text(json.dumps(_eval_report("pillarnet", 2.5, 0.4)))
    first = tmp_path / "first_stage.json"
    first.write_text(json.dumps({**_eval_report("second", 1.0, 0.05, trained=1.0), "stage": "proposals"}))
    figures, skipped = load_detector_reports(paths + [cross, other, first])
    assert sorted(figures["second"]) == sorted(hs) and len(skipped) == 2 and "cross-height" in skipped[0]["reason"]
    assert skipped[1]["source"] == str(first) and "first stage alone" in skipped[1]["reason"]
    corr = correlate_sweep(_sweep(hs), figures, replicates=200)
    rows = [r for r in corr["rows"] if r["model"] == "second"]
    assert len(rows) == 2 * 9 * 2  # metrics x cells x scores
    assert all(r["spearman"] == 1.0 and r["verdict"] == "predicts" for r in rows if r["score"] == "evidence")
    assert all(r["spearman"] == -1.0 and r["verdict"] == "inverted" for r in rows if r["score"] == "ldr_w")
    assert corr["summary"]["evidence"]["predicts"] == 18 and corr["summary"]["ldr_w"]["inverted"] == 18
    assert any("pillarnet" in n and "not in the sweep" in n for n in corr["notes"])
    assert any(s.startswith("ldr_w fails to predict second's recall in 9 of 9") for s in corr["statements"])
    md = correlation_markdown(corr, "evidence")
    assert ("| evidence | 18 | 18 | 0 | 0 |" in md and "| ldr_w | 18 | 0 | 0 | 18 |" in md
            and "Where the scores fail" in md)


def test_detector_report_errors(tmp_path):
    with pytest.raises(ValueError, match="no such detector report"):
        load_detector_reports([tmp_path / "missing.json"])
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad.json: not a JSON report"):
        load_detector_reports([bad])
    nomodel = tmp_path / "nomodel.json"
    rep = _eval_report("x", 1.0, 0.5)
    rep.pop("model")
    nomodel.write_text(json.dumps(rep))
    with pytest.raises(ValueError, match="nomodel.json: the report has no 'height' or no 'model'"):
        load_detector_reports([nomodel])
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_eval_report("m", 1.0, 0.5)))
    b.write_text(json.dumps(_eval_report("m", 1.0, 0.6)))
    with pytest.raises(ValueError, match="b.json: model 'm' at 1.0 m is also in"):
        load_detector_reports([a, b])


def test_four_heights_never_reach_a_verdict():
    """Four heights: the exact permutation p is at least 2 / 24, so even a perfect order is 'no evidence'."""
    a = rank_agreement(["0.5", "1.0", "1.5", "2.2"], [1, 2, 3, 4], [4, 3, 2, 1], replicates=300)
    assert (a["spearman"] == -1.0 and a["p_spearman"] == pytest.approx(2 / 24, abs=1e-5)
            and a["verdict"] == "no evidence")
