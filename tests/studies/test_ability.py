"""LiDAR detection-ability study: hand-made counting cases and the tools/analyze.py pipeline."""
import json

import numpy as np
import pytest

from detbench.data import DatasetWriter, Frame, Sensor
from detbench.studies.ability import CELLS, AbilityStudy, stacked_masks
from detbench.studies.ability_tables import ability_markdown
from tests.helpers import assert_golden
import tools.analyze


@pytest.fixture
def analyze_main():
    """Run tools/analyze.py's main in this process (saves the interpreter and numba start-up)."""
    return lambda argv: tools.analyze.main([str(a) for a in argv])


def car(x, y, heading=0.0, dz=1.5):
    """A 4 x 2 m car standing on the road at (x, y)."""
    return [x, y, dz / 2, 4.0, 2.0, dz, heading]


def frame(boxes, points, lanes=None, height=1.8, fid="0000_000"):
    boxes = np.asarray(boxes, np.float32).reshape(-1, 7)
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    pts = np.c_[pts, np.full(len(pts), 0.5, np.float32)].astype(np.float32)
    m = len(boxes)
    lanes = np.zeros(m, np.int64) if lanes is None else np.asarray(lanes, np.int64)
    return Frame(fid, fid.split("_")[0], pts, boxes, np.array(["car"] * m), np.arange(m, dtype=np.int64), lanes,
                 Sensor(height=height))


def cell(rep, h, r, lv):
    return rep["heights"][h][r][lv]


# ----------------------------------------------------------------------------- the 0.05 m lift

def test_bottom_lift_point_at_4cm_not_counted_6cm_counted():
    boxes = [car(10, 0), car(20, 0)]
    pts = [[10.0, 0.0, 0.04], [20.0, 0.0, 0.06]]
    st = AbilityStudy()
    st.add(frame(boxes, pts))
    rep = st.report()
    c = cell(rep, "1.8", "small", "all")
    assert (c["total"], c["detected"], c["ldr"]) == (2, 1, 0.5)
    # the box top is inclusive; above it nothing counts
    st2 = AbilityStudy()
    st2.add(frame([car(10, 0)], [[10.0, 0.0, 1.5], [10.0, 0.0, 1.51]]))
    assert cell(st2.report(), "1.8", "small", "all")["detected"] == 1
    st3 = AbilityStudy()
    st3.add(frame([car(10, 0)], [[10.0, 0.0, 1.51], [10.0, 1.2, 0.5]]))  # above the roof; beside the car
    assert cell(st3.report(), "1.8", "small", "all")["detected"] == 0


def test_one_lidar_detected_rule_for_every_counter():
    """The rule's functions count with DETECTED_BOTTOM_LIFT, and the simulator's config uses the same lift."""
    from detbench.data.regions import DETECTED_BOTTOM_LIFT, DETECTED_MIN_POINTS, detected_point_counts, lidar_detected
    from detbench.sim import load_sim_config, sim_presets

    assert (DETECTED_BOTTOM_LIFT, DETECTED_MIN_POINTS) == (0.05, 1)
    boxes = np.asarray([car(10, 0), car(20, 0), car(30, 0)], np.float32)
    pts = np.asarray([[10.0, 0.0, 0.04, 0.5], [20.0, 0.0, 0.06, 0.5], [20.0, 0.5, 1.0, 0.5]], np.float32)
    assert detected_point_counts(pts, boxes).tolist() == [0, 2, 0]
    assert lidar_detected(pts, boxes).tolist() == [False, True, False]
    assert lidar_detected(pts, boxes, min_points=3).tolist() == [False, False, False]
    assert lidar_detected(pts, boxes[:0]).shape == (0,)
    for preset in sim_presets():
        assert load_sim_config(preset)["output"]["count_bottom_lift_m"] == DETECTED_BOTTOM_LIFT


