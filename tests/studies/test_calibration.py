"""detbench.studies.calibration (Tables IV-VI criteria, decomposition, judging over seeds, precision, pass
rates) and tools/check_calibration.py end to end."""
import json

import numpy as np
import pytest

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies import calibration as cc
from detbench.studies.ability import PAPER_TABLES, decomposition, paper_decomposition
import tools.check_calibration

ALL, TOP3, TOP6 = (LEVELS.index(lv) for lv in ("all", "top3", "top6"))
SMALL, MODERATE, LARGE = range(3)


@pytest.fixture
def tool():
    return tools.check_calibration


def test_the_papers_own_counts_pass():
    res = cc.check_counts(cc.paper_counts(), cc.PAPER_FRAMES)
    assert res["ok"] and all(res[k] for k in cc.CRITERIA)
    assert res["worst_abs_deviation"] < 0.006  # the tables' LDRs are their counts, rounded
    assert res["worst_total_ratio_error"] == pytest.approx(0.0, abs=1e-12)
    assert res["worst_second_deviation"] == pytest.approx(0.0, abs=1e-12)


def test_paper_decomposition_is_the_tables_differences():
    ldr, per_frame = cc.paper_decomposition()
    # second-in-lane, small, 0.5 m: (11923 - 9725) / (13661 - 9949);
    # beyond-Top6, small, 0.5 m: (12638 - 11923) / (17268 - 13661)
    assert ldr[SMALL, 0, 0] == pytest.approx((11923 - 9725) / (13661 - 9949))
    assert ldr[SMALL, 1, 0] == pytest.approx((12638 - 11923) / (17268 - 13661))
    assert per_frame[SMALL, 0] == pytest.approx((13661 - 9949) / 8000)
    # the ability study's own decomposition of the same tables agrees
    other = paper_decomposition()
    assert other["second"]["1.8"]["large"]["ldr"] == pytest.approx(ldr[LARGE, 0, 2])
    assert other["beyond"]["1.0"]["moderate"]["total"] == 39455 - 20407


def test_each_criterion_can_fail():
    paper = cc.paper_counts().astype(float)
    f = cc.PAPER_FRAMES
    # 1. a Top6 cell 0.06 high, the rest on the paper: the tolerance fails (and with it the second-in-lane LDR
    #    derived from that cell, and the 0.5 / 1.0 m pair), the totals and the height order hold
    high = paper.copy()
    high[SMALL, TOP6, 1] += 0.06 * high[SMALL, TOP6, 0]
    res = cc.check_counts(high, f)
    assert not res["within_tolerance"] and res["totals_close"] and res["high_above_low"] and not res["ok"]
    assert res["worst_abs_deviation"] == pytest.approx(0.06 + abs(11923 / 13661 - 0.87), abs=1e-6)
    # 2. a fifth more vehicles per frame at the same LDRs: only the totals fail (20 % > 15 %)
    more = paper * 1.2
    res = cc.check_counts(more, f)
    assert not res["totals_close"] and res["within_tolerance"] and res["second_close"] and not res["ok"]
    assert res["worst_total_ratio_error"] == pytest.approx(0.2)
    assert cc.check_counts(paper * 1.14, f)["totals_close"]
    # 3. second-in-lane vehicles seen 0.08 less often, the Top3 and Top6 LDRs kept within 0.05
    low2 = paper.copy()
    n_second = paper[MODERATE, TOP6, 0] - paper[MODERATE, TOP3, 0]
    low2[MODERATE, TOP6, 1] -= 0.08 * n_second
    res = cc.check_counts(low2, f)
    assert res["within_tolerance"] and not res["second_close"] and not res["ok"]
    assert res["worst_second_deviation"] == pytest.approx(0.08, abs=0.005)
    # 4. 1.8 m no better than 0.5 m in one cell
    flat = paper.copy()
    flat[LARGE, TOP3, 3] = flat[LARGE, TOP3, 1]
    res = cc.check_counts(flat, f, tolerance=1.0, second_tolerance=1.0)
    assert res["within_tolerance"] and not res["high_above_low"] and not res["ok"]
    # 5. 0.5 m and 1.0 m 0.04 apart in one cell
    apart = paper.copy()
    apart[SMALL, ALL, 2] = apart[SMALL, ALL, 1] - 0.04 * apart[SMALL, ALL, 0]
    res = cc.check_counts(apart, f)
    assert not res["low_pair_close"] and res["within_tolerance"] and not res["ok"]
    # a range without vehicles: undefined, fails
    empty = paper.copy()
    empty[MODERATE] = 0
    res = cc.check_counts(empty, f)
    assert not res["ok"] and res["worst_abs_deviation"] is None


