"""The ranked detections an evaluation report keeps for a scene bootstrap of AP@R40, the weighted AP@R40 over
bootstrap replicates, and the paired difference of two reports' AP@R40 (detbench.eval.ap_bootstrap)."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from detbench.eval.ap_bootstrap import (
    ap_replicates, has_ap_ranking, paired_ap_difference, ranked_detections, weighted_ap_r40,
)
from detbench.eval.bootstrap import percentile_interval, scene_bootstrap_weights
from detbench.eval.evaluate import PAIRS, EvalFrame, ap_r40_ranked, evaluate
from tests.eval.test_evaluate_golden import golden_frames


def _shuffled_scenes(frames: list[EvalFrame]) -> list[EvalFrame]:
    """The frames with their scene ids permuted, so frame order is not scene order."""
    names = sorted({f.scene_id for f in frames})
    rename = dict(zip(names, reversed(names)))
    return [EvalFrame(f.gt_boxes, f.gt_num_points, f.gt_lane, f.pred_boxes, f.pred_scores, frame_id=f.frame_id,
                      scene_id=f"z{rename[f.scene_id]}" if i % 2 else rename[f.scene_id])
            for i, f in enumerate(frames)]


@pytest.mark.parametrize("shuffle", [False, True])
def test_unit_weights_on_the_stored_ranking_give_the_reports_ap_in_every_cell(shuffle):
    """Ties of score across frames and scenes, scores at the threshold, FPs, duplicates, ignored boxes:
    AP@R40 recomputed from the stored ranking with every scene drawn once is the report's, to the bit."""
    frames = golden_frames()
    if shuffle:
        frames = _shuffled_scenes(frames)
    rep = evaluate(frames, bootstrap=20, bootstrap_seed=1)
    num_scenes = rep["uncertainty"]["num_clusters"]
    assert has_ap_ranking(rep) and num_scenes == (8 if shuffle else 4)
    counted = 0
    for r, lv in PAIRS:
        tp, scene, det = ranked_detections(rep, r, lv)
        cell = rep["results"][r][lv]
        assert int(tp.sum()) == cell["tp"] and len(tp) - int(tp.sum()) == cell["fp"], (r, lv)
        assert int(det.sum()) == cell["lidar_detected"]
        ones = weighted_ap_r40(tp, scene, det, np.ones((1, num_scenes)))[0]
        if cell["ap_r40"] is None:
            assert np.isnan(ones)
        else:
            assert ones == cell["ap_r40"], (r, lv, ones, cell["ap_r40"])
            counted += 0.0 < cell["ap_r40"] < 1.0
    assert counted >= 6  # not vacuous: most cells have an AP strictly between 0 and 1


def test_the_stored_ranking_is_small():
    """One character per counted detection and range/level, and its scene index: a few bytes a detection."""
    import json

    rep = evaluate(golden_frames(), bootstrap=20)
    block = rep["uncertainty"]["ap_ranking"]
    k = len(block["scene"].split())
    assert k >= max(rep["results"][r][lv]["tp"] + rep["results"][r][lv]["fp"] for r, lv in PAIRS) > 0
    assert block["levels"] == ["all", "top3", "top6"] and all(len(text) == k for text in block["outcome"].values())
    assert len(json.dumps(block, indent=2)) < 8 * k  # text: no line per detection in an indented report.json


def test_weighted_ap_equals_ap_of_the_list_with_each_detection_repeated():
    rng = np.random.default_rng(5)
    for trial in range(40):
        scenes, k = int(rng.integers(2, 9)), int(rng.integers(0, 60))
        tp = rng.random(k) < rng.random()
        scene = rng.integers(0, scenes, k)
        det = np.bincount(scene[tp], minlength=scenes) + rng.integers(0, 3, scenes)
        w = scene_bootstrap_weights(scenes, 30, trial)
        got = weighted_ap_r40(tp, scene, det, w)
        for b in range(len(w)):
            copies = w[b].astype(np.int64)[scene]
            num_gt = int(w[b] @ det)
            want = ap_r40_ranked(np.repeat(tp, copies), num_gt) if num_gt else None
            assert (np.isnan(got[b]) if want is None else got[b] == want), (trial, b, got[b], want)


