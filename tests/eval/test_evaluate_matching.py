"""Hand-computed cases for every matching rule of detbench.eval.evaluate (docs/evaluation.md).

All boxes are 4 x 2 x 1.6 m cars with heading 0, so IoUs are easy by hand: a copy shifted by
s metres along x has 3D IoU (4 - s) / (4 + s): s = 0.5 -> 7/9 = 0.778 (>= 0.7), s = 0.3 ->
0.860, s = 0.6 -> 0.739, s = 1.0 -> 0.6, s = 1.2 -> 0.538 (< 0.7).
"""
import math

import numpy as np
import pytest

from detbench.eval import EvalFrame, evaluate


def car(x, y=0.0):
    return [x, y, 0.8, 4.0, 2.0, 1.6, 0.0]


def frame(gt, points, lanes, preds, scores, fid="f"):
    return EvalFrame(np.array(gt, dtype=float).reshape(-1, 7), points, lanes,
                     np.array(preds, dtype=float).reshape(-1, 7), scores, frame_id=fid)


def cell(report, r="small", lv="all"):
    return report["results"][r][lv]


def test_iou_of_the_hand_cases():
    from detbench.ops import boxes_iou3d

    a = np.array([car(10.0)])
    for s, want in ((0.5, 7 / 9), (0.3, 3.7 / 4.3), (0.6, 3.4 / 4.6), (1.0, 0.6), (1.2, 2.8 / 5.2)):
        assert boxes_iou3d(a, np.array([car(10.0 + s)]))[0, 0] == pytest.approx(want, abs=1e-9)


def test_single_tp():
    rep = evaluate([frame([car(10)], [5], [0], [car(10.5)], [0.9])])
    c = cell(rep)
    assert (c["total"], c["lidar_detected"], c["tp"], c["fp"]) == (1, 1, 1, 0)
    assert c["ldr"] == 1.0 and c["recall"] == 1.0 and c["ap_r40"] == 1.0


def test_below_iou_threshold_is_fp():
    c = cell(evaluate([frame([car(10)], [5], [0], [car(11)], [0.9])]))  # IoU 0.6
    assert (c["tp"], c["fp"], c["recall"], c["ap_r40"]) == (0, 1, 0.0, 0.0)


def test_duplicate_prediction_is_fp():
    # Two predictions on one vehicle: the higher score takes it, the other is an FP.
    c = cell(evaluate([frame([car(10)], [5], [0], [car(10), car(10.5)], [0.9, 0.8])]))
    assert (c["tp"], c["fp"]) == (1, 1)
    # ranked [TP, FP], 1 GT: precision 1 at recall 1 -> AP 1
    assert c["ap_r40"] == 1.0
    # Greedy goes by score, not by IoU: the worse box (IoU 0.78) first takes the vehicle.
    c = cell(evaluate([frame([car(10)], [5], [0], [car(10), car(10.5)], [0.8, 0.9])]))
    assert (c["tp"], c["fp"]) == (1, 1)


def test_prediction_takes_the_highest_iou_vehicle():
    # Vehicles A (x=10) and B (x=10.9). P1 at 10.6: IoU 0.739 with A, 0.860 with B -> takes B.
    # P2 at 11.2: IoU 0.860 with B (already taken), 0.538 with A -> FP.
    # (Taking the first box above the threshold instead would give A to P1 and B to P2.)
    c = cell(evaluate([frame([car(10), car(10.9)], [5, 5], [0, 0], [car(10.6), car(11.2)], [0.9, 0.8])]))
    assert (c["tp"], c["fp"]) == (1, 1)
    assert c["recall"] == 0.5


def test_prediction_on_undetected_vehicle_is_ignored():
    # The vehicle at x=20 has no LiDAR point: it is an ignored box; a prediction on it is ignored.
    rep = evaluate([frame([car(10), car(20)], [3, 0], [0, 0], [car(10), car(20)], [0.9, 0.95])])
    c = cell(rep)
    assert (c["total"], c["lidar_detected"], c["tp"], c["fp"]) == (2, 1, 1, 0)
    assert c["ldr"] == 0.5 and c["recall"] == 1.0 and c["ap_r40"] == 1.0


def test_prediction_on_non_top3_vehicle_is_ignored():
    # Two detected vehicles in the ego lane: only the nearer (x=10) is Top3; the one at x=20 is
    # an ignored box in top3 but evaluated in all and top6.
    rep = evaluate([frame([car(10), car(20)], [3, 3], [0, 0], [car(20.5)], [0.9])])
    assert (cell(rep, lv="top3")["total"], cell(rep, lv="top3")["tp"], cell(rep, lv="top3")["fp"]) == (1, 0, 0)
    assert cell(rep, lv="top3")["recall"] == 0.0
    assert (cell(rep, lv="all")["tp"], cell(rep, lv="all")["fp"]) == (1, 0)
    assert (cell(rep, lv="top6")["tp"], cell(rep, lv="top6")["fp"]) == (1, 0)


