"""tools/study.py's executors give the same study: one job at a time, two at once, and the jobs as Ray tasks."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

import models
from detbench.studies.study import StudyOptions, run_study
from tests.helpers import ROOT

SMOKE = ["train.epochs=1", "train.tensorboard=false", "study.models=[second]"]


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("data") / "sim"
    return simulate_dataset(root, frames=9, heights=[0.5, 1.8], seed=7, frames_per_scene=3, progress=False)


def comparable(out: Path) -> dict:
    """study.json without its timing fields (seconds, per second, minutes) and with the study's own folder replaced
    by OUT."""
    text = (out / "study.json").read_text().replace(str(out), "OUT")

    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if not any(t in k for t in ("seconds", "per_second", "minutes"))}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v

    return strip(json.loads(text))


def study(data: Path, out: Path, heights: list[float], **kw) -> dict:
    kw.setdefault("no_progress", True)
    run_study(StudyOptions(preset="smoke", heights=heights, data=str(data), out=str(out), overrides=SMOKE, **kw),
              registry=models, repo=ROOT)
    return comparable(out)


@pytest.mark.slow
def test_one_job_at_a_time_and_two_at_once_give_the_same_study(tiny_dataset, tmp_path):
    one = study(tiny_dataset, tmp_path / "one", [0.5, 1.8], jobs=1)
    two = study(tiny_dataset, tmp_path / "two", [0.5, 1.8], jobs=2, no_progress=False)
    assert one["models"] == ["second"] and one["summary"]["detectors"]
    assert one == two
    # two jobs at once write to their logs only, so they run without progress bars (no carriage returns)
    logs = sorted((tmp_path / "two" / "logs").glob("*.log"))
    assert len(logs) >= 5 and not [p.name for p in logs if "\r" in p.read_text()]
    assert "epoch 1/" in (tmp_path / "two" / "logs" / "train_second_h0.5.log").read_text()


@pytest.mark.slow  # about a minute: .ci/run runs it on its own after the default suite
def test_the_study_on_a_local_ray_instance_matches_the_local_executor(tiny_dataset, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[cluster]'): the cluster executor "
                                            "is not tested")
    local = study(tiny_dataset, tmp_path / "local", [0.5], jobs=1)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = study(tiny_dataset, tmp_path / "ray", [0.5], executor="ray", no_progress=False)
    finally:
        ray.shutdown()
    log = (tmp_path / "ray" / "logs" / "train_second_h0.5.log").read_text()
    assert "epoch 1/" in log and "\r" not in log  # a Ray task's output goes to its log only: no progress bars
    assert on_ray == local


@pytest.mark.slow
def test_seeds_train_each_run_once_per_seed_and_the_report_gives_the_spread(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "seeds"
    got = study(tiny_dataset, out, [0.5], jobs=2, seeds=[0, 1])
    # seed 0 is the config's train.seed: today's folder; seed 1 its own, trained with --set train.seed=1
    assert (out / "second_h0.5" / "eval_h0.5_test" / "report.json").is_file()
    assert (out / "second_h0.5_s1" / "eval_h0.5_test" / "report.json").is_file()
    rep = json.loads((out / "second_h0.5_s1" / "eval_h0.5_test" / "report.json").read_text())
    assert (rep["train_seed"], rep["train_preset"]) == (1, "smoke")  # the figures' titles name the preset
    rec = json.loads((out / "stage_inputs" / "train_second_h0.5_s1.json").read_text())
    assert rec["inputs"]["config"]["train"]["seed"] == 1
    assert json.loads((out / "stage_inputs" / "train_second_h0.5.json").read_text())["inputs"]["config"]["train"][
        "seed"] == 0
    assert got["seeds"]["seeds"] == [0, 1] and "0.5" in got["seeds"]["by_height"]
    comb = got["seeds"]["by_height"]["0.5"]["models"]["second"]
    assert comb["num_seeds"] == 2 and comb["seeds"] == [0, 1]
    md = (out / "study.md").read_text()
    assert "**Over the training seeds** 0, 1" in md and "seed sd" in md and "scene-only" in md
    # the one-table answer: seed means, the paper's Table VII recall beside them, the training minutes
    row = json.loads((out / "study.json").read_text())["seeds"]["table"][0]  # the table's data, unrounded
    minutes = row["train_minutes"]
    assert (row["model"], row["height"], row["num_seeds"]) == ("second", 0.5, 2)
    assert row["paper_recall"] == [0.97, 0.90, 0.85]
    assert minutes > 0 and "| second | 0.5 m | 2 | " in md and f"| 0.97 / 0.90 / 0.85 | {minutes:.1f} |" in md
    assert "| 0.5 m | large | Recall | second " in md and got["seeds"]["pairs"]["0.5"]["large"]["recall"]["pairs"] == []
    # the same command again: every job is kept
    capsys.readouterr()
    study(tiny_dataset, out, [0.5], jobs=2, seeds=[0, 1])
    assert "start train" not in capsys.readouterr().out