def test_the_reports_ap_interval_is_the_stored_rankings_bootstrap():
    rep = evaluate(golden_frames(), bootstrap=200, bootstrap_seed=3)
    for r, lv in PAIRS:
        samples = ap_replicates(rep, r, lv, 200, 3)
        assert percentile_interval(samples) == rep["uncertainty"]["results"][r][lv]["ap_r40_ci95"], (r, lv)


def _two_models(scenes: int = 8, per_scene: int = 3, seed: int = 0) -> tuple[dict, dict]:
    """Two detectors on the same frames: scenes are easy or hard for both (correlated over scenes)."""
    rng = np.random.default_rng(seed)
    a_frames, b_frames = [], []
    for s in range(scenes):
        hard = s % 2
        for i in range(per_scene):
            n = 6
            gt = np.column_stack([np.linspace(8, 45, n), np.zeros(n), np.full(n, 0.8), np.full(n, 4.5),
                                  np.full(n, 1.9), np.full(n, 1.6), np.zeros(n)])
            for skill, out in ((0.9 - 0.5 * hard, a_frames), (0.8 - 0.5 * hard, b_frames)):
                found = rng.random(n) < skill
                fp = gt[:2].copy()
                fp[:, 1] += 4.0
                pred = np.concatenate([gt[found], fp])
                scores = np.concatenate([rng.uniform(0.4, 1.0, int(found.sum())), rng.uniform(0.1, 0.7, 2)])
                out.append(EvalFrame(gt, np.full(n, 30), np.zeros(n), pred, scores, frame_id=f"{s}_{i}",
                                     scene_id=f"s{s}"))
    return evaluate(a_frames, bootstrap=400), evaluate(b_frames, bootstrap=400)


def test_the_paired_difference_resamples_both_sides_with_the_same_scenes():
    a, b = _two_models()
    diff = paired_ap_difference([a], [b], "small", "all", 400, 0)
    want = ap_replicates(a, "small", "all", 400, 0) - ap_replicates(b, "small", "all", 400, 0)
    assert np.array_equal(diff, want)
    # seeds pooled: each side the mean over its reports, replicate by replicate
    twin = copy.deepcopy(a)
    assert np.array_equal(paired_ap_difference([a, twin], [b], "small", "all", 400, 0), diff)
    # a scene that is hard for both moves both: the paired interval is narrower than each side's own
    lo, hi = percentile_interval(diff)
    own = [percentile_interval(ap_replicates(x, "small", "all", 400, 0)) for x in (a, b)]
    assert hi - lo < min(o[1] - o[0] for o in own), (lo, hi, own)


def test_reports_on_other_scenes_or_without_the_ranking_are_refused():
    a, b = _two_models()
    other = copy.deepcopy(b)
    other["uncertainty"]["clusters"] = [f"t{i}" for i in range(len(other["uncertainty"]["clusters"]))]
    with pytest.raises(ValueError, match="same test scenes"):
        paired_ap_difference([a], [other], "small", "all", 100, 0)
    broken = copy.deepcopy(a)
    broken["uncertainty"]["ap_ranking"]["outcome"]["small"] += "1"
    with pytest.raises(ValueError, match="evaluate again"):
        ranked_detections(broken, "small", "all")
    broken["uncertainty"]["ap_ranking"]["outcome"]["small"] = "z" * len(broken["uncertainty"]["ap_ranking"]["scene"])
    with pytest.raises(ValueError, match="characters other than"):
        ranked_detections(broken, "small", "all")
    old = copy.deepcopy(a)
    del old["uncertainty"]["ap_ranking"]
    assert not has_ap_ranking(old) and not has_ap_ranking({"results": {}})
