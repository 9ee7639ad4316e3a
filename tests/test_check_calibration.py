"""detbench.eval.calibration (the Table IV criteria, precision, pass rates) and tools/check_calibration.py end to end."""
import json

import numpy as np
import pytest

from detbench.data.regions import RANGE_NAMES
from detbench.eval import calibration as cc
from detbench.eval.ability import PAPER_TABLE_IV


@pytest.fixture
def tool(load_tool):
    return load_tool("check_calibration")


def paper_counts() -> np.ndarray:
    return np.array([[PAPER_TABLE_IV[r][0]] + [PAPER_TABLE_IV[r][1][h][0] for h in cc.HEIGHTS] for r in RANGE_NAMES])


def test_the_papers_own_counts_pass():
    res = cc.check_counts(paper_counts())
    assert res["ok"] and res["worst_abs_deviation"] < 0.006  # Table IV's LDRs are its counts, rounded


def test_each_criterion_can_fail():
    c = paper_counts().astype(float)
    high = c.copy()
    high[0, 2] = c[0, 0] * 0.79  # small at 1.0 m: 0.79 vs 0.73
    res = cc.check_counts(high)
    assert not res["within_tolerance"] and not res["low_pair_close"] and res["high_above_low"] and not res["ok"]
    assert res["worst_abs_deviation"] == pytest.approx(0.06, abs=1e-9)
    flat = c.copy()
    flat[2, 3] = flat[2, 1]  # large: 1.8 m no better than 0.5 m
    res = cc.check_counts(flat, tolerance=1.0)
    assert res["within_tolerance"] and not res["high_above_low"] and not res["ok"]
    empty = c.copy()
    empty[1] = 0  # no vehicle in the moderate range: undefined, fails
    res = cc.check_counts(empty)
    assert not res["ok"] and res["worst_abs_deviation"] is None


def test_tiny_run_writes_json_and_markdown(tmp_path, tool):
    out = tmp_path / "cal"
    rc = tool.main(["--seeds", "0", "--frames", "40", "--frames-per-scene", "20", "--block-frames", "20",
                  "--out", str(out), "--no-progress"])
    assert rc == 0
    rep = json.loads((out / "calibration.json").read_text())
    runs = rep["seeds"]["0"]["runs"]
    assert set(runs) == {"all", "block 0", "block 1"}
    tot = sum(runs[k]["vehicles_per_frame"]["large"] for k in ("block 0", "block 1")) / 2
    assert runs["all"]["vehicles_per_frame"]["large"] == pytest.approx(tot, abs=1e-3)
    for r in RANGE_NAMES:
        for h in cc.HEIGHTS:
            v = runs["all"]["ldr"][r][h]
            assert v is None or 0.0 <= v <= 1.0
    assert "| 0 | all (40) |" in (out / "calibration.md").read_text()


def test_bad_arguments_exit_2(tmp_path, capsys, tool):
    assert tool.main(["--frames", "40", "--frames-per-scene", "20", "--block-frames", "30", "--out", str(tmp_path)]) == 2
    assert "multiple of the frames per scene" in capsys.readouterr().err
    assert tool.main(["--set", "traffic.no_such_key=1", "--out", str(tmp_path)]) == 2


def test_pooled_row_sums_the_seeds(tmp_path, tool):
    out = tmp_path / "cal"
    assert tool.main(["--seeds", "0", "1", "--frames", "20", "--frames-per-scene", "20", "--block-frames", "0",
                    "--out", str(out), "--no-progress"]) == 0
    rep = json.loads((out / "calibration.json").read_text())
    per_seed = [rep["seeds"][s]["runs"]["all"]["vehicles_per_frame"]["large"] for s in ("0", "1")]
    assert rep["pooled"]["frames"] == 40 and rep["pooled"]["seeds"] == [0, 1]
    assert rep["pooled"]["vehicles_per_frame"]["large"] == pytest.approx(sum(per_seed) / 2, abs=1e-3)
    assert "| pooled | all seeds (40) |" in (out / "calibration.md").read_text()
    # a pooled LDR is a count-weighted mean of the seeds' LDRs: it lies between them
    for r in RANGE_NAMES:
        for h in cc.HEIGHTS:
            seeds = [rep["seeds"][s]["runs"]["all"]["ldr"][r][h] for s in ("0", "1")]
            pooled = rep["pooled"]["ldr"][r][h]
            if None not in seeds:
                assert min(seeds) - 1e-4 <= pooled <= max(seeds) + 1e-4