def test_rotated_box_footprint():
    # a car turned 90 degrees is 2 m long in x and 4 m wide in y
    st = AbilityStudy()
    st.add(frame([car(10, 0, heading=np.pi / 2)], [[11.5, 0.0, 0.5]]))
    assert cell(st.report(), "1.8", "small", "all")["detected"] == 0
    st = AbilityStudy()
    st.add(frame([car(10, 0, heading=np.pi / 2)], [[10.0, 1.9, 0.5]]))
    assert cell(st.report(), "1.8", "small", "all")["detected"] == 1


# ----------------------------------------------------------------------------- ranges

@pytest.mark.parametrize("x, y, small, moderate, large", [
    (50.0, 0.0, True, True, True),
    (50.01, 0.0, False, True, True),
    (0.0, 5.0, True, True, True),
    (10.0, -5.01, False, True, True),
    (-0.01, 0.0, False, False, False),
    (100.0, 10.0, False, True, True),
    (100.01, 0.0, False, False, True),
    (150.0, -15.0, False, False, True),
    (150.01, 0.0, False, False, False),
    (20.0, 15.01, False, False, False),
])
def test_range_borders(x, y, small, moderate, large):
    st = AbilityStudy()
    st.add(frame([car(x, y)], np.zeros((0, 3))))
    rep = st.report()
    got = [cell(rep, "1.8", r, "all")["total"] == 1 for r in ("small", "moderate", "large")]
    assert got == [small, moderate, large]


# ----------------------------------------------------------------------------- importance levels

def test_top3_top6_with_missing_lane_and_other_lanes_excluded():
    # lanes: ego lane 0 has three cars, left lane +1 one car, no right lane; lane 2 and the
    # opposite carriageway (99) never count for Top3/Top6
    boxes = [car(30, 0), car(10, 0), car(20, 0), car(15, 3.5), car(5, 7.0), car(8, -3.5)]
    lanes = [0, 0, 0, 1, 2, 99]
    pts = [[30, 0, 0.5], [15, 3.5, 0.5], [8, -3.5, 0.5]]  # hit: far ego car, the left car, the opposite car
    st = AbilityStudy()
    st.add(frame(boxes, pts, lanes))
    rep = st.report()
    assert cell(rep, "1.8", "large", "all")["total"] == 6
    t3, t6 = cell(rep, "1.8", "large", "top3"), cell(rep, "1.8", "large", "top6")
    assert (t3["total"], t3["detected"]) == (2, 1)  # car(10,0) not hit, car(15,3.5) hit
    assert (t6["total"], t6["detected"]) == (3, 1)  # + car(20,0), not hit
    m = stacked_masks(np.asarray(boxes, np.float32), np.asarray(lanes))
    assert m[CELLS.index(("large", "top3"))].tolist() == [False, True, False, True, False, False]
    assert m[CELLS.index(("large", "top6"))].tolist() == [False, True, True, True, False, False]


def test_top3_ties_and_range_restriction():
    # two cars in the ego lane at the same bird's-eye distance: the earlier box is the Top3 one
    boxes = [car(12, 1.2), car(12, -1.2), car(60, 0)]
    lanes = [0, 0, 0]
    st = AbilityStudy()
    st.add(frame(boxes, [[12, -1.2, 0.5]], lanes))  # only the second of the tied pair is hit
    rep = st.report()
    assert (cell(rep, "1.8", "small", "top3")["total"], cell(rep, "1.8", "small", "top3")["detected"]) == (1, 0)
    assert cell(rep, "1.8", "small", "top6")["total"] == 2 and cell(rep, "1.8", "small", "top6")["detected"] == 1
    # Top-k is chosen among the vehicles of the range: car(60, 0) is outside small but in moderate
    assert cell(rep, "1.8", "small", "all")["total"] == 2
    assert cell(rep, "1.8", "moderate", "top6")["total"] == 2
    assert cell(rep, "1.8", "moderate", "all")["total"] == 3


def test_unknown_lanes_come_from_lateral_offset():
    from detbench.data.frame import LANE_UNKNOWN

    boxes = [car(10, 0.3), car(12, 3.6), car(14, 3.4)]
    st = AbilityStudy(lane_width=3.5)
    st.add(frame(boxes, [], [LANE_UNKNOWN] * 3))
    assert cell(st.report(), "1.8", "small", "top3")["total"] == 2  # lane 0 and lane +1


