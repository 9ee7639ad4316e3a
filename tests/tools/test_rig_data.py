"""A rig wherever a height goes: the ability study on a rig dataset, validation, the OpenPCDet export and the study
(tools/study.py --rigs), on a small dataset simulated with the headlight pair and the forehead unit."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import models
from detbench.data.regions import RANGE_NAMES
from detbench.studies.study import StudyOptions, run_study
from detbench.utils.cli import UserError, run_main
from tests.helpers import ROOT

RIGS = ["headlights", "forehead"]


@pytest.fixture(scope="module")
def rig_data(tmp_path_factory):
    """24 frames (3 scenes of 8, seed 3) seen by the headlight pair and the forehead unit of configs/rigs.yaml."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("data") / "rigs"
    return simulate_dataset(root, frames=24, heights=RIGS, seed=3, frames_per_scene=8, frame_stride=1,
                            progress=False)


def test_a_rigs_ability_on_disk_is_the_simulators(rig_data):
    # counting a rig's saved points (tools/analyze.py --data --heights RIG) gives the cells the simulator's hit counts
    # give on the same instants (tools/analyze.py --simulate --rigs RIG): each point is read back under its rig,
    # not under its first sensor's height, and no sensor's points are lost on the way to disk
    from detbench.studies.ability_run import AbilityOptions, run_ability
    from detbench.studies.rig_ability import RigAbilityOptions, run_rig_ability

    disk, _, _ = run_ability(AbilityOptions(data=str(rig_data), heights=list(RIGS), no_figures=True, bootstrap=0,
                                            no_progress=True))
    sim, _ = run_rig_ability(RigAbilityOptions(simulate=24, rigs=list(RIGS), seed=3, frames_per_scene=8,
                                               bootstrap=0, no_progress=True))
    assert list(disk["heights"]) == RIGS
    for rig in RIGS:
        assert {r: disk["heights"][rig][r] for r in RANGE_NAMES} == {r: sim["rigs"][rig][r] for r in RANGE_NAMES}
    assert disk["heights"]["headlights"]["large"]["all"]["total"] > 0


def test_analyze_takes_a_rig_name_with_data_only(rig_data, tmp_path, capsys):
    import tools.analyze

    out = tmp_path / "ability"
    assert run_main(tools.analyze.main, ["--data", str(rig_data), "--heights", "headlights", "--out", str(out),
                                         "--no-figures", "--bootstrap", "0", "--no-progress"]) == 0
    assert list(json.loads((out / "ability.json").read_text())["heights"]) == ["headlights"]
    assert "| headlights Number / LDR |" in (out / "ability.md").read_text()
    assert run_main(tools.analyze.main, ["--simulate", "4", "--heights", "headlights", "--out",
                                         str(tmp_path / "s")]) == 2
    assert "--heights headlights: a rig's name goes with --data" in capsys.readouterr().err


def test_validate_checks_a_rigs_sensor_index(rig_data, tmp_path):
    from detbench.data.layout import sensor_index_path
    from detbench.data.validate import validate_dataset

    rep = validate_dataset(rig_data)
    assert rep.ok and rep.heights == RIGS, rep.errors
    data = tmp_path / "copy"
    shutil.copytree(rig_data, data)
    ids = sorted(p.stem for p in (data / "sensor_index" / "headlights").glob("*.npy"))
    short, wrong, gone = (sensor_index_path(data, "headlights", f) for f in ids[:3])
    np.save(short, np.load(short)[:-1])
    index = np.load(wrong)
    index[0] = 2  # the headlight pair has sensors 0 and 1
    np.save(wrong, index)
    gone.unlink()
    rep = validate_dataset(data, heights=["headlights"])
    assert not rep.ok and len(rep.errors) == 3
    assert any(e.startswith(str(short)) and "1-D integer array of one sensor a point" in e for e in rep.errors)
    assert any(e.startswith(str(wrong)) and "outside the rig's 2 sensor(s) 0..1" in e for e in rep.errors)
    assert any(e.startswith(str(gone)) and "missing" in e and "--rigs headlights" in e for e in rep.errors)
    assert validate_dataset(data, heights=["forehead"]).ok  # the other rig's files are whole


