"""The scene bootstrap behind the intervals of recall and AP@R40 (`evaluate(..., bootstrap=B)`)."""
from __future__ import annotations

import numpy as np
import pytest

from detbench.eval.evaluate import PAIRS, EvalFrame, evaluate


def _frame(rng, fid, scene, n_gt=4, hit=3, extra_fp=1, score_base=0.0):
    """A frame with n_gt cars 10-40 m ahead; `hit` of them predicted exactly, plus FPs."""
    x = np.sort(rng.uniform(8.0, 40.0, n_gt))
    gt = np.stack([x, rng.uniform(-6, 6, n_gt), np.full(n_gt, 0.8), np.full(n_gt, 4.5),
                   np.full(n_gt, 1.9), np.full(n_gt, 1.6), np.zeros(n_gt)], axis=1)
    fp = gt[:extra_fp].copy()
    fp[:, 1] += 3.5 if extra_fp else 0.0  # a box beside a car: IoU 0 with it
    pred = np.concatenate([gt[:hit], fp])
    scores = score_base + rng.uniform(0.2, 0.99, len(pred))
    return EvalFrame(gt, np.full(n_gt, 50), np.zeros(n_gt), pred, scores, frame_id=fid, scene_id=scene)


def _frames(seed=0, scenes=6, per_scene=3):
    rng = np.random.default_rng(seed)
    return [_frame(rng, f"{s:04d}_{i:03d}", f"{s:04d}", hit=int(rng.integers(1, 5)))
            for s in range(scenes) for i in range(per_scene)]


def test_per_scene_counts_add_up_to_the_report():
    rep = evaluate(_frames(), bootstrap=200)
    unc = rep["uncertainty"]
    assert unc["num_clusters"] == 6 and unc["replicates"] == 200
    for r, lv in PAIRS:
        cell = rep["results"][r][lv]
        pc = unc["per_cluster"][r][lv]
        assert sum(pc["tp"]) == cell["tp"]
        assert sum(pc["lidar_detected"]) == cell["lidar_detected"]


def test_interval_brackets_the_estimate_and_is_reproducible():
    frames = _frames()
    a = evaluate(frames, bootstrap=300, bootstrap_seed=3)
    b = evaluate(frames, bootstrap=300, bootstrap_seed=3)
    assert a["uncertainty"]["results"] == b["uncertainty"]["results"]
    cell = a["results"]["small"]["all"]
    ci = a["uncertainty"]["results"]["small"]["all"]
    assert ci["recall_ci95"][0] <= cell["recall"] <= ci["recall_ci95"][1]
    assert ci["ap_r40_ci95"][0] <= cell["ap_r40"] <= ci["ap_r40_ci95"][1]
    assert ci["ap_r40_ci95"][1] - ci["ap_r40_ci95"][0] > 0.01  # scenes differ: the interval has width


def test_identical_scenes_give_a_zero_width_interval():
    rng = np.random.default_rng(1)
    base = [_frame(rng, f"x_{i}", None, hit=2 + i % 3) for i in range(3)]
    frames = [EvalFrame(f.gt_boxes, f.gt_num_points, f.gt_lane, f.pred_boxes, f.pred_scores,
                        frame_id=f"{s}_{i}", scene_id=f"scene{s}")
              for s in range(5) for i, f in enumerate(base)]
    rep = evaluate(frames, bootstrap=100)
    cell = rep["results"]["small"]["all"]
    lo, hi = rep["uncertainty"]["results"]["small"]["all"]["ap_r40_ci95"]
    # Every resample is the same frames repeated 5 times; AP is the same up to how tied copies
    # interleave, recall exactly.
    rlo, rhi = rep["uncertainty"]["results"]["small"]["all"]["recall_ci95"]
    assert rlo == pytest.approx(cell["recall"]) and rhi == pytest.approx(cell["recall"])
    assert hi - lo < 0.05


def test_one_scene_gives_no_interval():
    rng = np.random.default_rng(2)
    frames = [_frame(rng, f"0000_{i}", "0000") for i in range(4)]
    unc = evaluate(frames, bootstrap=50)["uncertainty"]
    assert unc["num_clusters"] == 1 and "note" in unc
    assert unc["results"]["small"]["all"] == {"recall_ci95": None, "ap_r40_ci95": None}


def test_frames_without_scene_are_their_own_clusters():
    rng = np.random.default_rng(4)
    frames = [_frame(rng, f"f{i}", None) for i in range(5)]
    assert evaluate(frames, bootstrap=20)["uncertainty"]["num_clusters"] == 5


def test_negative_replicates_is_an_error():
    with pytest.raises(ValueError, match="bootstrap"):
        evaluate(_frames(scenes=2), bootstrap=-1)


def test_no_bootstrap_no_uncertainty_key():
    assert "uncertainty" not in evaluate(_frames(scenes=2))
