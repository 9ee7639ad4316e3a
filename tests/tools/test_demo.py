"""tools/demo.py: a checkpoint's predictions drawn on one frame, end to end on the session's smoke run."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from detbench.data import Height3Dataset
from detbench.eval import parse_prediction_file
from detbench.utils.cli import run_main
import tools.demo
import tools.eval


def test_help_names_the_options_and_units(capsys):
    with pytest.raises(SystemExit) as exc:
        tools.demo.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for opt in ("--ckpt", "--frame", "--split", "--out", "--score-threshold", "metres", "radians", ".json", ".png"):
        assert opt in text, opt


def test_demo_draws_what_eval_evaluates(smoke_run, smoke_data, tmp_path, capsys):
    """The newest checkpoint of a run folder on the split's last frame (--frame -1): a PNG, and a JSON whose ground
    truth is the frame's boxes and whose predictions are tools/eval.py's for that frame at or above the threshold;
    the same frame by id gives the same JSON; the run folder stays a run folder."""
    from detbench.train.run_layout import RUN_FOLDER
    from detbench.utils.folder_ownership import check_claimable

    run = Path(shutil.copytree(smoke_run, tmp_path / "run"))
    last = Height3Dataset(smoke_data, 1.8, "test").frame_ids[-1]
    assert run_main(tools.demo.main, ["--ckpt", str(run), "--frame", "-1", "--score-threshold", "0.3"]) == 0
    printed = capsys.readouterr().out
    out = run / "demo_h1.8_test"
    png, js = out / f"{last}.png", out / f"{last}.json"
    assert f"on frame {last} of the test split at 1.8 m" in printed and f"wrote {png}, {js}" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    rec = json.loads(js.read_text())
    assert (rec["frame_id"], rec["split"], rec["height_m"], rec["model"]) == (last, "test", 1.8, "second")
    assert rec["checkpoint"] == str(run / "checkpoints" / "epoch_001.pt") and "metres" in rec["units"]["boxes"]
    frame = Height3Dataset(smoke_data, 1.8, "test").load(last)
    np.testing.assert_allclose(rec["ground_truth"], frame.boxes, atol=1e-4)
    assert run_main(tools.eval.main, ["--ckpt", str(run), "--out", str(tmp_path / "eval"), "--no-progress",
                                      "--bootstrap", "0"]) == 0
    parsed = parse_prediction_file(tmp_path / "eval" / "pred" / f"{last}.txt")
    boxes, scores = parsed.boxes, parsed.scores
    keep = scores >= 0.3
    assert len(rec["predictions"]) == int(keep.sum())
    assert rec["predictions_below_threshold"] == int((~keep).sum())
    if keep.any():
        np.testing.assert_allclose([p["box"] for p in rec["predictions"]], boxes[keep], atol=1e-3)
        np.testing.assert_allclose([p["score"] for p in rec["predictions"]], scores[keep], atol=1e-3)
    assert run_main(tools.demo.main, ["--ckpt", str(run / "checkpoints" / "epoch_001.pt"), "--frame", last,
                                      "--score-threshold", "0.3", "--out", str(tmp_path / "by_id")]) == 0
    assert json.loads((tmp_path / "by_id" / f"{last}.json").read_text()) == rec
    check_claimable(run, RUN_FOLDER)  # a demo folder inside a run is the run's own entry


def test_demo_errors_are_one_line(smoke_run, tmp_path, capsys):
    for argv, words in ((["--frame", "9"], "--frame 9: neither a frame id of the test split at 1.8 m"),
                        (["--frame", "nope"], "nor an index in 0..2"),
                        (["--score-threshold", "1.5"], "--score-threshold 1.5: must be a score in [0, 1]"),
                        (["--score-threshold", "0.05"], "--score-threshold 0.05 is below model.post.score_threshold"),
                        (["--stage", "proposals"], "second is a one-stage detector")):
        rc = run_main(tools.demo.main, ["--ckpt", str(smoke_run), "--out", str(tmp_path / "o"), *argv])
        err = capsys.readouterr().err
        assert rc == 2 and words in err and err.count("\n") == 1, err
    rc = run_main(tools.demo.main, ["--ckpt", str(tmp_path), "--out", str(tmp_path / "o")])
    assert rc == 2 and "holds no checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_eval_misses_writes_where_recall_goes_beside_the_report(smoke_run, tmp_path):
    """tools/eval.py --misses: misses.json holds each range's vehicles (the report's LiDAR-detected count) and a
    recall at least the report's (a vehicle counts when any kept prediction overlaps it enough, without the
    one-to-one matching), misses.md their tables; the folder stays an evaluation's."""
    out = tmp_path / "eval"
    assert run_main(tools.eval.main, ["--ckpt", str(smoke_run), "--out", str(out), "--no-progress", "--bootstrap",
                                      "0", "--misses"]) == 0
    report = json.loads((out / "report.json").read_text())
    found = json.loads((out / "misses.json").read_text())
    for r in ("small", "moderate", "large"):
        cell = report["results"][r]["all"]
        assert found[r]["vehicles"] == cell["lidar_detected"]
        if cell["lidar_detected"]:
            assert found[r]["recall"] >= cell["recall"] - 1e-4
    assert "# Where recall goes: small range" in (out / "misses.md").read_text()
    assert run_main(tools.eval.main, ["--ckpt", str(smoke_run), "--out", str(out), "--no-progress", "--bootstrap",
                                      "0"]) == 0  # an evaluation's own folder, misses files and all