def test_prediction_on_other_lane_vehicle_is_ignored_in_topk():
    # Lane +2 and the opposite carriageway take no part in Top-k; in range, so evaluated in "all".
    for lane in (2, 99, -99):
        rep = evaluate([frame([car(10, 4.0)], [3], [lane], [car(10, 4.0)], [0.9])])
        assert cell(rep, lv="top3")["total"] == 0 and cell(rep, lv="top3")["fp"] == 0
        assert cell(rep, lv="top3")["recall"] is None and cell(rep, lv="top3")["ap_r40"] is None
        assert cell(rep, lv="all")["tp"] == 1


def test_unmatched_prediction_outside_range_is_ignored():
    # No vehicle at all; predictions at x=70 (moderate/large only) and x=30, y=7 (|y| > 5).
    rep = evaluate([frame([], [], [], [car(70), car(30, 7.0)], [0.9, 0.8])])
    assert cell(rep, "small")["fp"] == 0
    assert cell(rep, "moderate")["fp"] == 2
    assert cell(rep, "large")["fp"] == 2
    # x = 160 is outside every range; x = -1 (behind the ego) too
    rep = evaluate([frame([], [], [], [car(160), car(-1)], [0.9, 0.8])])
    assert all(cell(rep, r, lv)["fp"] == 0 for r in ("small", "moderate", "large") for lv in ("all", "top3", "top6"))


def test_unmatched_prediction_inside_range_is_fp_at_every_level():
    rep = evaluate([frame([car(10)], [3], [0], [car(10), car(30)], [0.9, 0.8])])
    for lv in ("all", "top3", "top6"):
        assert (cell(rep, lv=lv)["tp"], cell(rep, lv=lv)["fp"]) == (1, 1)


def test_prediction_on_vehicle_outside_range_is_ignored():
    # Vehicle at x=49.9 is in small; at x=50.2 it is not. A prediction centred at 49.9 on the
    # out-of-range vehicle at 50.2 (IoU 0.86) lies inside small but overlaps an ignored box.
    rep = evaluate([frame([car(50.2)], [3], [0], [car(49.9)], [0.9])])
    assert cell(rep, "small")["fp"] == 0 and cell(rep, "small")["total"] == 0
    assert cell(rep, "moderate")["tp"] == 1


def test_score_threshold_boundary():
    gt = [car(10)]
    for score, kept in ((0.09, False), (0.0999999, False), (0.1, True), (np.float32(0.1), True), (0.11, True)):
        c = cell(evaluate([frame(gt, [3], [0], [car(10)], [score])]))
        assert c["tp"] == int(kept), score
    # dropped predictions do not count as FPs either
    c = cell(evaluate([frame([], [], [], [car(10)], [0.09])]))
    assert c["fp"] == 0
    # another threshold
    c = cell(evaluate([frame(gt, [3], [0], [car(10)], [0.3])], score_threshold=0.5))
    assert c["tp"] == 0


def test_iou_threshold_is_inclusive():
    # A 2 x 2 x 1.6 box centred in the 4 x 2 x 1.6 car has IoU exactly 0.5.
    inner = [10, 0, 0.8, 2.0, 2.0, 1.6, 0.0]
    assert cell(evaluate([frame([car(10)], [3], [0], [inner], [0.9])], iou_threshold=0.5))["tp"] == 1
    assert cell(evaluate([frame([car(10)], [3], [0], [inner], [0.9])], iou_threshold=0.51))["tp"] == 0


def test_equal_scores_keep_input_order():
    # Vehicle at x=49.8 (in small). P_out at x=50.3 (centre outside small; IoU 0.78) and
    # P_in at x=49.8 (IoU 1) with the same score. The earlier one in the input goes first.
    gt = [car(49.8)]
    c = cell(evaluate([frame(gt, [3], [0], [car(50.3), car(49.8)], [0.5, 0.5])]))
    assert (c["tp"], c["fp"]) == (1, 1)  # P_out takes the vehicle; P_in is a duplicate, in range
    c = cell(evaluate([frame(gt, [3], [0], [car(49.8), car(50.3)], [0.5, 0.5])]))
    assert (c["tp"], c["fp"]) == (1, 0)  # P_in takes it; P_out is unmatched and outside -> ignored


def test_pooled_ranking_across_frames():
    # Frame 1: one vehicle found with score 0.9. Frame 2: an FP with score 0.95 and one missed
    # vehicle. Pooled ranking [FP 0.95, TP 0.9], 2 vehicles: precision 1/2 at recall 1/2.
    f1 = frame([car(10)], [3], [0], [car(10)], [0.9], "a")
    f2 = frame([car(20)], [3], [0], [car(30)], [0.95], "b")
    c = cell(evaluate([f1, f2]))
    assert (c["tp"], c["fp"], c["lidar_detected"]) == (1, 1, 2)
    assert c["recall"] == 0.5
    assert c["ap_r40"] == pytest.approx(20 * 0.5 / 40)
    # Equal scores across frames: the earlier frame ranks first.
    f2b = frame([car(20)], [3], [0], [car(30)], [0.9], "b")
    assert cell(evaluate([f1, f2b]))["ap_r40"] == pytest.approx(20 * 1.0 / 40)
    assert cell(evaluate([f2b, f1]))["ap_r40"] == pytest.approx(20 * 0.5 / 40)


