"""tools/curves.py --evaluate: a run's epoch checkpoints evaluated afterwards make its learning curve."""
import json

import tools.curves
import tools.train
from detbench.utils.cli import run_main


def test_epoch_checkpoints_are_evaluated_once_and_make_the_curve(smoke_data, tmp_path, capsys, monkeypatch):
    run = tmp_path / "second_h1.8"
    assert run_main(tools.train.main, ["--model", "second", "--height", "1.8", "--preset", "smoke", "--data",
                                       str(smoke_data), "--out", str(run), "--epochs", "2", "--no-eval",
                                       "--no-progress", "--set", "train.tensorboard=false",
                                       "--set", "train.keep_checkpoints=0"]) == 0
    out = tmp_path / "curves"
    assert run_main(tools.curves.main, [str(run), "--evaluate", "3", "--out", str(out)]) == 0
    cached = json.loads((run / "curve_eval.json").read_text())
    assert cached["frames"] == 3 and set(cached["checkpoints"]) == {"epoch_001.pt", "epoch_002.pt"}
    assert set(cached["checkpoints"]["epoch_002.pt"]) >= {"ap_r40_small", "recall_small", "recall_large"}
    (curve,) = json.loads((out / "curves.json").read_text())["curves"]
    assert [p["epoch"] for p in curve["points"]] == [1, 2] and curve["clock"] == "cpu"
    assert curve["points"][1]["minutes"] > curve["points"][0]["minutes"] > 0
    # a second run reuses the evaluations: no checkpoint is loaded again
    import models

    monkeypatch.setattr(models, "load_from_checkpoint", lambda *a, **k: (_ for _ in ()).throw(AssertionError))
    capsys.readouterr()
    assert run_main(tools.curves.main, [str(run), "--evaluate", "3", "--out", str(out)]) == 0
    assert "epoch_00" not in capsys.readouterr().out.split("wrote")[0].replace("evaluated epochs", "")
    # a run without epoch checkpoints is named, with the fix
    bare = tmp_path / "bare"
    assert run_main(tools.train.main, ["--model", "second", "--height", "1.8", "--preset", "smoke", "--data",
                                       str(smoke_data), "--out", str(bare), "--epochs", "1", "--no-eval",
                                       "--no-progress", "--set", "train.tensorboard=false"]) == 0
    for p in (bare / "checkpoints").iterdir():
        p.unlink()
    assert run_main(tools.curves.main, [str(bare), "--evaluate", "3", "--out", str(tmp_path / "c2")]) == 2
    assert "holds no epoch checkpoint" in capsys.readouterr().err
