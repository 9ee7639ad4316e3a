"""The speed/accuracy trade study: Pareto fronts, the budget planner and its cost model, the
learning curve's time axis, the report, the sweep's points, and (slow) a reduced sweep end to end."""
import json
import math
import sys
import time

import numpy as np
import pytest

from detbench.config import ConfigError

from detbench.studies.executor import LocalExecutor, run_to_end
from detbench.studies.jobs import Job
from detbench.studies.tradeoff import (
    CostModel, Task, mark_pareto, pareto_flags, plan_within_budget, plot_learning_curves, plot_tradeoff,
    train_seconds_at_step, tradeoff_markdown, world_label,
)
from detbench.studies.tradeoff_points import KNOBS, fit_range, scale_widths, set_dotted, sweep_points
from detbench.utils.bench import median_p90
import tools.tradeoff



# ---- Pareto -------------------------------------------------------------------------------------
def test_pareto_flags_dominance_ties_and_missing():
    lat = [10.0, 20.0, 15.0, 30.0, 10.0, None, 5.0, 40.0]
    ap = [0.50, 0.70, 0.40, 0.70, 0.50, 0.90, float("nan"), 0.80]
    flags = pareto_flags(lat, ap)
    # 0 and 4 are identical (both on the front); 1 beats 3 (same AP, faster); 2 is beaten by 0;
    # 5 and 6 have no figure; 7 is the most accurate
    assert flags == [True, True, False, False, True, None, None, True]


def test_pareto_flags_single_and_strict():
    assert pareto_flags([1.0], [0.0]) == [True]
    assert pareto_flags([1.0, 1.0], [0.5, 0.6]) == [False, True]  # same latency: the more accurate wins
    assert pareto_flags([1.0, 2.0], [0.6, 0.6]) == [True, False]  # same AP: the faster wins
    with pytest.raises(ValueError, match="2 latencies but 1"):
        pareto_flags([1.0, 2.0], [0.5])


def _pt(model, name, lat, aps, device="cpu", trained="at this point"):
    return {"model": model, "point": name, "device": device, "trained": trained, "knob": name,
            "latency_ms": {"total": {"median": lat, "p90": lat * 1.1}, "head": {"median": lat / 2, "p90": lat / 2}},
            "peak_rss_mib": 400.0, "parameters": 1_000_000,
            "accuracy": {r: (None if a is None else {"ap_r40": a, "recall": a}) for r, a in
                         zip(("small", "moderate", "large"), aps)}}


def test_mark_pareto_groups_by_device_and_model():
    pts = [_pt("a", "p1", 10, (0.5, 0.4, 0.3)), _pt("a", "p2", 20, (0.6, 0.3, 0.2)),
           _pt("b", "p1", 5, (0.4, 0.5, None)), _pt("b", "p2", 50, (0.3, 0.2, 0.1)),
           _pt("a", "gpu", 100, (0.1, 0.1, 0.1), device="cuda")]
    mark_pareto(pts)
    assert [p["pareto"]["small"] for p in pts] == [True, True, True, False, True]
    assert [p["pareto"]["moderate"] for p in pts] == [False, False, True, False, True]
    assert [p["pareto"]["large"] for p in pts] == [True, False, None, False, True]
    # within model b, p2 is beaten by p1 in small and moderate but p1 has no large figure
    assert pts[3]["pareto_in_model"] == {"small": False, "moderate": False, "large": True}
    assert pts[0]["pareto_in_model"]["moderate"] is True  # a's own front: p1 beats p2 in moderate


# ---- the planner ----------------------------------------------------------------------------------
def test_plan_takes_needs_first_and_counts_shared_needs_once():
    tasks = [Task("train a", 100), Task("m a1", 10, ("train a",)), Task("m a2", 10, ("train a",)),
             Task("train b", 500), Task("m b", 10, ("train b",))]
    goals = ["m a1", "m b", "m a2"]
    p = plan_within_budget(tasks, 125, goals)
    assert p.run == ["train a", "m a1", "m a2"]  # b (510 s) does not fit; a2 only adds 10 s
    assert p.skipped == ["m b"] and "510.0 s" in p.reasons["m b"]
    assert p.cost_s == pytest.approx(120)
    full = plan_within_budget(tasks, None, goals)
    assert full.run == ["train a", "m a1", "train b", "m b", "m a2"] and not full.skipped