def test_check_counts_rejects_bad_shapes():
    with pytest.raises(ValueError, match="3 ranges, 3 levels, 4"):
        cc.check_counts(np.zeros((3, 4)), 10)
    with pytest.raises(ValueError, match="frames"):
        cc.check_counts(cc.paper_counts(), 0)


def _seed_result(shift: float) -> dict:
    """check_counts of the paper's counts with every detected count moved by shift x total."""
    c = cc.paper_counts().astype(float)
    c[..., 1:] += shift * c[..., :1]
    return cc.check_counts(c, cc.PAPER_FRAMES, tolerance=1.0)


def test_judge_seeds_counts_seeds_within_and_the_pooled_bar():
    seeds = {str(k): _seed_result(0.0) for k in range(5)}
    seeds["5"] = _seed_result(0.06)  # one seed off in every cell: allowed (5 of 6)
    pooled = _seed_result(0.01)
    judged = cc.judge_seeds(seeds, pooled)
    assert judged["verdict"]["cells_per_seed"] and judged["verdict"]["cells_pooled"] and judged["verdict"]["ok"]
    assert int(judged["seeds_within"].min()) == 5 and judged["seeds_needed"] == 5
    # two seeds off: 4 of 6, fails
    seeds["4"] = _seed_result(-0.06)
    judged = cc.judge_seeds(seeds, pooled)
    assert not judged["verdict"]["cells_per_seed"] and not judged["verdict"]["ok"]
    assert judged["worst_seed_deviation"].max() == pytest.approx(0.06 + 0.006, abs=0.01)
    # pooled off by 0.04 (> 0.03) with every seed within 0.05: fails on the pooled bar alone
    seeds = {str(k): _seed_result(0.04) for k in range(6)}
    judged = cc.judge_seeds(seeds, _seed_result(0.04))
    assert judged["verdict"]["cells_per_seed"] and not judged["verdict"]["cells_pooled"] and not judged["verdict"]["ok"]


def test_scene_counts_layout_and_ability_decomposition():
    from detbench.data.frame import Frame, Sensor
    from detbench.studies.ability import AbilityStudy

    # one instant: ego lane holds three vehicles at 10, 20, 30 m, the left lane one at 15 m; only the first two
    # ego-lane vehicles and the left one are hit
    boxes = np.array([[10, 0, 0.75, 4.5, 1.8, 1.5, 0], [20, 0, 0.75, 4.5, 1.8, 1.5, 0],
                      [30, 0, 0.75, 4.5, 1.8, 1.5, 0], [15, 3.5, 0.75, 4.5, 1.8, 1.5, 0]], float)
    lanes = np.array([0, 0, 0, 1])
    hits = np.array([5, 2, 0, 9])

    frames = [Frame(frame_id="0000_000", scene_id="0000", points=np.zeros((0, 4), np.float32), boxes=boxes,
                    classes=np.array(["car"] * 4), track_ids=np.arange(4), lanes=lanes,
                    sensor=Sensor(height=float(h)), ego={}) for h in cc.HEIGHTS]
    for f in frames:
        f.hit_counts = hits
    S = cc.scene_counts([frames])
    assert S.shape == (1, 3, 3, 4)
    small = S[0, SMALL]
    assert small[ALL].tolist() == [4, 3, 3, 3] and small[TOP3].tolist() == [2, 2, 2, 2]
    assert small[TOP6].tolist() == [3, 3, 3, 3]
    dec = cc.decompose(S[0])
    assert dec[SMALL, 0].tolist() == [1, 1, 1, 1]  # the second ego-lane vehicle, hit
    assert dec[SMALL, 1].tolist() == [1, 0, 0, 0]  # the third, hidden
    study = AbilityStudy(thresholds=(1,), keep_example=False, bootstrap=0)
    study.add(frames, counts=[hits] * 3)
    rep = study.report()
    assert rep["extras"]["decomposition"]["beyond"]["0.5"]["small"] == {"total": 1, "detected": 0, "ldr": 0.0}
    assert decomposition(rep["heights"])["second"]["1.8"]["small"]["detected"] == 1


