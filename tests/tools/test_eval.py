"""tools/eval.py: its arguments and errors, --combine, and end to end on a tiny dataset."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from detbench.eval import evaluate_predictions
from detbench.utils.cli import run_main
import tools.bench_eval
import tools.eval
from tests.helpers import ROOT



# ------------------------------------------------------------------ CLI without data

def test_help_runs_as_script():
    out = subprocess.run([sys.executable, "tools/eval.py", "--help"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0
    for opt in ("--data", "--height", "--split", "--pred", "--ckpt", "--out", "--combine", "metres"):
        assert opt in out.stdout


def test_ckpt_errors_name_the_file(tmp_path, capsys):
    tool = tools.eval
    rc = run_main(tool.main, ["--ckpt", str(tmp_path / "m.pt"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "m.pt: checkpoint not found" in err
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint at all")
    rc = run_main(tool.main, ["--ckpt", str(tmp_path / "bad.pt"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "bad.pt: " in err and "tools/train.py" in err
    rc = run_main(tool.main, ["--data", str(tmp_path), "--height", "1.8", "--pred", str(tmp_path),
                              "--test-height", "0.5", "--out", str(tmp_path / "o")])
    assert rc == 2 and "--test-height goes with --ckpt" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_argument_errors(tmp_path, capsys):
    tool = tools.eval
    assert run_main(tool.main, ["--height", "1.8", "--pred", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "missing --data" in capsys.readouterr().err
    assert run_main(tool.main, ["--data", str(tmp_path), "--height", "1.8", "--out", str(tmp_path)]) == 2
    assert "exactly one of --pred" in capsys.readouterr().err
    assert run_main(tool.main, ["--combine", str(tmp_path / "r.json")]) == 2
    assert "--out" in capsys.readouterr().err
    assert run_main(tool.main, ["--combine", str(tmp_path / "r.json"), "--out", str(tmp_path)]) == 2
    assert "r.json: file not found" in capsys.readouterr().err


def test_combine_cli(tmp_path, capsys):
    from detbench.eval import EvalFrame, evaluate
    from detbench.utils.atomic import atomic_write_json

    car = [10, 0, 0.8, 4, 2, 1.6, 0]
    paths = []
    for model, found in (("A", 1), ("B", 0)):
        for h in (0.5, 1.8):
            rep = evaluate([EvalFrame([car], [3], [0], [car] * found, [0.9] * found)])
            paths.append(atomic_write_json(tmp_path / model / str(h) / "report.json",
                                           {"model": model, "height": h, "split": "test", **rep}))
    tool = tools.eval
    out = tmp_path / "comb"
    assert run_main(tool.main, ["--combine", *map(str, paths), "--out", str(out)]) == 0
    assert "models A, B; heights 0.5 m, 1.8 m" in capsys.readouterr().out
    for name in ("combined.json", "combined.md", "combined.csv", "fig8_by_height.png",
                 "fig9_recall_by_range.png", "fig10_recall_by_level.png"):
        assert (out / name).stat().st_size > 0, name
    comb = json.loads((out / "combined.json").read_text())
    assert comb["models"] == ["A", "B"] and comb["sources"] == list(map(str, paths))
    assert comb["data"] == "data source not recorded" and "warning" not in capsys.readouterr().err
    # reports of two simulator calibrations: combined, named, and warned about
    for p, cal in zip(paths, ("v1", "v2", "v1", "v2")):
        atomic_write_json(p, dict(json.loads(p.read_text()), data_source={"kind": "simulator", "calibration": cal}))
    assert run_main(tool.main, ["--combine", *map(str, paths), "--out", str(out), "--no-figures"]) == 0
    assert "come from different data (simulator calibration v1 + simulator calibration v2)" in capsys.readouterr().err
    assert "Frames: simulator calibration v1 + simulator calibration v2." in (out / "combined.md").read_text()
    # a report without a model name is refused with the fix
    bad = json.loads(paths[0].read_text())
    bad["model"] = None
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    assert run_main(tool.main, ["--combine", str(tmp_path / "bad.json"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.json: no 'model'" in err and "--model" in err
    # a cross-height report (trained at 0.5 m, tested at 1.8 m) is refused by name; --with-variants labels it
    cross = dict(json.loads(paths[0].read_text()), height=1.8, trained_height=0.5, stage="refined")
    atomic_write_json(tmp_path / "cross" / "report.json", cross)
    argv = ["--combine", *map(str, paths), str(tmp_path / "cross" / "report.json"), "--out", str(out), "--no-figures"]
    assert run_main(tool.main, argv) == 2
    err = capsys.readouterr().err
    assert "cross/report.json (trained at 0.5 m)" in err and "--with-variants" in err
    assert run_main(tool.main, [*argv, "--with-variants"]) == 0
    assert json.loads((out / "combined.json").read_text())["models"] == ["A", "B", "A [trained at 0.5 m]"]


# ------------------------------------------------------------------ end to end on a tiny dataset

def car(x, y=0.0):
    return [x, y, 0.8, 4.0, 2.0, 1.6, 0.0]


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """3 scenes x 2 frames at 1.8 m. Every frame: vehicles at (10, 0) lane 0 and (20, 3.5) lane +1,
    each with a point inside, and (30, -3.5) lane -1 whose only point is 0.03 m above the road
    (below the 0.05 m lift -> not LiDAR-detected)."""
    from detbench.data import DatasetWriter, Frame, Sensor

    root = tmp_path_factory.mktemp("ds")
    boxes = np.array([car(10), car(20, 3.5), car(30, -3.5)], dtype=np.float32)
    points = np.array([[10, 0, 1.0, 0.5], [20, 3.5, 0.5, 0.5], [30, -3.5, 0.03, 0.5]], dtype=np.float32)
    with DatasetWriter(root, [1.8], {"kind": "test fixture"}) as w:
        for s in range(3):
            for i in range(2):
                w.add([Frame(f"{s:04d}_{i:03d}", f"{s:04d}", points, boxes, np.array(["car"] * 3),
                             np.arange(3), np.array([0, 1, -1]), Sensor(1.8))])
    return root


def test_evaluate_predictions_on_dataset(tiny_dataset):
    from detbench.data import Height3Dataset

    ds = Height3Dataset(tiny_dataset, 1.8, "all")
    ids = ds.frame_ids
    preds = {ids[0]: (np.array([car(10), car(20.5, 3.5)]), np.array([0.9, 0.8])),
             ids[1]: (np.array([car(30, -3.5), car(40)]), np.array([0.9, 0.05]))}
    rep = evaluate_predictions(ds, preds, progress=False, extras=False)
    c = rep["results"]["small"]["all"]
    # 6 frames x 3 vehicles, 2 detected each; 2 TPs in frame 0; the hit on the undetected
    # vehicle is ignored and the 0.05-score box dropped
    assert (c["total"], c["lidar_detected"], c["tp"], c["fp"]) == (18, 12, 2, 0)
    assert c["recall"] == pytest.approx(2 / 12)
    assert "extras" not in rep
    with pytest.raises(KeyError, match="not in the dataset"):
        evaluate_predictions(ds, {"9999_999": preds[ids[0]]}, progress=False)


def test_tool_end_to_end(tiny_dataset, tmp_path, capsys):
    from detbench.data import Height3Dataset

    test_ids = Height3Dataset(tiny_dataset, 1.8, "test").frame_ids
    train_ids = Height3Dataset(tiny_dataset, 1.8, "train").frame_ids
    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / f"{test_ids[0]}.txt").write_text("10 0 0.8 4 2 1.6 0 0.9 car\n20.5 3.5 0.8 4 2 1.6 0 0.8\n"
                                             "70 0 0.8 4 2 1.6 0 0.7\n")
    (pred / f"{train_ids[0]}.txt").write_text("10 0 0.8 4 2 1.6 0 0.9\n")
    out = tmp_path / "out"
    tool = tools.eval
    rc = run_main(tool.main, ["--data", str(tiny_dataset), "--height", "1.8", "--split", "test", "--pred", str(pred),
                    "--out", str(out), "--model", "SECOND", "--no-progress"])
    stdout = capsys.readouterr().out
    assert rc == 0, stdout
    assert "skipped 1 prediction file" in stdout and "recall" in stdout
    rep = json.loads((out / "report.json").read_text())
    assert (rep["model"], rep["height"], rep["split"], rep["num_frames"]) == ("SECOND", 1.8, "test", len(test_ids))
    small, moderate = rep["results"]["small"]["all"], rep["results"]["moderate"]["all"]
    n = len(test_ids)
    assert (small["total"], small["lidar_detected"], small["tp"], small["fp"]) == (3 * n, 2 * n, 2, 0)
    assert small["ldr"] == pytest.approx(2 / 3) and small["recall"] == pytest.approx(2 / (2 * n))
    # the box at x = 70 is outside small (ignored) but an FP in moderate, ranked last
    assert moderate["fp"] == 1 and moderate["ap_r40"] == pytest.approx(2 / (2 * n))
    assert set(rep["extras"]) == {"bev_0.7", "3d_0.5", "bev_0.5"}
    assert rep["data_source"] == {"kind": "test fixture"}  # not the simulator: no calibration to name
    md = (out / "report.md").read_text()
    assert "SECOND at 1.8 m (test split)" in md and "| Small | All |" in md and "data on disk" in md
    assert (out / "report.csv").read_text().startswith("model,height_m,split,variant")

    # a file for an unknown frame id, and a malformed line: errors naming the file (and line)
    (pred / "9999_999.txt").write_text("")
    assert run_main(tool.main, ["--data", str(tiny_dataset), "--height", "1.8", "--pred", str(pred), "--out", str(out),
                      "--no-progress"]) == 2
    assert "9999_999.txt: unknown frame id" in capsys.readouterr().err
    (pred / "9999_999.txt").unlink()
    (pred / f"{test_ids[-1]}.txt").write_text("1 2 3\n")
    assert run_main(tool.main, ["--data", str(tiny_dataset), "--height", "1.8", "--pred", str(pred), "--out", str(out),
                      "--no-progress"]) == 2
    assert f"{test_ids[-1]}.txt:1: expected 8 numbers" in capsys.readouterr().err
    # a height the dataset does not hold
    assert run_main(tool.main, ["--data", str(tiny_dataset), "--height", "0.5", "--pred", str(pred), "--out", str(out),
                      "--no-progress"]) == 2
    assert "0.5" in capsys.readouterr().err


def test_bench_eval_small_run(tmp_path, capsys):
    bench = tools.bench_eval
    assert bench.main(["--frames", "40", "--repeats", "1", "--out", str(tmp_path)]) == 0
    assert "median" in capsys.readouterr().out
    res = json.loads((tmp_path / "bench_eval.json").read_text())
    assert res["frames"] == 40 and res["predictions_per_frame"] == 30 and res["seconds_median"] > 0
    assert set(res["seconds_by_stage_median"]) == {"prepare", "iou", "match", "ap"}
    # the synthetic load has TPs, FPs and undetected vehicles
    la = res["large_all"]
    assert la["tp"] > 0 and la["fp"] > 0 and la["lidar_detected"] < la["total"]
    assert "| **total** |" in (tmp_path / "bench_eval.md").read_text()
    # with a scene bootstrap: its time and report.json's size, the AP ranking a part of it
    assert bench.main(["--frames", "40", "--repeats", "1", "--bootstrap", "20", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "bench_eval.json").read_text())
    assert res["bootstrap_scenes"] == 4 and res["bootstrap_seconds_median"] > 0
    assert res["ranked_detections"] >= la["tp"] + la["fp"]
    assert res["report_json_bytes_without_ap_ranking"] < res["report_json_bytes"] < \
        res["report_json_bytes_without_ap_ranking"] + 8 * res["ranked_detections"]
    assert "of which the AP ranking" in (tmp_path / "bench_eval.md").read_text()


# ------------------------------------------------------------------ --ckpt RUN_DIR: the run's newest checkpoint

def test_ckpt_takes_a_run_folder_and_evaluates_its_newest_checkpoint(smoke_run, tmp_path, capsys):
    """--ckpt RUN_DIR (or RUN_DIR/checkpoints) evaluates the newest checkpoint by epoch, then step, and says which;
    the report equals the one of that checkpoint given as a file; a folder without one is one error line."""
    import shutil

    run = Path(shutil.copytree(smoke_run, tmp_path / "run"))
    ckpt = run / "checkpoints" / "epoch_001.pt"
    shutil.copy(ckpt, run / "checkpoints" / "epoch_000_step_000002.pt")  # older: a step inside epoch 1
    assert run_main(tools.eval.main, ["--ckpt", str(ckpt), "--out", str(tmp_path / "file"), "--no-progress",
                                      "--bootstrap", "0"]) == 0
    capsys.readouterr()
    assert run_main(tools.eval.main, ["--ckpt", str(run), "--no-progress", "--bootstrap", "0"]) == 0
    out = capsys.readouterr().out
    assert f"checkpoint: {ckpt} (the newest in {run})" in out
    by_file = json.loads((tmp_path / "file" / "report.json").read_text())
    by_run = json.loads((run / "eval_h1.8_test" / "report.json").read_text())  # the run's own eval folder
    assert by_run["results"] == by_file["results"] and by_run["model"] == "second"
    # a newer epoch is taken over the older ones, from the checkpoints/ folder too: here a damaged file,
    # refused with its name
    (run / "checkpoints" / "epoch_002.pt").write_bytes(b"not a checkpoint")
    assert run_main(tools.eval.main, ["--ckpt", str(run / "checkpoints"), "--out", str(tmp_path / "e2"),
                                      "--no-progress"]) == 2
    assert "epoch_002.pt" in capsys.readouterr().err
    empty = tmp_path / "empty_run"
    (empty / "checkpoints").mkdir(parents=True)
    assert run_main(tools.eval.main, ["--ckpt", str(empty), "--out", str(tmp_path / "e3"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{empty}: holds no checkpoint" in err and "tools/train.py --out" in err