def test_plan_tries_cheaper_goals_after_a_skip_and_never_runs_a_need_alone():
    tasks = [Task("big", 50), Task("small", 5), Task("train", 30), Task("m", 1, ("train",))]
    p = plan_within_budget(tasks, 20, ["big", "m", "small"])
    assert p.run == ["small"] and p.skipped == ["big", "m"]
    assert "train" not in p.run  # not a goal: runs only as a need
    done = plan_within_budget([Task("train", 0), Task("m", 1, ("train",))], 2, ["m"])
    assert done.run == ["train", "m"]  # a finished need costs nothing


def test_plan_skips_a_goal_whose_goal_need_was_skipped():
    tasks = [Task("x", 100), Task("y", 1, ("x",))]
    p = plan_within_budget(tasks, 10, ["x", "y"])
    assert p.skipped == ["x", "y"] and "needs x" in p.reasons["y"]


def test_plan_rejects_bad_tasks():
    with pytest.raises(ValueError, match="not a task"):
        plan_within_budget([Task("a", 1, ("b",))], None)
    with pytest.raises(ValueError, match="cycle"):
        plan_within_budget([Task("a", 1, ("b",)), Task("b", 1, ("a",))], None)
    with pytest.raises(ValueError, match="costs are seconds >= 0"):
        plan_within_budget([Task("a", -1)], None)
    with pytest.raises(ValueError, match="listed twice"):
        plan_within_budget([Task("a", 1), Task("a", 2)], None)
    with pytest.raises(ValueError, match="goal 'z' is not a task"):
        plan_within_budget([Task("a", 1)], None, ["z"])


def test_cost_model_calibrates_per_model_then_across_models():
    cm = CostModel({"train": 100.0, "measure": 10.0, "overhead": 5.0})
    assert cm.estimate("train", "a", 2.0) == pytest.approx(205.0)
    cm.observe("train", "a", 1.0, 55.0)  # (55 - 5) / 100 = 0.5
    assert cm.estimate("train", "a", 2.0) == pytest.approx(105.0)
    assert cm.estimate("train", "b", 1.0) == pytest.approx(55.0)  # b borrows a's ratio
    cm.observe("train", "b", 1.0, 305.0)  # 3.0
    assert cm.estimate("train", "b", 1.0) == pytest.approx(305.0)
    assert cm.estimate("measure", "a") == pytest.approx(15.0)  # other kinds keep their prior
    cm.observe("measure", "a", 1.0, 1.0)  # below the overhead: a small ratio, not zero
    assert cm.estimate("measure", "a") > 5.0
    with pytest.raises(KeyError, match="no prior"):
        cm.estimate("nope", "a")


# ---- learning curve, timing rows ----------------------------------------------------------------------
def test_train_seconds_at_step_interpolates_within_epochs():
    hist = [{"global_step": 10, "seconds": 20.0}, {"global_step": 20, "seconds": 40.0}]
    assert train_seconds_at_step(hist, 0) == 0.0
    assert train_seconds_at_step(hist, 5) == pytest.approx(10.0)
    assert train_seconds_at_step(hist, 10) == pytest.approx(20.0)
    assert train_seconds_at_step(hist, 15) == pytest.approx(40.0)
    assert train_seconds_at_step(hist, 20) == pytest.approx(60.0)
    with pytest.raises(ValueError, match="past the history"):
        train_seconds_at_step(hist, 21)
    with pytest.raises(ValueError, match="must increase"):
        train_seconds_at_step([{"global_step": 10, "seconds": 1}, {"global_step": 10, "seconds": 1}], 15)


def test_median_p90():
    rows = [{"total": float(v), "head": 1.0} for v in range(1, 11)]  # 1..10
    out = median_p90(rows)
    assert out["total"] == {"median": 5.5, "p90": 9.1}
    assert out["head"] == {"median": 1.0, "p90": 1.0}
    assert median_p90([]) == {}