# ----------------------------------------------------------------------------- accumulation, extras

def test_accumulates_heights_thresholds_and_distance():
    boxes = [car(10, 0), car(45, 2), car(149.9, 0), car(80, -9)]
    rng = np.random.default_rng(0)
    st = AbilityStudy(thresholds=(1, 5, 10))
    for i in range(3):
        fid = f"0000_{i:03d}"
        # 1.8 m: 7 points on the first car, 1 on the second; 0.5 m: 12 on the first
        p18 = np.r_[np.c_[10 + rng.uniform(-1, 1, 7), rng.uniform(-0.5, 0.5, 7), np.full(7, 1.0)], [[45, 2, 1.0]]]
        p05 = np.c_[10 + rng.uniform(-1, 1, 12), rng.uniform(-0.5, 0.5, 12), np.full(12, 0.3)]
        st.add([frame(boxes, p05, height=0.5, fid=fid), frame(boxes, p18, height=1.8, fid=fid)])
    rep = st.report()
    assert rep["num_frames"] == 3 and list(rep["heights"]) == ["0.5", "1.8"]
    assert cell(rep, "0.5", "large", "all") == {"total": 12, "detected": 3, "ldr": 0.25}
    assert cell(rep, "1.8", "large", "all") == {"total": 12, "detected": 6, "ldr": 0.5}
    mp = rep["extras"]["min_points"]
    assert mp["5"]["1.8"]["large"]["all"]["detected"] == 3 and mp["10"]["1.8"]["large"]["all"]["detected"] == 0
    assert mp["10"]["0.5"]["large"]["all"]["detected"] == 3
    assert mp["1"]["1.8"] == rep["heights"]["1.8"]
    dist = rep["extras"]["ldr_vs_distance"]
    assert dist["edges_m"][0] == 0 and dist["edges_m"][-1] == 150 and len(dist["edges_m"]) == 16
    tot = dist["heights"]["1.8"]["total"]
    assert tot[1] == 3 and tot[4] == 3 and tot[8] == 3 and tot[14] == 3 and sum(tot) == 12
    assert dist["heights"]["1.8"]["detected"][4] == 3 and dist["heights"]["0.5"]["detected"][4] == 0
    assert dist["heights"]["1.8"]["ldr"][0] != dist["heights"]["1.8"]["ldr"][0]  # empty bin -> NaN
    assert rep["extras"]["mean_points_per_detected"]["1.8"]["small"] == pytest.approx(4.0)  # (7 + 1) / 2
    assert rep["extras"]["vehicles_per_frame"]["small"] == pytest.approx(2.0)
    ex = st.example_frames()
    assert ex is not None and set(ex.frames) == {"0.5", "1.8"}
    md = ability_markdown(rep)
    assert "| Large | 12 | 3 / 0.25 | 6 / 0.50 |" in md


def test_precomputed_counts_and_input_checks():
    st = AbilityStudy()
    f = frame([car(10, 0), car(20, 0)], [])
    st.add(f, counts=np.array([3, 0]))
    assert cell(st.report(), "1.8", "small", "all")["detected"] == 1
    with pytest.raises(ValueError, match="counts has shape"):
        st.add(f, counts=np.array([1]))
    with pytest.raises(ValueError, match="thresholds must start with 1"):
        AbilityStudy(thresholds=(5, 10))


def test_empty_frames_and_json_nan():
    from detbench.utils.atomic import to_json

    st = AbilityStudy()
    st.add(frame(np.zeros((0, 7)), [[1, 2, 3]]))
    rep = st.report()
    assert cell(rep, "1.8", "small", "top3") == {"total": 0, "detected": 0, "ldr": rep["heights"]["1.8"]["small"][
        "top3"]["ldr"]}
    assert json.loads(to_json(rep))["heights"]["1.8"]["small"]["all"]["ldr"] is None


# ----------------------------------------------------------------------------- figures and the tool

