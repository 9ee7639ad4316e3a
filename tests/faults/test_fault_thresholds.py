"""The evaluator's score threshold may not lie below the model's `model.post.score_threshold`: the model keeps
no box under its own threshold, so a lower evaluator threshold would change nothing while the report says it
was applied. tools/train.py and tools/eval.py refuse it in one line, naming both values and the fix, before any
frame is read or file written; the shipped defaults (both 0.1) pass."""
import yaml

from tests.faults.faultkit import train_argv


def _one_line(code: int, err: str, *named: str) -> None:
    assert code == 2 and err.startswith("error: ") and all(n in err for n in named), err[-2000:]
    assert err.count("\n") == 1 and "Traceback" not in err


def test_train_refuses_an_evaluator_threshold_below_the_models(fault_data, tool, tmp_path):
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--set", "eval.score_threshold=0.05"))
    _one_line(code, err, "eval.score_threshold 0.05 is below model.post.score_threshold 0.1",
              "set model.post.score_threshold to 0.05 as well, or use eval.score_threshold 0.1 or above")
    assert not out.exists()


def test_eval_refuses_a_threshold_below_the_checkpoints_model_and_takes_the_default(trained_run, tool, tmp_path):
    """trained_run is tools/train.py at the shipped thresholds (it exits 0); its checkpoint evaluates at the
    default --score-threshold and is refused at 0.05."""
    saved = yaml.safe_load((trained_run / "config.yaml").read_text())
    assert saved["eval"]["score_threshold"] == saved["model"]["post"]["score_threshold"] == 0.1
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    code, err = tool("eval", "--ckpt", ckpt, "--score-threshold", "0.05", "--out", tmp_path / "low", "--no-progress")
    _one_line(code, err, f"--ckpt {ckpt}: --score-threshold 0.05 is below model.post.score_threshold 0.1",
              "train it with --set model.post.score_threshold=0.05, or use --score-threshold 0.1 or above")
    assert not (tmp_path / "low").exists()
    code, err = tool("eval", "--ckpt", ckpt, "--out", tmp_path / "default", "--no-progress", "--no-extras",
                     "--bootstrap", "0")
    assert code == 0 and (tmp_path / "default" / "report.json").is_file(), err[-2000:]


def test_precision_refuses_a_threshold_below_the_checkpoints_model(trained_run, tool, tmp_path):
    """tools/precision.py drops detections below --score-threshold after the model dropped those below its own
    model.post.score_threshold: a lower value is refused in one line before any frame is read."""
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    code, err = tool("precision", "--ckpt", ckpt, "--score-threshold", "0.05", "--out", tmp_path / "low",
                     "--no-progress")
    _one_line(code, err, f"--ckpt {ckpt}: --score-threshold 0.05 is below model.post.score_threshold 0.1")
    assert not (tmp_path / "low").exists()