def test_peak_rss_resets_to_what_runs_after():
    from detbench.utils.bench import peak_rss_mib, reset_peak_rss, rss_mib

    if not reset_peak_rss() or rss_mib() is None:
        pytest.skip("no /proc/self/clear_refs here (not Linux, or refused)")
    big = np.ones(64 * 2 ** 20 // 8)  # 64 MiB touched
    high = peak_rss_mib()
    del big
    assert reset_peak_rss()
    assert high - peak_rss_mib() > 48  # the new peak starts from now, without the freed array
    assert peak_rss_mib() >= rss_mib() - 1


# ---- report ------------------------------------------------------------------------------------------
def test_markdown_marks_the_front_and_unmodelled_ranges(tmp_path):
    pts = [_pt("a", "preset", 10, (0.5, 0.4, 0.3), trained="preset model"),
           _pt("a", "region small", 6, (0.45, None, None)), _pt("a", "slow", 30, (0.1, 0.1, 0.1))]
    pts[1]["knob"], pts[1]["region_range"], pts[1]["point_cloud_range"] = "region", "small", [0, -6.4, 0, 54.4, 6.4, 4]
    pts[0]["knob"] = "preset"
    mark_pareto(pts)
    result = {"meta": {"preset": "smoke", "height": 1.8, "elapsed_s": 60.0, "budget_min": 2.0, "frames": 3},
              "points": pts, "curves": {"a": {"run": "runs/a/curve", "epochs": 2, "points": [
                  {"checkpoint": "epoch_001.pt", "epochs_done": 1.0, "train_wall_s": 30.0, "train_cpu_s": 45.0,
                   "accuracy": {"small": {"ap_r40": 0.2}, "moderate": {"ap_r40": 0.1}, "large": {"ap_r40": 0.0}}}]}},
              "skipped": [{"task": "measure a width x2", "estimated_s": 99.0, "reason": "too long"}],
              "failed": [{"task": "train a voxel", "error": "boom\nlast line"}]}
    md = tradeoff_markdown(result)
    assert md.splitlines()[0] == "# Speed / accuracy trade (smoke preset, 1.8 m, data source not recorded)"
    sim = {"kind": "simulator", "calibration": "v2", "seed": 3, "preset": "paper", "overrides": []}
    label = world_label({**result["meta"], "data_source": sim})
    assert label == "smoke preset, 1.8 m, simulator calibration v2, seed 3"
    rows = {ln.split(" | ")[1]: ln for ln in md.splitlines() if ln.startswith("| a |")}
    assert rows["preset"].endswith("**small, moderate, large** |")
    assert rows["region small"].endswith("**small** |") and rows["region small"].count("n/m") == 4
    assert rows["slow"].endswith("|  |")
    assert "| a | small | 54.4 / 6.4 | 6.0 / 10.0 | 0.450 / 0.500 |" in md
    assert "a / region small (6.0 ms, AP 0.450) -> a / preset (10.0 ms, AP 0.500)" in md
    assert "| epoch_001.pt | 1.00 | 0.50 | 0.75 | 0.200 | 0.100 | 0.000 |" in md
    assert "| measure a width x2 | 99 | too long |" in md and "| train a voxel | last line |" in md
    assert plot_tradeoff(pts, tmp_path / "t.png").stat().st_size > 10_000
    ends = {"a": {"train_cpu_s": 40.0, "accuracy": pts[0]["accuracy"]}}
    assert plot_learning_curves(result["curves"], tmp_path / "c.png", ends).stat().st_size > 10_000


# ---- the sweep's points (detbench.studies.tradeoff_points) -------------------------------------------------
@pytest.mark.parametrize("model", ["second", "pillarnet", "pointrcnn", "ct3d"])
def test_sweep_points_build_and_cover_the_knobs(model):
    import models
    from detbench.train.run_config import load_run_config

    mc = load_run_config(model, "smoke")["model"]
    pts = sweep_points(model, mc, KNOBS, "cpu", cores=4, default_threads=1, registry=models)
    assert pts[0].name == "preset" and not pts[0].train and not pts[0].infer
    assert len({p.id for p in pts}) == len(pts) >= 15
    knobs = {p.knob for p in pts}
    assert {"width", "region", "points", "precision", "threads", "joint"} <= knobs
    assert ("voxel" in knobs) == ("voxel_size" in mc) and ("proposals" in knobs) == (model in ("pointrcnn", "ct3d"))
    assert [p.infer["threads"] for p in pts if p.knob == "threads"] == [2, 4]
    # inference-only points share the preset's training; points with the same training share a run
    assert all(p.train_id == "preset" for p in pts if not p.train)
    fast = [p for p in pts if p.name in ("fast", "fast + bf16")]
    assert len(fast) == 2 and fast[0].train_id == fast[1].train_id != "preset"
    boxes = np.asarray([[20.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0]], np.float32)

    def n_params(cfg):
        m = models.build_model(model, models.prepare_model_config(model, cfg, boxes))
        return sum(t.numel() for t in m.parameters())

    params = {"preset": n_params(mc)}
    for p in pts:
        if not p.train:
            continue
        cfg = json.loads(json.dumps(mc))
        for key, value in p.train.items():
            if key.startswith("model."):  # the road knob's road.drop is a run-config key outside model:
                set_dotted(cfg, key.removeprefix("model."), value)
        params[p.name] = n_params(cfg)  # every trained point builds
        if p.region_range:
            from detbench.data.regions import RANGES

            _, x1, y = RANGES[p.region_range]
            pcr = cfg["point_cloud_range"]
            assert x1 < pcr[3] < mc["point_cloud_range"][3] and y < pcr[4] < mc["point_cloud_range"][4]
    assert params["width x0.5"] < params["preset"] < params["width x2"]


def test_fit_range_finds_the_smallest_grid_that_builds():
    import models
    from detbench.train.run_config import load_run_config

    mc = load_run_config("second", "smoke")["model"]  # 0.2 m voxels, BEV stride 16 -> 3.2 m steps
    assert fit_range("second", mc, 53.6, 6.0, registry=models) == [0.0, -6.4, -0.6, 54.4, 6.4, 4.2]
    assert fit_range("second", mc, 153.6, 16.0, registry=models) == [0.0, -16.0, -0.6, 153.6, 16.0, 4.2]
    pr = load_run_config("pointrcnn", "smoke")["model"]  # no grid: the range itself
    assert fit_range("pointrcnn", pr, 53.6, 6.0, registry=models) == [0.0, -6.0, -0.6, 53.6, 6.0, 4.2]


@pytest.mark.parametrize("model", ["second", "pillarnet", "ct3d", "pointrcnn"])
def test_road_knob_trains_the_opposite_drop_through_the_run_config(model):
    """The road knob is one trained point with road.drop flipped from the preset's, and its override is one
    that tools/train.py's --set accepts and the trained run config then holds."""
    import models
    from detbench.train.run_config import load_run_config

    cfg = load_run_config(model, "quick")
    drop = cfg["road"]["drop"]
    pts = sweep_points(model, cfg["model"], ["road"], "cpu", cores=2, default_threads=2, registry=models,
                       road_drop=drop)
    (road,) = [p for p in pts if p.knob == "road"]
    assert road.train == {"road.drop": not drop} and not road.infer and road.train_id != "preset"
    assert road.name == ("road kept" if drop else "road dropped")
    sets = [f"{k}={json.dumps(v)}" for k, v in road.train.items()]  # as the sweep passes them to tools/train.py
    trained = load_run_config(model, "quick", overrides=sets)
    assert trained["road"]["drop"] is (not drop) and trained["model"] == cfg["model"]
    assert "road" not in [p.knob for p in sweep_points(model, cfg["model"], ["width"], "cpu", cores=2,
                                                       default_threads=2, registry=models)]


def test_scale_widths():
    from detbench.train.run_config import load_run_config

    mc = load_run_config("ct3d", "cpu")["model"]
    half = scale_widths("ct3d", mc, 0.5)
    assert half["model.backbone3d.channels"] == [v // 2 for v in mc["backbone3d"]["channels"]]
    assert half["model.roi_head.hidden_dim"] % mc["roi_head"]["heads"] == 0
    with pytest.raises(ConfigError, match="unknown"):  # a model without a config has no width keys to read
        scale_widths("unknown", mc, 0.5)


def test_a_task_is_stopped_at_its_deadline_and_its_cpu_time_is_its_own(tmp_path):
    """The sweep's tasks on the study's executor: a task still running at the deadline gets the stop signal
    (a training's SIGTERM: it writes its checkpoint and exits), the log grows over reruns, and a task's CPU
    time is its own (a busy loop of about 0.3 s)."""
    ex = LocalExecutor(1, stream=False, env={}, append_logs=True)
    log = tmp_path / "log.txt"
    stopping = ("import signal, sys, time, pathlib\n"
                "def stop(*_):\n    pathlib.Path(sys.argv[1]).write_text('checkpoint')\n    sys.exit(130)\n"
                "signal.signal(signal.SIGTERM, stop)\nprint('started', flush=True)\ntime.sleep(60)\n")
    t0 = time.perf_counter()
    res = run_to_end(ex, Job("train", "train", "train", log=log),
                     [sys.executable, "-c", stopping, str(tmp_path / "ckpt")], deadline=time.perf_counter() + 2.0)
    assert res.timed_out and res.returncode == 130 and time.perf_counter() - t0 < 30
    assert (tmp_path / "ckpt").read_text() == "checkpoint" and not ex.running
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\nprint('hi')"
    res = run_to_end(ex, Job("measure", "measure", "measure", log=log), [sys.executable, "-c", busy])
    assert not res.timed_out and res.returncode == 0 and res.wall_s >= res.cpu_s >= 0.3
    text = log.read_text()
    assert "started" in text and "hi" in text and text.count("$ ") == 2


# ---- end to end (reduced) ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("data") / "sim"
    return simulate_dataset(root, frames=9, heights=[1.8], seed=3, frames_per_scene=3, progress=False)


@pytest.mark.slow
def test_reduced_smoke_sweep_writes_points_with_pareto_flags(tiny_dataset, tmp_path):
    """`tools/tradeoff.py --preset smoke` on one model and the inference-only knobs: at least five points,
    each with latency, memory, AP@R40 per range and a Pareto flag; a rerun reuses every point."""
    out = tmp_path / "t"
    argv = ["--preset", "smoke", "--models", "second", "--knobs", "points", "precision", "threads", "curve",
            "--frames", "2", "--warmup", "1", "--curve-points", "3", "--data", str(tiny_dataset), "--out", str(out),
            "--no-progress"]
    tool = tools.tradeoff
    assert tool.main(argv) == 0
    res = json.loads((out / "tradeoff.json").read_text())
    pts = res["points"]
    assert len(pts) >= 5 and {p["model"] for p in pts} == {"second"}
    for p in pts:
        lat = p["latency_ms"]["total"]
        assert 0 < lat["median"] <= lat["p90"] and p["peak_rss_mib"] > p["rss_before_model_mib"] > 0
        assert set(p["accuracy"]) == {"small", "moderate", "large"}
        for r in ("small", "moderate", "large"):
            ap = p["accuracy"][r]["ap_r40"]
            assert ap is None or 0.0 <= ap <= 1.0
            assert p["pareto"][r] in (True, False) or (p["pareto"][r] is None and ap is None)
        assert p["parameters"] > 0 and "voxelize" in p["latency_ms"]
    by = {p["point"]: p for p in pts}
    assert by["preset"]["trained"] == "preset model" and by["bf16"]["inference"] == {"precision": "bf16"}
    assert "subsample" in by["fps 4096 points"]["latency_ms"] and "subsample" not in by["preset"]["latency_ms"]
    assert by["random 4096 points"]["points_per_frame"] <= 4096
    assert any(any(v for v in p["pareto"].values()) for p in pts)  # some point is on a front
    assert (out / "tradeoff.md").read_text().count("| second |") == len(pts)
    assert (out / "tradeoff.md").read_text().splitlines()[0] == f"# Speed / accuracy trade ({world_label(res['meta'])})"
    assert "data source not recorded" not in world_label(res["meta"])  # the dataset's source is read
    assert (out / "tradeoff.png").stat().st_size > 10_000
    # the learning curve: a 4-epoch run (2 x the preset's 2), every checkpoint evaluated, time increasing
    curve = res["curves"]["second"]
    assert curve["epochs"] == 4 and curve["run"] == "runs/second/curve-4ep"
    steps = [e["global_step"] for e in curve["points"]]
    assert len(steps) >= 4 and steps == sorted(steps) and curve["points"][-1]["epochs_done"] == pytest.approx(4.0)
    cpu = [e["train_cpu_s"] for e in curve["points"]]
    assert all(b > a for a, b in zip(cpu, cpu[1:])) and cpu[0] > 0
    assert all(set(e["accuracy"]) == {"small", "moderate", "large"} for e in curve["points"])
    assert res["preset_run_ends"]["second"]["train_cpu_s"] > 0
    assert ((out / "learning_curve.png").stat().st_size > 10_000
            and "## Training budget" in (out / "tradeoff.md").read_text())
    before = {f: f.stat().st_mtime_ns for f in (out / "points").rglob("*.json")}
    assert tool.main(argv) == 0  # resumed: nothing measured again
    assert {f: f.stat().st_mtime_ns for f in (out / "points").rglob("*.json")} == before
    assert json.loads((out / "tradeoff.json").read_text())["curves"] == res["curves"]
    assert not math.isnan(json.loads((out / "tradeoff.json").read_text())["meta"]["elapsed_s"])