def _study_dataset(root, instants=4):
    """A small dataset whose points hit some boxes: points on each box top, fewer at lower heights."""
    rng = np.random.default_rng(1)
    with DatasetWriter(root, [0.5, 1.8], {"kind": "test"}) as w:
        for i in range(instants):
            fid = f"{i // 2:04d}_{i % 2:03d}"
            m = 12
            boxes = np.array([car(x, y, rng.uniform(-0.2, 0.2)) for x, y in
                              zip(rng.uniform(3, 140, m), rng.choice([-7.0, -3.5, 0.0, 3.5, 7.0], m))], np.float32)
            lanes = np.round(boxes[:, 1] / 3.5).astype(np.int64)
            frames = []
            for h, share in ((0.5, 0.4), (1.8, 0.8)):
                hit = rng.uniform(size=m) < share
                pts = [np.c_[b[0] + rng.uniform(-1.5, 1.5, 20), b[1] + rng.uniform(-0.8, 0.8, 20), np.full(20, 1.0)]
                       for b, k in zip(boxes, hit) if k]
                road = np.c_[rng.uniform(0, 100, 2000), rng.uniform(-15, 15, 2000), np.zeros(2000)]
                pts = np.vstack(pts + [road])
                pts = np.c_[pts, rng.uniform(0, 1, len(pts))].astype(np.float32)
                frames.append(Frame(fid, fid[:4], pts, boxes, np.array(["car"] * m), np.arange(m), lanes,
                                    Sensor(height=h), {}, 0.5 * i))
            w.add(frames)


