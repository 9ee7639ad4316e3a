"""The default smoke study's report is pinned: study.json without its timings equals tests/golden/.

`python tools/study.py --preset smoke` (the paper's heights, every registered detector) is the study every
other option (rigs, cross-height, seeds) extends; a change that moves any figure, key or row of its report
fails here."""
from __future__ import annotations

import json

import pytest

import models
from detbench.studies.study import StudyOptions, run_study
from tests.helpers import ROOT, assert_golden
from tests.tools.test_study_executors import comparable


@pytest.mark.slow  # every detector at the three heights, smoke preset: several minutes on 2 cores
def test_the_default_smoke_study_report_is_unchanged(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("DETBENCH_CACHE", str(cache))  # the simulated default dataset, made afresh
    out = tmp_path / "study"
    run_study(StudyOptions(preset="smoke", out=str(out), no_progress=True), registry=models, repo=ROOT)
    report = json.dumps(comparable(out), indent=1, sort_keys=True).replace(str(cache), "CACHE")
    assert str(tmp_path) not in report
    assert_golden("study_smoke_default.json", report + "\n")