def test_tiny_run_writes_json_and_markdown(tmp_path, tool):
    out = tmp_path / "cal"
    rc = tool.main(["--seeds", "0", "--frames", "40", "--frames-per-scene", "20", "--block-frames", "20",
                    "--out", str(out), "--no-progress"])
    assert rc == 0
    rep = json.loads((out / "calibration.json").read_text())
    runs = rep["seeds"]["0"]["runs"]
    assert set(runs) == {"all", "block 0", "block 1"}
    tot = sum(runs[k]["vehicles_per_frame"]["all"]["large"] for k in ("block 0", "block 1")) / 2
    assert runs["all"]["vehicles_per_frame"]["all"]["large"] == pytest.approx(tot, abs=1e-3)
    for lv in LEVELS:
        for r in RANGE_NAMES:
            for h in cc.HEIGHTS:
                v = runs["all"]["ldr"][lv][r][h]
                assert v is None or 0.0 <= v <= 1.0
    assert set(runs["all"]["decomposition_ldr"]) == {"second", "beyond"}
    assert rep["preset"] == "paper" and rep["calibration"] == "v3"  # the default preset is calibration v3
    md = (out / "calibration.md").read_text()
    assert "| 0 | all (40) |" in md and "### Top6 (Table VI)" in md and "second-in-lane (Top6 - Top3)" in md
    assert "(paper preset, calibration v3)" in md


def test_judges_the_preset_it_is_given(tmp_path, tool):
    # --sim-preset v1 judges calibration v1's world: its id in the report, and other traffic than the default's
    runs = {}
    for preset in ("paper", "v1"):
        out = tmp_path / preset
        assert tool.main(["--seeds", "0", "--frames", "20", "--frames-per-scene", "20", "--sim-preset", preset,
                          "--out", str(out), "--no-progress"]) == 0
        runs[preset] = json.loads((out / "calibration.json").read_text())
    assert runs["v1"]["preset"] == "v1" and runs["v1"]["calibration"] == "v1"
    assert "(v1 preset, calibration v1)" in (tmp_path / "v1" / "calibration.md").read_text()
    vpf = [runs[p]["seeds"]["0"]["runs"]["all"]["vehicles_per_frame"] for p in ("paper", "v1")]
    assert vpf[0] != vpf[1]


def test_bad_arguments_exit_2(tmp_path, capsys, tool):
    assert tool.main(["--frames", "40", "--frames-per-scene", "20", "--block-frames", "30",
                      "--out", str(tmp_path)]) == 2
    assert "multiple of the frames per scene" in capsys.readouterr().err
    assert tool.main(["--set", "traffic.no_such_key=1", "--out", str(tmp_path)]) == 2
    assert tool.main(["--allowed-misses", "-1", "--out", str(tmp_path)]) == 2


def test_pooled_row_sums_the_seeds_and_judges(tmp_path, tool):
    out = tmp_path / "cal"
    assert tool.main(["--seeds", "0", "1", "--frames", "20", "--frames-per-scene", "20",
                      "--out", str(out), "--no-progress"]) == 0
    rep = json.loads((out / "calibration.json").read_text())
    per_seed = [rep["seeds"][s]["runs"]["all"]["vehicles_per_frame"]["all"]["large"] for s in ("0", "1")]
    assert rep["pooled"]["frames"] == 40 and rep["pooled"]["seeds"] == [0, 1]
    assert rep["pooled"]["vehicles_per_frame"]["all"]["large"] == pytest.approx(sum(per_seed) / 2, abs=1e-3)
    assert "| pooled | all seeds (40) |" in (out / "calibration.md").read_text()
    assert set(rep["verdict"]) >= {"ok", "cells_per_seed", "cells_pooled", "totals_pooled", "second_pooled"}
    assert rep["verdict"]["seeds_needed"] == 1
    for lv in LEVELS:
        for r in RANGE_NAMES:
            for h in cc.HEIGHTS:
                seeds = [rep["seeds"][s]["runs"]["all"]["ldr"][lv][r][h] for s in ("0", "1")]
                pooled = rep["pooled"]["ldr"][lv][r][h]
                if None not in seeds:  # a pooled LDR is a count-weighted mean of the seeds' LDRs
                    assert min(seeds) - 1e-4 <= pooled <= max(seeds) + 1e-4


def test_bootstrap_intervals_hold_the_pooled_value():
    rng = np.random.default_rng(0)
    paper = cc.paper_counts().astype(float)
    scenes = np.stack([np.round(paper / 40 * rng.uniform(0.8, 1.2)) for _ in range(40)])
    scenes[..., 1:] = np.minimum(scenes[..., 1:], scenes[..., :1])
    iv = cc.bootstrap_intervals(scenes, 200, replicates=300)
    pooled = cc.ratios(scenes.sum(0))
    lo, hi = iv["ldr"][SMALL][TOP6][0]
    assert lo <= pooled[SMALL, TOP6, 0] <= hi and hi - lo < 0.1
    lo, hi = iv["vehicles_per_frame"][LARGE][ALL]
    assert lo <= scenes[:, LARGE, ALL, 0].sum() / (40 * 200) <= hi
    assert cc.bootstrap_intervals(scenes[:1], 200)["ldr"] is None


