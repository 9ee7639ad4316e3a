"""tools/train.py -> tools/eval.py --ckpt (and --test-height) end to end on a tiny simulated dataset."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from detbench.benchmarks.detectors import idle_loaded_markdown, loaded_figures
from detbench.utils.cli import run_main
import tools.eval
import tools.study
from tests.helpers import ROOT



@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("data") / "sim"
    # seed 7: the test scene holds LiDAR-detected vehicles in the small range at both heights (seed 3 did on
    # calibration v1; on v2 its test scene has none there, and the cross-height matrix has no AP@R40 to show)
    return simulate_dataset(root, frames=9, heights=[0.5, 1.8], seed=7, frames_per_scene=3, progress=False)


def run(args, cwd=ROOT):
    proc = subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


@pytest.mark.parametrize("model", ["second", "pillarnet", "pointrcnn", "ct3d"])
def test_train_then_eval_checkpoint(tiny_dataset, tmp_path, model, capsys):
    out = tmp_path / "run"
    run(["tools/train.py", "--model", model, "--height", "1.8", "--preset", "smoke", "--data", str(tiny_dataset),
         "--out", str(out), "--epochs", "1", "--no-progress", "--set", "train.tensorboard=false",
         "--set", "train.seed=3"])
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["epochs_completed"] == 1 and not summary["interrupted"]
    ckpt = Path(summary["checkpoint"])
    assert ckpt.is_file() and (out / "config.yaml").is_file()
    # a new run in the same folder without --resume is refused; with --resume and no more epochs it is a no-op
    proc = subprocess.run([sys.executable, "tools/train.py", "--model", model, "--height", "1.8", "--preset", "smoke",
                           "--data", str(tiny_dataset), "--out", str(out), "--epochs", "1", "--no-progress"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0 and "--resume" in proc.stderr
    # evaluate at the training height (everything from the checkpoint) and at another height
    run(["tools/eval.py", "--ckpt", str(ckpt), "--out", str(tmp_path / "e18"), "--no-progress"])
    rep = json.loads((tmp_path / "e18" / "report.json").read_text())
    assert rep["model"] == model and rep["height"] == 1.8 and rep["trained_height"] == 1.8
    assert rep["stage"] == "refined" and rep["train_seed"] == 3  # the seed statistics name runs by it
    assert rep["num_frames"] == 3 and set(rep["results"]) == {"small", "moderate", "large"}
    assert len(list((tmp_path / "e18" / "pred").glob("*.txt"))) == 3
    run(["tools/eval.py", "--ckpt", str(ckpt), "--test-height", "0.5", "--out", str(tmp_path / "e05"),
         "--no-progress"])
    rep = json.loads((tmp_path / "e05" / "report.json").read_text())
    assert rep["height"] == 0.5 and rep["trained_height"] == 1.8
    # --stage proposals (in process, on the same checkpoint): the first stage alone of a two-stage
    # model; a one-stage model has no such stage and is refused before anything is written
    out_p = tmp_path / "e18_proposals"
    rc = run_main(tools.eval.main, ["--ckpt", str(ckpt), "--stage", "proposals", "--out", str(out_p),
                                    "--no-progress"])
    err = capsys.readouterr().err
    if model in ("pointrcnn", "ct3d"):
        assert rc == 0, err
        rep = json.loads((out_p / "report.json").read_text())
        assert (rep["model"], rep["stage"], rep["height"], rep["trained_height"]) == (model, "proposals", 1.8, 1.8)
        assert rep["num_frames"] == 3 and set(rep["results"]) == {"small", "moderate", "large"}
        assert len(list((out_p / "pred").glob("*.txt"))) == 3
        assert "proposals of the first stage alone" in (out_p / "report.md").read_text()
    else:
        assert rc == 2 and "--stage proposals" in err and f"{model} is a one-stage detector" in err
        assert not out_p.exists()


def test_train_rejects_unknown_config_key(tiny_dataset, tmp_path):
    proc = subprocess.run([sys.executable, "tools/train.py", "--height", "1.8", "--preset", "smoke", "--data",
                           str(tiny_dataset), "--out", str(tmp_path / "r"), "--set", "train.epoch=3"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and "did you mean 'epochs'" in proc.stderr


def test_a_bug_during_training_keeps_its_traceback_a_checked_error_is_one_line(tiny_dataset, tmp_path, monkeypatch,
                                                                                capsys):
    """numpy's ValueError from inside a kernel is a bug (exit 1, traceback), not "error: ..." with exit 2;
    a ValueError a check of ours raises stays one line."""
    import numpy as np

    import detbench.train
    import tools.train

    def kernel_bug(*a, **k):
        return np.zeros(-1)  # what an overflowed grid size does inside a numba kernel

    def checked(*a, **k):
        raise ValueError("frame 000003: points must be float32; rewrite it with the dataset writer")

    argv = ["--model", "second", "--height", "1.8", "--preset", "smoke", "--data", str(tiny_dataset), "--epochs", "1",
            "--no-progress", "--set", "train.tensorboard=false"]
    monkeypatch.setattr(detbench.train, "train", kernel_bug)
    with pytest.raises(ValueError, match="negative dimensions"):
        run_main(tools.train.main, [*argv, "--out", str(tmp_path / "bug")])
    monkeypatch.setattr(detbench.train, "train", checked)
    assert run_main(tools.train.main, [*argv, "--out", str(tmp_path / "checked")]) == 2
    assert "error: frame 000003: points must be float32" in capsys.readouterr().err


def test_benchmark_reports_every_model(tiny_dataset, tmp_path):
    run(["tools/benchmark.py", "--preset", "smoke", "--data", str(tiny_dataset), "--frames", "2", "--warmup", "1",
         "--threads", "1", "--out", str(tmp_path / "b")])
    res = json.loads((tmp_path / "b" / "benchmark.json").read_text())["results"]
    assert {r["model"] for r in res} >= {"second", "pillarnet", "pointrcnn", "ct3d"}
    for r in res:
        lat = r["latency_ms"]
        stages = [v for k, v in lat.items() if k not in ("total", "points")]
        assert r["parameters"] > 0 and r["weights_mb"] > 0 and r["peak_rss_mib"] > 0
        assert 0 < sum(stages) <= lat["total"] * 1.05  # the stage split accounts for (nearly) all the time
    md = (tmp_path / "b" / "benchmark.md").read_text()
    assert "ms" in md and "MiB" in md


def test_benchmark_idle_and_loaded_table():
    idle = {"model": "second", "device": "cpu", "latency_ms": {"total": 100.0, "points": 5.0}, "train_step_ms": 400.0}
    loaded = {"latency_ms": {"total": 150.0, "points": 5.0}, "train_step_ms": 800.0}
    idle["loaded"] = loaded_figures(idle, loaded, {"processes": 1})
    assert idle["loaded"]["ratio"] == {"total": 1.5, "train_step": 2.0}
    md = "\n".join(idle_loaded_markdown([idle]))
    assert "| second | cpu | 100.0 | 150.0 | 1.5 | 400.0 | 800.0 | 2.0 |" in md and "1 busy-loop process" in md


def test_study_runs_end_to_end_with_summary_progress_and_resume(tiny_dataset, tmp_path):
    out = tmp_path / "study"
    args = ["tools/study.py", "--preset", "smoke", "--set", "study.models=[second]", "--heights", "0.5", "1.8",
            "--data", str(tiny_dataset), "--out", str(out), "--no-progress", "--set", "train.epochs=1",
            "--set", "train.tensorboard=false", "--cross-height", "--jobs", "1"]
    proc = run(args)
    # one progress line per job started or done: the running jobs, how many are done, the time left
    assert "=== dataset (smoke preset)" in proc.stdout
    assert "=== 8 jobs (1 ability, 2 train, 2 eval, 2 cross_eval, 1 combine), up to 1 at once" in proc.stdout
    assert "=== start train second 0.5 m | running: train second 0.5 m | 0/8 done" in proc.stdout  # longest path first
    later = proc.stdout.split("=== start combine reports")[1].splitlines()[0]
    assert "left" in later and "known once" not in later  # known once a training or an evaluation has run
    assert "wrote " in (out / "logs" / "eval_second_h0.5_on_h0.5.log").read_text()  # each job's own log
    md = (out / "study.md").read_text()
    assert md.index("## Summary") < md.index("## 1. LiDAR detection ability")
    assert "Which height sees the most vehicles?" in md and "Which detector finds the most" in md
    assert "| 0.5 m | second |" in md and "| 1.8 m | second |" in md
    assert "--preset paper --device cuda" in md and "proves that the pipeline runs" in md
    # the models the preset's study.models leaves out are named, with how to add them
    assert "*Not in this study: ct3d, pillarnet, pointrcnn" in md and "`--models ct3d pillarnet pointrcnn second`" in md
    # every table names the preset and data that produced it
    for section in md.split("\n#")[1:]:
        if "\n|---" in section:
            assert "*Preset `smoke`" in section, section[:200]
    study = json.loads((out / "study.json").read_text())
    assert set(study["summary"]) == {"heights", "detectors"} and study["test_frames"] == 3
    assert study["models"] == ["second"] and study["left_out"] == ["ct3d", "pillarnet", "pointrcnn"]
    assert study["train_seconds"]["second"] > 0 and "Training time (the runs' epochs" in md
    rep = json.loads((out / "second_h1.8" / "eval_h1.8_test" / "report.json").read_text())
    assert "uncertainty" in rep  # the evaluation ran with the scene bootstrap
    # --cross-height: each checkpoint tested at the other height, a matrix per model in the report
    assert "start evaluate second trained at 0.5 m on 1.8 m" in proc.stdout
    cross = json.loads((out / "cross_height" / "cross_height.json").read_text())["matrices"]
    assert cross[0]["heights"] == [0.5, 1.8] and all(v is not None for row in cross[0]["values"]["second"] for v in row)
    assert "## 3. Cross-height matrix" in md and (out / "cross_height" / "cross_height_ap_r40_small.png").is_file()
    # a second call finds every stage done: only the combine step runs again
    proc = run(args)
    assert "train second" not in proc.stdout and "evaluate" not in proc.stdout
    assert "start combine reports | running: combine reports | 7/8 done" in proc.stdout


def test_study_models_come_from_models_then_the_preset_then_the_registry():
    import models
    from detbench.studies.study import study_models

    # quick names all four detectors; a study.models override leaves the others out; --models wins
    assert study_models("quick", None, [], registry=models) == (["ct3d", "pillarnet", "pointrcnn", "second"], [])
    assert study_models("quick", None, ["study.models=[second]"], registry=models) == (
        ["second"], ["ct3d", "pillarnet", "pointrcnn"])
    assert study_models("quick", ["pointrcnn"], [], registry=models) == (["pointrcnn"], [])
    assert study_models("smoke", None, [], registry=models) == (["ct3d", "pillarnet", "pointrcnn", "second"], [])
    with pytest.raises(ValueError):
        study_models("smoke", None, ["study.models=[nosuchmodel]"], registry=models)


def test_train_option_overrides_follow_the_users_set_values(tmp_path):
    from detbench.train.run import option_overrides

    assert option_overrides(["train.lr=0.1"]) == ["train.lr=0.1"]
    assert option_overrides(["a=1"], epochs=3, batch_size=2, workers=0, data=str(tmp_path)) == [
        "a=1", "train.epochs=3", "train.batch_size=2", "train.workers=0", f"data.root={tmp_path.resolve()}"]


def test_a_run_whose_checkpoint_stores_an_earlier_versions_model_config_resumes(tiny_dataset, tmp_path):
    """A checkpoint stores its model config; one written before the head's loss weights, focal loss and
    direction bins were YAML keys lacks them. --resume upgrades the stored config before comparing it with
    today's (models.upgrade_stored_run_config), so such a run continues instead of being refused as another
    config; a real difference is still refused."""
    import torch

    from detbench.train.checkpoint import config_digest

    out = tmp_path / "run"
    args = ["tools/train.py", "--model", "second", "--height", "1.8", "--preset", "smoke", "--data",
            str(tiny_dataset), "--out", str(out), "--no-progress", "--set", "train.tensorboard=false"]
    run([*args, "--epochs", "1"])
    ckpt_path = Path(json.loads((out / "train_summary.json").read_text())["checkpoint"])
    ck = torch.load(ckpt_path, weights_only=True)
    head = ck["config"]["model"]["head"]
    for key in ("num_dir_bins", "dir_offset", "focal_alpha", "focal_gamma", "loss_weights"):
        del head[key]
    ck["config_digest"] = config_digest(ck["config"])
    torch.save(ck, ckpt_path)
    proc = run([*args, "--epochs", "1", "--resume"])
    assert "already complete" in proc.stdout + proc.stderr
    head["focal_gamma"] = 3.0  # a value today's YAML does not hold: another config
    ck["config_digest"] = config_digest(ck["config"])
    torch.save(ck, ckpt_path)
    proc = subprocess.run([sys.executable, *args, "--epochs", "1", "--resume"], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 2 and "model.head.focal_gamma: 3.0 (checkpoint) vs 2.0 (now)" in proc.stderr


@pytest.fixture(scope="module")
def rig_dataset(tmp_path_factory):
    """9 frames (3 scenes of 3, seed 7) seen by the headlight pair and the forehead unit of configs/rigs.yaml."""
    from detbench.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("data") / "rigs"
    return simulate_dataset(root, frames=9, heights=["headlights", "forehead"], seed=7, frames_per_scene=3,
                            progress=False)


@pytest.mark.parametrize("model", ["second", "pillarnet", "pointrcnn", "ct3d"])
def test_train_then_eval_on_a_rig(rig_dataset, tmp_path, model, capsys):
    # a headlight-pair dataset trains and evaluates through the same commands as a height, --height naming the rig
    import tools.train
    from detbench.data import Height3Dataset

    out = tmp_path / "run"
    assert run_main(tools.train.main, ["--model", model, "--height", "headlights", "--preset", "smoke", "--data",
                                       str(rig_dataset), "--out", str(out), "--epochs", "1", "--no-progress",
                                       "--set", "train.tensorboard=false"]) == 0
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["height"] == "headlights" and summary["epochs_completed"] == 1
    assert "at rig headlights" in (out / "train_summary.md").read_text()
    # the checkpoint records the rig: --ckpt alone evaluates it on the rig's own test split
    assert run_main(tools.eval.main, ["--ckpt", str(out), "--bootstrap", "0", "--no-progress"]) == 0
    report = json.loads((out / "eval_hheadlights_test" / "report.json").read_text())
    assert (report["model"], report["height"], report["trained_height"]) == (model, "headlights", "headlights")
    assert report["num_frames"] == len(Height3Dataset(rig_dataset, "headlights", "test").frame_ids) > 0
    assert report["results"]["large"]["all"]["lidar_detected"] > 0  # the rig's merged points were read
    assert "at rig headlights (test split)" in (out / "eval_hheadlights_test" / "report.md").read_text()
    if model != "second":
        return
    # the drawing of a prediction on a rig's frame (tools/demo.py) takes the rig from the checkpoint too
    import tools.demo

    assert run_main(tools.demo.main, ["--ckpt", str(out), "--frame", "0"]) == 0
    drawn = json.loads(next((out / "demo_hheadlights_test").glob("*.json")).read_text())
    assert drawn["height_m"] == "headlights" and drawn["ground_truth"]
    # and so does the precision check (tools/precision.py)
    import tools.precision

    assert run_main(tools.precision.main, ["--ckpt", str(next((out / "checkpoints").glob("*.pt"))), "--frames", "2",
                                           "--precisions", "float32", "--no-progress"]) == 0
    checked = json.loads(next(out.glob("precision_hheadlights_test/precision.json")).read_text())
    assert checked["height"] == "headlights"
    # another rig is a cross-rig evaluation, as another height is a cross-height one
    assert run_main(tools.eval.main, ["--ckpt", str(out), "--test-height", "forehead", "--bootstrap", "0",
                                      "--no-progress"]) == 0
    cross = json.loads((out / "eval_hforehead_test" / "report.json").read_text())
    assert (cross["height"], cross["trained_height"]) == ("forehead", "headlights")
    from detbench.eval.report import report_variant

    assert report_variant(cross) == "trained at rig headlights" and report_variant(report) is None
    capsys.readouterr()
    assert run_main(tools.eval.main, ["--ckpt", str(out), "--height", "forehead", "--out", str(tmp_path / "e")]) == 2
    assert "was trained at rig headlights, not --height forehead" in capsys.readouterr().err
