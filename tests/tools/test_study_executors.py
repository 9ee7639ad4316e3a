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
    """study.json without its timing fields and with the study's own folder replaced by OUT."""
    text = (out / "study.json").read_text().replace(str(out), "OUT")

    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if "seconds" not in k and "per_second" not in k}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v

    return strip(json.loads(text))


def study(data: Path, out: Path, heights: list[float], **kw) -> dict:
    run_study(StudyOptions(preset="smoke", heights=heights, data=str(data), out=str(out), overrides=SMOKE,
                           no_progress=True, **kw), registry=models, repo=ROOT)
    return comparable(out)


@pytest.mark.slow
def test_one_job_at_a_time_and_two_at_once_give_the_same_study(tiny_dataset, tmp_path):
    one = study(tiny_dataset, tmp_path / "one", [0.5, 1.8], jobs=1)
    two = study(tiny_dataset, tmp_path / "two", [0.5, 1.8], jobs=2)
    assert one["models"] == ["second"] and one["summary"]["detectors"]
    assert one == two


def test_the_study_on_a_local_ray_instance_matches_the_local_executor(tiny_dataset, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install .[cluster]): the cluster executor "
                                            "is not tested")
    local = study(tiny_dataset, tmp_path / "local", [0.5], jobs=1)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = study(tiny_dataset, tmp_path / "ray", [0.5], executor="ray")
    finally:
        ray.shutdown()
    assert (tmp_path / "ray" / "logs" / "train_second_h0.5.log").is_file()
    assert on_ray == local