def test_openpcdet_export_of_a_rig(rig_data, tmp_path, capsys):
    import tools.export_openpcdet

    out = tmp_path / "opc"
    assert run_main(tools.export_openpcdet.main, [str(rig_data), "--height", "headlights", "--out", str(out),
                                                  "--no-progress"]) == 0
    assert capsys.readouterr().out.startswith(f"{out}: headlights in the ground frame")
    manifest = json.loads((out / "detbench_export.json").read_text())
    assert manifest["source"]["height"] == "headlights"
    from detbench.data.openpcdet_export import EXPORT_MARKDOWN

    assert "`, the rig headlights. Frame of points and labels: **ground**" in (out / EXPORT_MARKDOWN).read_text()
    assert "--height headlights" in manifest["commands"]["evaluate_in_detbench"]
    assert len(list((out / "points").glob("*.npy"))) == sum(len((out / "ImageSets" / f"{s}.txt").read_text().split())
                                                            for s in ("train", "val"))
    assert run_main(tools.export_openpcdet.main, [str(rig_data), "--height", "headlights", "--out",
                                                  str(tmp_path / "s"), "--frame", "sensor"]) == 2
    assert "no one sensor frame" in capsys.readouterr().err


def test_study_rig_arguments_are_checked_before_anything_is_created(rig_data, tmp_path):
    out = tmp_path / "study"
    cases = [(dict(rigs=["headlights"], heights=[1.8]), "--heights and --rigs: give one of them"),
             (dict(rigs=["headlights", "headlights"]), "headlights is given twice"),
             (dict(rigs=["nowhere"]), "--rigs nowhere: not in rigs.yaml"),
             (dict(rigs=["plate"], data=str(rig_data)), "--rigs plate: not in the dataset"),
             (dict(data=str(rig_data)), "holds the rigs headlights, forehead and no height; study them with --rigs "
                                        "headlights forehead"),
             (dict(data=str(rig_data), heights=[1.8]), "holds no height; give heights among them")]
    for kw, words in cases:
        with pytest.raises(UserError, match=words.replace("(", r"\(")):
            run_study(StudyOptions(preset="smoke", out=str(out), **kw), registry=models, repo=ROOT)
        assert not out.exists()


@pytest.mark.slow  # a smoke study of one model at two rigs, two seeds, the cross-rig matrix: a minute or two on 2 cores
def test_a_smoke_study_of_two_rigs(tmp_path, monkeypatch):
    # tools/study.py --rigs headlights forehead: the rigs simulated, counted, trained, evaluated and crossed
    import tools.study

    monkeypatch.setenv("DETBENCH_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "study"
    assert run_main(tools.study.main, ["--preset", "smoke", "--rigs", *RIGS, "--models", "second", "--cross-height",
                                       "--seeds", "0", "1", "--out", str(out), "--no-progress",
                                       "--set", "train.epochs=1"]) == 0
    study = json.loads((out / "study.json").read_text())
    assert study["heights"] == RIGS and list(study["ability"]["heights"]) == RIGS
    info = json.loads((next((tmp_path / "cache").glob("sim-*")) / "dataset.json").read_text())
    assert sorted(info["heights"]) == sorted(RIGS) and all("rig" in h for h in info["heights"].values())
    assert sorted(study["summary"]["detectors"]) == sorted(RIGS)
    assert sorted(e["height"] for e in study["detection"]["entries"]) == sorted(RIGS)
    for rig in RIGS:  # each rig's detection report counts the vehicles its own points hit
        report = json.loads((out / f"second_h{rig}" / f"eval_h{rig}_test" / "report.json").read_text())
        assert report["height"] == rig and report["trained_height"] == rig
    mats = study["cross_height"]
    assert [m["heights"] for m in mats] == [sorted(RIGS)] * 2
    assert all(v is not None for m in mats for row in m["values"]["second"] for v in row)
    md = (out / "study.md").read_text()
    assert "| rig headlights | second |" in md and "| trained \\ tested | rig forehead | rig headlights |" in md
    assert (out / "cross_height" / "cross_height_recall_large.png").is_file()
    assert (out / "combined" / "fig8_by_height.png").is_file()
    # two seeds per rig: the seed statistics keyed by rig
    assert sorted(study["seeds"]["by_height"]) == sorted(RIGS) and (out / "second_hheadlights_s1").is_dir()
    assert "| second | rig headlights | 2 |" in md
