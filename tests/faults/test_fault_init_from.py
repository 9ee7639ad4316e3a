"""tools/train.py --init-from with a checkpoint that cannot start the model: refused before any training,
naming the file and the fix, and nothing is written."""
from tests.faults.faultkit import train_argv


def test_missing_init_checkpoint_is_refused(tool, fault_data, tmp_path):
    """An --init-from checkpoint that does not exist is refused naming the file, and no run folder is made."""
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--init-from", tmp_path / "nope.pt"))
    assert code == 2 and f"{tmp_path / 'nope.pt'}: checkpoint not found" in err, err
    assert not out.exists()


def test_init_checkpoint_of_an_unrelated_model_is_refused(tool, fault_data, trained_run, tmp_path):
    """An --init-from checkpoint of which no weight fits the model (a SECOND checkpoint for PointRCNN) is refused
    naming the file and the model, and no run folder is made."""
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--model", "pointrcnn", "--init-from", ckpt))
    assert code == 2 and str(ckpt) in err and "fits model pointrcnn" in err, err
    assert not out.exists()


def test_fine_tuning_at_another_height_starts_from_the_checkpoint(tool, fault_data, trained_run, tmp_path):
    """The README's example: anchor sizes resolved from the other height's vehicles may differ."""
    import json

    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    out = tmp_path / "ft"
    code, log = tool("train", *train_argv(fault_data, out, "--height", "0.5", "--epochs", "1", "--no-eval",
                                          "--init-from", ckpt))
    assert code == 0, log
    assert "initialised" in log and "0 start from scratch" in log
    summary = json.loads((out / "train_summary.json").read_text())
    assert summary["init_from"]["path"] == str(ckpt) and summary["init_from"]["new_tensors"] == 0