def test_analyze_tool_on_disk_dataset(tmp_path, analyze_main):
    data = tmp_path / "ds"
    _study_dataset(data)
    out = tmp_path / "out"
    assert analyze_main(["--data", data, "--out", out, "--no-progress"]) == 0
    rep = json.loads((out / "ability.json").read_text())
    assert rep["num_frames"] == 4 and list(rep["heights"]) == ["0.5", "1.8"]
    for h in rep["heights"]:
        assert set(rep["heights"][h]) == {"small", "moderate", "large"}
        for r in rep["heights"][h].values():
            assert set(r) == {"all", "top3", "top6"}
            for c in r.values():
                assert set(c) == {"total", "detected", "ldr"} and isinstance(c["total"], int)
    assert cell(rep, "1.8", "large", "all")["detected"] > cell(rep, "0.5", "large", "all")["detected"]
    assert {"min_points", "ldr_vs_distance", "source"} <= set(rep["extras"])
    for name in ("ability.md", "ability_by_range.png", "ability_by_level.png", "ldr_vs_distance.png",
                 "bev_example.png"):
        p = out / name
        assert p.is_file() and p.stat().st_size > 1000, name
    assert (out / "bev_example.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| Range | Total | 0.5 m Number / LDR | 1.8 m Number / LDR |" in (out / "ability.md").read_text()


def test_analyze_tool_reports_bad_frame(tmp_path, analyze_main):
    data = tmp_path / "ds"
    _study_dataset(data)
    np.save(data / "points" / "1.8" / "0001_000.npy", np.zeros((2, 3), np.float32))
    argv = ["--data", data, "--out", tmp_path / "o", "--no-progress", "--no-figures"]
    with pytest.raises(SystemExit, match=r"0001_000\.npy: points array has shape \(2, 3\)"):
        analyze_main(argv)
    assert analyze_main(argv + ["--skip-bad"]) == 0
    rep = json.loads((tmp_path / "o" / "ability.json").read_text())
    assert rep["num_frames"] == 3 and len(rep["extras"]["source"]["skipped"]) == 1


def test_analyze_tool_simulated_end_to_end(tmp_path, analyze_main):
    out = tmp_path / "sim"
    assert analyze_main(["--simulate", 6, "--heights", 0.5, 1.0, 1.8, "--seed", 3, "--out", out,
                         "--json", tmp_path / "r.json", "--no-progress"]) == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["num_frames"] == 6 and list(rep["heights"]) == ["0.5", "1.0", "1.8"]
    totals = {cell(rep, h, "large", "all")["total"] for h in rep["heights"]}
    assert len(totals) == 1  # the same traffic at every height
    for h in rep["heights"]:
        c = cell(rep, h, "large", "all")
        assert 0 <= c["detected"] <= c["total"]
    for name in ("ability.md", "ability_by_range.png", "ability_by_level.png", "ldr_vs_distance.png",
                 "bev_example.png"):
        assert (out / name).is_file(), name


def test_simulator_counts_match_points_in_boxes(tmp_path, analyze_main):
    """The fast path (simulator hit counts, no points) and full clouds + points_in_boxes give the same report."""
    common = ["--simulate", 3, "--heights", 0.5, 1.8, "--seed", 11, "--no-progress", "--no-figures"]
    assert analyze_main(common + ["--out", tmp_path / "a"]) == 0
    assert analyze_main(common + ["--out", tmp_path / "b", "--points"]) == 0
    a = json.loads((tmp_path / "a" / "ability.json").read_text())
    b = json.loads((tmp_path / "b" / "ability.json").read_text())
    assert a["heights"] == b["heights"] and a["extras"]["min_points"] == b["extras"]["min_points"]
    assert a["extras"]["ldr_vs_distance"] == b["extras"]["ldr_vs_distance"]
    assert cell(a, "0.5", "large", "all")["total"] > 0


# ----------------------------------------------------------------------------- sampling uncertainty

def _scene_study(ldrs_05, ldrs_18=None, vehicles=10, frames=4, bootstrap=400, seed=0):
    """Scenes with a known LDR each: `vehicles` cars in the small range per frame, the first
    round(ldr x vehicles) detected (counts given, no points needed)."""
    st = AbilityStudy(thresholds=(1,), keep_example=False, bootstrap=bootstrap, bootstrap_seed=seed)
    boxes = [car(4.0 + 4.5 * k, 0.0) for k in range(vehicles)]
    for s, l05 in enumerate(ldrs_05):
        l18 = l05 if ldrs_18 is None else ldrs_18[s]
        for i in range(frames):
            fid = f"{s:04d}_{i:03d}"
            fs, cs = [], []
            for h, ldr in ((0.5, l05), (1.8, l18)):
                fs.append(frame(boxes, [], height=h, fid=fid))
                cs.append((np.arange(vehicles) < round(ldr * vehicles)).astype(np.int64))
            st.add(fs, counts=cs)
    return st


def test_bootstrap_interval_covers_the_estimate_and_shrinks_with_scenes():
    few = _scene_study([0.4, 0.9, 0.6, 0.7]).report()["extras"]["uncertainty"]
    many = _scene_study([0.4, 0.9, 0.6, 0.7] * 9).report()["extras"]["uncertainty"]
    assert few["clusters"] == "scene" and few["num_clusters"] == 4 and many["num_clusters"] == 36
    lo, hi = few["heights"]["0.5"]["small"]["all"]["ci95"]
    assert lo < 0.65 < hi and 0.4 <= lo and hi <= 0.9  # the pooled 0.65 inside, within the scenes' range
    mlo, mhi = many["heights"]["0.5"]["small"]["all"]["ci95"]
    assert mlo < 0.65 < mhi and (mhi - mlo) < 0.6 * (hi - lo)  # 9x the scenes: about a third of the width
    # one scene's scatter: the sample std of 0.4 / 0.9 / 0.6 / 0.7
    assert few["heights"]["0.5"]["small"]["all"]["scene_std"] == pytest.approx(np.std([0.4, 0.9, 0.6, 0.7], ddof=1),
                                                                               abs=1e-6)
    # deterministic for a seed, different for another
    again = _scene_study([0.4, 0.9, 0.6, 0.7]).report()["extras"]["uncertainty"]
    other = _scene_study([0.4, 0.9, 0.6, 0.7], seed=1).report()["extras"]["uncertainty"]
    assert again == few and other["heights"] != few["heights"]


def test_paired_height_difference_is_tight_when_heights_move_together():
    # every scene: 1.8 m sees exactly 0.2 more than 0.5 m, whatever the scene's level
    st = _scene_study([0.3, 0.7, 0.5, 0.6, 0.4], ldrs_18=[0.5, 0.9, 0.7, 0.8, 0.6])
    unc = st.report()["extras"]["uncertainty"]
    d = unc["differences"]["1.8-0.5"]["small"]["all"]
    assert d["diff"] == pytest.approx(0.2) and d["ci95"] == pytest.approx([0.2, 0.2])
    wide = unc["heights"]["0.5"]["small"]["all"]["ci95"]
    assert wide[1] - wide[0] > 0.1  # the LDR itself is uncertain; the paired difference is not
    # identical heights: a zero difference exactly
    same = _scene_study([0.3, 0.7]).report()["extras"]["uncertainty"]["differences"]["1.8-0.5"]["small"]["all"]
    assert same == {"diff": 0.0, "ci95": [0.0, 0.0]}


def test_uncertainty_needs_two_scenes_and_frames_without_scene_count_alone():
    one = _scene_study([0.5]).report()["extras"]["uncertainty"]
    assert one["num_clusters"] == 1 and "note" in one
    assert one["heights"]["0.5"]["small"]["all"] == {"ci95": None, "scene_std": None, "vehicles_per_frame_ci95": None}
    off = _scene_study([0.5, 0.7], bootstrap=0).report()["extras"]["uncertainty"]
    assert off["heights"]["0.5"]["small"]["all"]["ci95"] is None
    with pytest.raises(ValueError, match="bootstrap"):
        AbilityStudy(bootstrap=-1)
    st = AbilityStudy(thresholds=(1,), keep_example=False, bootstrap=200)
    for i in range(3):
        f = frame([car(10, 0)], [], fid=f"f{i}")
        f.scene_id = ""
        st.add(f, counts=np.array([i % 2]))
    unc = st.report()["extras"]["uncertainty"]
    assert unc["clusters"] == "frame" and unc["num_clusters"] == 3
    md = ability_markdown(_scene_study([0.4, 0.9, 0.6]).report())
    assert "## Sampling uncertainty" in md and "1.8-0.5 m difference" in md


# ----------------------------------------------------------------------------- the Markdown, pinned

def _golden_study(heights, scenes=5, frames=3, vary_traffic=False, scene_ids=True):
    """A fixed study: per frame 14 cars over the three ranges and five lanes; counts drawn from a seeded
    generator, fewer points on a car at lower heights. `vary_traffic` drops the last car at the lowest height,
    so totals differ between heights."""
    rng = np.random.default_rng(5)
    st = AbilityStudy(bootstrap=200, bootstrap_seed=2, keep_example=False)
    for s in range(scenes):
        for i in range(frames):
            fid = f"{s:04d}_{i:03d}"
            xs = rng.uniform(2, 148, 14)
            ys = rng.choice([-7.0, -3.5, 0.0, 3.5, 7.0, 12.0], 14) + rng.uniform(-0.4, 0.4, 14)
            boxes = [car(x, y) for x, y in zip(xs, ys)]
            lanes = np.round(np.asarray(ys) / 3.5).astype(np.int64)
            fs, cs = [], []
            for j, h in enumerate(heights):
                keep = len(boxes) - 1 if vary_traffic and j == 0 else len(boxes)
                f = frame(boxes[:keep], [], lanes[:keep], height=h, fid=fid)
                if not scene_ids:
                    f.scene_id = ""
                share = 0.45 + 0.2 * j
                cs.append(np.where(rng.uniform(size=keep) < share, rng.integers(1, 40, keep), 0))
                fs.append(f)
            st.add(fs, counts=cs)
    return st


def test_ability_markdown_is_pinned():
    """Every table of ability.md for fixed reports: the paper's three heights (with the paper's tables beside
    ours), two heights with different traffic (totals per height) and frames without a scene id, and none."""
    three = _golden_study([0.5, 1.0, 1.8]).report(source={"kind": "test", "seed": 4, "nested": {"a": 1}})
    two = _golden_study([0.5, 1.8], vary_traffic=True, scene_ids=False).report()
    empty = AbilityStudy().report(source={"kind": "empty"})
    text = "\n\n<!-- next report -->\n\n".join(
        [ability_markdown(three), ability_markdown(two, title="Two heights"), ability_markdown(empty)])
    assert_golden("ability.md", text)