def test_nulls_when_nothing_is_evaluated():
    rep = evaluate([])
    assert rep["num_frames"] == 0
    for r in ("small", "moderate", "large"):
        for lv in ("all", "top3", "top6"):
            c = cell(rep, r, lv)
            assert c == {"total": 0, "lidar_detected": 0, "ldr": None, "tp": 0, "fp": 0,
                         "recall": None, "ap_r40": None}
    # only undetected vehicles: LDR 0, recall and AP null, FPs still counted
    c = cell(evaluate([frame([car(10)], [0], [0], [car(30)], [0.9])]))
    assert c["ldr"] == 0.0 and c["recall"] is None and c["ap_r40"] is None and c["fp"] == 1
    # detected vehicles, no predictions: recall 0, AP 0
    c = cell(evaluate([frame([car(10)], [1], [0], [], [])]))
    assert c["recall"] == 0.0 and c["ap_r40"] == 0.0


def test_empty_frames_and_shapes():
    rep = evaluate([EvalFrame([], [], [], [], []), EvalFrame(np.zeros((0, 7)), np.zeros(0), np.zeros(0),
                                                            np.zeros((0, 7)), np.zeros(0))])
    assert rep["num_frames"] == 2 and cell(rep)["total"] == 0
    # frames as dicts are accepted
    rep = evaluate([{"gt_boxes": [car(10)], "gt_num_points": [2], "gt_lane": [0],
                     "pred_boxes": [car(10)], "pred_scores": [0.5]}])
    assert cell(rep)["tp"] == 1


def test_report_layout_and_json():
    from detbench.utils.atomic import to_json

    rep = evaluate([frame([car(10)], [3], [0], [car(10)], [0.9])], extras=True)
    assert set(rep) == {"iou_threshold", "iou_kind", "score_threshold", "num_frames", "results", "extras"}
    assert rep["iou_threshold"] == 0.7 and rep["score_threshold"] == 0.1 and rep["iou_kind"] == "3d"
    assert list(rep["results"]) == ["small", "moderate", "large"]
    assert all(list(v) == ["all", "top3", "top6"] for v in rep["results"].values())
    assert set(rep["extras"]) == {"bev_0.7", "3d_0.5", "bev_0.5"}
    for ex in rep["extras"].values():
        assert set(ex) == {"iou_kind", "iou_threshold", "results"}
    to_json(rep)  # strict JSON (no NaN)
    assert "extras" not in evaluate([])


def test_bev_and_iou05_extras_differ_where_they_should():
    # A prediction of the right footprint but 1 m too high: BEV IoU 1, 3D IoU (1.6-1)/(1.6+1) = 0.23.
    high = car(10)
    high[2] += 1.0
    rep = evaluate([frame([car(10)], [3], [0], [high], [0.9])], extras=True)
    assert cell(rep)["tp"] == 0
    assert rep["extras"]["bev_0.7"]["results"]["small"]["all"]["tp"] == 1
    # Shift 1.0 m: IoU 0.6 -> FP at 0.7, TP at 0.5.
    rep = evaluate([frame([car(10)], [3], [0], [car(11)], [0.9])], extras=True)
    assert cell(rep)["tp"] == 0
    assert rep["extras"]["3d_0.5"]["results"]["small"]["all"]["tp"] == 1
    # main BEV evaluation
    assert cell(evaluate([frame([car(10)], [3], [0], [high], [0.9])], iou_kind="bev"))["tp"] == 1


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match="gt_boxes must have shape"):
        EvalFrame(np.zeros((2, 6)), [1, 1], [0, 0], [], [], frame_id="x")
    with pytest.raises(ValueError, match="'x'.*gt_num_points must have shape"):
        EvalFrame([car(1)], [1, 2], [0], [], [], frame_id="x")
    with pytest.raises(ValueError, match="pred_scores must be finite"):
        EvalFrame([], [], [], [car(1)], [math.nan])
    with pytest.raises(ValueError, match="whole numbers"):
        EvalFrame([car(1)], [1.5], [0], [], [])
    with pytest.raises(ValueError, match="not finite"):
        EvalFrame([[1, 2, math.inf, 1, 1, 1, 0]], [1], [0], [], [])
    with pytest.raises(ValueError, match="iou_threshold"):
        evaluate([], iou_threshold=0)
    with pytest.raises(ValueError, match="iou_kind"):
        evaluate([], iou_kind="2d")
    with pytest.raises(TypeError, match="EvalFrame"):
        evaluate([np.zeros(3)])