def test_precision_from_scene_scatter():
    paper, _ = cc.paper_arrays()
    rng = np.random.default_rng(0)
    # 50 scenes of 1000 vehicles per range whose LDRs scatter by 0.1 around the paper's
    ldr = np.clip(paper[None] + rng.normal(0, 0.1, (50, 3, 3)), 0, 1)
    scenes = np.concatenate([np.full((50, 3, 1), 1000.0), np.round(ldr * 1000)], axis=2)
    p = cc.precision(scenes, paper, 0.05, 10)
    std = p["scene_std"]["large"]["0.5"]
    assert 0.07 < std < 0.13 and p["scenes"] == 50 and p["scenes_per_block"] == 10
    assert p["half_width_95_at_block"]["large"]["0.5"] == pytest.approx(1.96 * std / np.sqrt(10), abs=1e-3)
    pooled = p["pooled_ldr"]["large"]["0.5"]
    expect = np.ceil((1.96 * std / (0.05 - abs(pooled - 0.63))) ** 2)
    assert p["scenes_needed"]["large"]["0.5"] == pytest.approx(expect, abs=1)
    # a pooled LDR off by more than the tolerance: no study length helps
    off = scenes.copy()
    off[:, 0, 1] = np.round(off[:, 0, 0] * 0.5)  # small at 0.5 m: 0.5 against the paper's 0.73
    assert cc.precision(off, paper, 0.05, 10)["scenes_needed"]["small"]["0.5"] is None
    # one scene: no scatter to speak of
    assert cc.precision(scenes[:1], paper, 0.05, None)["scene_std"]["small"]["1.8"] is None


def _scenes_at(ldr: np.ndarray, vehicles: float = 1000.0) -> np.ndarray:
    """Scene counts (scenes, 3, 4) with the given per-scene LDRs (scenes, 3, 3)."""
    return np.concatenate([np.full(ldr.shape[:2] + (1,), vehicles), np.round(ldr * vehicles)], axis=2)


def test_block_pass_rate_counts_passing_draws():
    paper, _ = cc.paper_arrays()
    on = _scenes_at(np.repeat(paper[None], 20, axis=0))
    assert cc.block_pass_rate(on, 10, 0.05, 0.03)["ok"] == 1.0
    # every scene 0.08 low at 1.8 m in the large range: no draw passes, yet the other criteria hold
    low = on.copy()
    low[:, 2, 3] -= 80
    r = cc.block_pass_rate(low, 10, 0.05, 0.03)
    assert r["ok"] == 0.0 and r["within"] == 0.0
    res = cc.check_counts(low.sum(0))
    assert res["high_above_low"] and res["low_pair_close"] and not res["within_tolerance"]
    # half the scenes on the paper, half 0.2 high at 0.5 m small: a 2-scene study passes only when both of its
    # scenes (drawn independently) are on it (one of each: mean +0.1, fails): P = 1/4
    mixed = on.copy()
    mixed[10:, 0, 1] += 200
    r = cc.block_pass_rate(mixed, 2, 0.05, 0.03, replicates=4000)
    assert r["ok"] == pytest.approx(0.25, abs=0.03)
    assert r["within"] == r["ok"]
    # a block longer than the scenes at hand: no estimate
    assert cc.block_pass_rate(on[:3], 10, 0.05, 0.03)["ok"] is None


def test_tiny_run_reports_precision(tmp_path, tool):
    out = tmp_path / "cal"
    assert tool.main(["--seeds", "0", "--frames", "60", "--frames-per-scene", "20", "--block-frames", "40",
                    "--out", str(out), "--no-progress"]) == 0
    rep = json.loads((out / "calibration.json").read_text())
    assert rep["precision"]["scenes"] == 3 and rep["precision"]["scenes_per_block"] == 2
    rates = rep["precision"]["pass_rate"]
    assert sorted(rates) == ["40", "60"]  # the block and the whole run
    rate = rates["40"]
    assert rate["scenes_per_block"] == 2 and rate["replicates"] == 2000 and 0.0 <= rate["ok"] <= rate["within"] <= 1.0
    assert 0.0 <= rates["60"]["ok"] <= rates["60"]["within"] <= 1.0 and rates["60"]["scenes_per_block"] == 3
    assert "Precision (all seeds' scenes)" in (out / "calibration.md").read_text()
