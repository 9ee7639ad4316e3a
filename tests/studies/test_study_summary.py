"""The study report's opening summary: best height per cell, best detector per height, paired leads."""
from __future__ import annotations

import numpy as np

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies.study_summary import (
    detector_summary, detector_summary_lines, height_summary, height_summary_lines, paired_recall_difference,
    unlearned_lines, unlearned_models,
)


def _ability(ldrs: dict, diff_ci=(0.01, 0.05)):
    heights = {h: {r: {lv: {"total": 100, "detected": round(100 * v), "ldr": v} for lv in LEVELS}
                   for r in RANGE_NAMES} for h, v in ldrs.items()}
    hs = list(ldrs)
    diffs = {}
    for i in range(len(hs)):
        for j in range(i + 1, len(hs)):
            d = ldrs[hs[j]] - ldrs[hs[i]]
            diffs[f"{hs[j]}-{hs[i]}"] = {r: {lv: {"diff": d, "ci95": [d - diff_ci[1], d + diff_ci[1]]
                                                 if abs(d) < diff_ci[1] else [d - diff_ci[0], d + diff_ci[0]]}
                                             for lv in LEVELS} for r in RANGE_NAMES}
    return {"heights": heights, "extras": {"uncertainty": {"differences": diffs}}}


def test_best_height_and_its_paired_lead():
    s = height_summary(_ability({"0.5": 0.70, "1.0": 0.72, "1.8": 0.85}))
    c = s["large"]["top6"]
    assert c["best"] == "1.8" and c["runner_up"] == "1.0"
    assert abs(c["diff"] - 0.13) < 1e-9 and c["supported"]
    text = "\n".join(height_summary_lines(_ability({"0.5": 0.70, "1.0": 0.72, "1.8": 0.85})))
    assert "1.8 m hits the most vehicles at every level and range" in text
    assert "resolved (the 95 % interval excludes 0) in 9 of 9" in text


def test_a_lead_within_noise_is_not_resolved_and_a_lower_best_reads_the_reversed_difference():
    s = height_summary(_ability({"0.5": 0.80, "1.0": 0.79, "1.8": 0.60}))
    c = s["small"]["all"]
    assert c["best"] == "0.5" and c["runner_up"] == "1.0"
    assert c["diff"] > 0 and not c["supported"]  # stored as 1.0-0.5 = -0.01: read reversed
    assert c["ci95"][0] < 0 < c["ci95"][1]
    assert "(not resolved)" in "\n".join(height_summary_lines(_ability({"0.5": 0.80, "1.0": 0.79, "1.8": 0.60})))


def _report(model, height, tp, det, recall_ci=None):
    tp, det = np.asarray(tp), np.asarray(det)
    res = {r: {lv: {"total": int(det.sum()), "lidar_detected": int(det.sum()), "ldr": 1.0, "tp": int(tp.sum()),
                    "fp": 0, "recall": tp.sum() / det.sum(), "ap_r40": tp.sum() / det.sum() * 0.9}
               for lv in LEVELS} for r in RANGE_NAMES}
    unc = {"clusters": [f"s{i}" for i in range(len(det))],
           "per_cluster": {r: {lv: {"tp": tp.tolist(), "lidar_detected": det.tolist()} for lv in LEVELS}
                           for r in RANGE_NAMES},
           "results": {r: {lv: {"recall_ci95": recall_ci, "ap_r40_ci95": None} for lv in LEVELS}
                       for r in RANGE_NAMES}}
    return {"model": model, "height": height, "results": res, "uncertainty": unc}


def test_paired_difference_is_tight_when_one_model_wins_in_every_scene():
    det = [20, 30, 25, 40, 10, 35]
    a = _report("a", 1.8, [15, 22, 20, 30, 8, 27], det)
    b = _report("b", 1.8, [10, 15, 14, 21, 5, 18], det)
    d = paired_recall_difference(a, b, "large", "all", replicates=500)
    assert d["diff"] > 0 and d["ci95"][0] > 0
    same = paired_recall_difference(a, a, "large", "all", replicates=100)
    assert same["diff"] == 0 and same["ci95"] == [0.0, 0.0]


def test_paired_difference_needs_the_same_scenes():
    a = _report("a", 1.8, [1, 2], [3, 4])
    b = _report("b", 1.8, [1, 2], [3, 5])
    assert paired_recall_difference(a, b, "large", "all") is None


def test_detector_summary_ranks_by_recall_per_height():
    det = [20, 30, 25, 40]
    reps = [_report("second", 1.8, [10, 15, 12, 20], det), _report("ct3d", 1.8, [15, 25, 20, 33], det),
            _report("second", 0.5, [18, 28, 22, 38], det), _report("ct3d", 0.5, [10, 10, 10, 10], det)]
    s = detector_summary(reps)
    assert s[1.8]["best"] == "ct3d" and s[1.8]["runner_up"] == "second"
    assert s[0.5]["best"] == "second"
    text = "\n".join(detector_summary_lines(reps))
    assert "| 1.8 m | ct3d |" in text and "| 0.5 m | second |" in text


def test_equal_ldrs_are_reported_as_a_tie_not_a_lead():
    ab = _ability({"0.5": 0.9, "1.8": 0.9})
    c = height_summary(ab)["small"]["top3"]
    assert c["tied"] == ["1.8"]
    text = "\n".join(height_summary_lines(ab))
    assert "0.5 m = 1.8 m (tied)" in text and "a tie in 9 of 9" in text


def _ap_report(model: str, height: float, ap_small: float) -> dict:
    cell = {"recall": ap_small, "ap_r40": ap_small}
    return {"model": model, "height": height, "results": {r: {lv: dict(cell) for lv in LEVELS} for r in RANGE_NAMES}}


def test_a_model_below_the_learning_floor_at_every_height_is_named_and_one_that_learned_somewhere_is_not():
    reps = [_ap_report("pointrcnn", 1.8, 0.049), _ap_report("pointrcnn", 0.5, 0.035),
            _ap_report("pointrcnn", 1.0, 0.012),
            _ap_report("second", 0.5, 0.52), _ap_report("second", 1.8, 0.55),
            _ap_report("pillarnet", 0.5, 0.02), _ap_report("pillarnet", 1.8, 0.30)]  # learned at 1.8 m: not named
    bad = unlearned_models(reps)
    assert bad == {"pointrcnn": [0.035, 0.012, 0.049]}  # in height order
    text = "\n".join(unlearned_lines(reps))
    assert "pointrcnn (AP@R40 small 0.012-0.049)" in text and "second" not in text and "pillarnet" not in text
    assert unlearned_lines([_ap_report("second", 0.5, 0.52)]) == []
    assert unlearned_models([_ap_report("second", 0.5, None)]) == {}  # no AP at all: not evidence of anything
    assert unlearned_models(reps, threshold=0.6) == {"pillarnet": [0.02, 0.3], "pointrcnn": [0.035, 0.012, 0.049],
                                                     "second": [0.52, 0.55]}