def test_precision_from_scene_scatter():
    paper, _ = cc.paper_arrays()
    rng = np.random.default_rng(0)
    ldr = np.clip(paper[None] + rng.normal(0, 0.1, (50,) + paper.shape), 0, 1)
    scenes = np.concatenate([np.full((50, 3, 3, 1), 1000.0), np.round(ldr * 1000)], axis=-1)
    p = cc.precision(scenes, 0.05, 10)
    std = p["scene_std"]["all"]["large"]["0.5"]
    assert 0.07 < std < 0.13 and p["scenes"] == 50 and p["scenes_per_block"] == 10
    assert p["half_width_95_at_block"]["all"]["large"]["0.5"] == pytest.approx(1.96 * std / np.sqrt(10), abs=1e-3)
    pooled = p["pooled_ldr"]["all"]["large"]["0.5"]
    expect = np.ceil((1.96 * std / (0.05 - abs(pooled - 0.63))) ** 2)
    assert p["scenes_needed"]["all"]["large"]["0.5"] == pytest.approx(expect, abs=1)
    off = scenes.copy()
    off[:, SMALL, ALL, 1] = np.round(off[:, SMALL, ALL, 0] * 0.5)  # 0.5 against the paper's 0.73
    assert cc.precision(off, 0.05, 10)["scenes_needed"]["all"]["small"]["0.5"] is None


def test_block_pass_rate_counts_passing_draws():
    paper = cc.paper_counts().astype(float) / 40  # one scene of 200 frames: the paper's rates per frame
    on = np.repeat(paper[None], 20, axis=0)
    assert cc.block_pass_rate(on, 10, 200)["ok"] == 1.0
    low = on.copy()
    low[:, LARGE, ALL, 3] -= 0.08 * low[:, LARGE, ALL, 0]  # 1.8 m large 0.08 low in every scene
    r = cc.block_pass_rate(low, 10, 200)
    assert r["ok"] == 0.0 and r["within"] == 0.0
    assert cc.block_pass_rate(on[:3], 10, 200)["ok"] is None


def test_paper_tables_are_consistent():
    # Top3 within Top6 within All, in totals and detected counts, every range and height
    for r in RANGE_NAMES:
        t3, t6, a = (PAPER_TABLES[lv][r] for lv in ("top3", "top6", "all"))
        assert t3[0] <= t6[0] <= a[0]
        for h in cc.HEIGHTS:
            assert t3[1][h][0] <= t6[1][h][0] <= a[1][h][0]


# ----------------------------------------------------------------------------- the check's output, pinned

def _paper_like_scenes(seed: int, frames: int, frames_per_scene: int, cfg, progress) -> np.ndarray:
    """Stand-in for the simulator: scene counts near the paper's tables, drawn from `seed` (detected <= total)."""
    rng = np.random.default_rng(seed)
    per_scene = cc.paper_counts().astype(float) * frames_per_scene / cc.PAPER_FRAMES
    scenes = np.stack([np.round(per_scene * rng.uniform(0.85, 1.15, per_scene.shape))
                       for _ in range(frames // frames_per_scene)]).astype(np.int64)
    scenes[..., 1:] = np.minimum(scenes[..., 1:], scenes[..., :1])
    return scenes


@pytest.mark.parametrize("name, options", [
    ("one_seed_blocks", dict(seeds=[0], frames=800, frames_per_scene=100, block_frames=400)),
    ("three_seeds", dict(seeds=[0, 1, 2], frames=600, frames_per_scene=200, tolerance=0.04, allowed_misses=1)),
])
def test_check_calibration_output_is_pinned(monkeypatch, capsys, name, options):
    """calibration.json, calibration.md, the verdict and the printed lines of check_calibration for fixed scene
    counts (the simulator replaced by counts drawn near the paper's tables); wall-clock seconds are blanked."""
    import re

    from detbench.studies import calibration_check
    from tests.helpers import assert_golden

    monkeypatch.setattr(calibration_check, "simulated_scene_counts", _paper_like_scenes)
    report, md, failed = calibration_check.check_calibration(
        calibration_check.CalibrationOptions(no_progress=True, **options))
    printed = re.sub(r" in \d+ s,", " in N s,", capsys.readouterr().out)
    for seed in report["seeds"].values():
        seed["seconds"] = "N"
    text = "\n".join([f"failed: {failed}", "--- printed", printed, "--- calibration.md", md, "--- calibration.json",
                      json.dumps(report, indent=1)]) + "\n"
    assert_golden(f"calibration_{name}.txt", text)
