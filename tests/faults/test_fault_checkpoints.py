"""Faults around checkpoints: NaN weights, truncated, random and malicious files, and kill -9 during
training and during a checkpoint write, then --resume (bit-identical to an uninterrupted run)."""
import json
import os

import pytest
import torch

from tests.faults.faultkit import (kill_when_stalled, load_checkpoint_dict, same_tensors, snapshot, stalling_trainer,
                                   train_argv)


def eval_argv(ckpt, out):
    return ["--ckpt", ckpt, "--out", out, "--no-progress", "--no-extras"]


def test_nan_weights_are_refused_naming_the_tensor(trained_run, tool, tmp_path):
    """NaN weights are a user error naming the tensor, not an evaluation with recall 0 and exit 0."""
    ckpt = load_checkpoint_dict(trained_run / "checkpoints" / "epoch_002.pt")
    name = next(k for k, v in ckpt["model"].items() if v.is_floating_point() and v.numel() > 1)
    ckpt["model"][name].view(-1)[1] = float("nan")
    bad = tmp_path / "checkpoints" / "epoch_002.pt"
    bad.parent.mkdir()
    torch.save(ckpt, bad)
    code, err = tool("eval", *eval_argv(bad, tmp_path / "e"))
    assert code == 2 and f"{bad}: weight {name!r} holds 1 NaN or inf value(s)" in err
    assert not (tmp_path / "e").exists()


def test_non_finite_outputs_are_reported_not_dropped(trained_run):
    """A model whose outputs go NaN (weights broken after loading) is an error, not recall 0."""
    import models
    from detbench.data import Height3Dataset
    from detbench.train.inference import NonFiniteOutputError, predict_frames

    model, ck = models.load_from_checkpoint(trained_run / "checkpoints" / "epoch_002.pt")
    with torch.no_grad():
        next(p for p in model.parameters() if p.numel() > 1).fill_(float("nan"))
    frames = Height3Dataset(ck["data"]["source"], 1.8, "test")
    with pytest.raises(NonFiniteOutputError, match=r"NaN or inf in the batches of 4 of 4 frames \(e\.g\. 0002_000"):
        predict_frames(model, frames, ck["config"]["model"]["point_cloud_range"], progress=False)


def test_non_finite_loss_stops_training_naming_the_frames(fault_data, tool, tmp_path):
    """lr 1e12 breaks the weights at the first step: every later step is skipped and logged with its frames, and
    the fifth in a row (train.max_nonfinite_steps) stops the run naming the newest checkpoint."""
    out = tmp_path / "run"
    code, err = tool("train", *train_argv(fault_data, out, "--set", "train.lr=1e12", "--set", "train.grad_clip=0",
                                          "--set", "train.epochs=3", "--set", "train.eval_every=10"))
    assert code == 2 and "epoch 1, step 2: non-finite loss (loss nan); step skipped" in err
    assert "5 steps in a row had a non-finite loss or gradient (the last at epoch 2, step 2" in err
    assert f"the newest checkpoint, {out / 'checkpoints' / 'epoch_001.pt'}" in err
    assert "frames [" in err and "train.lr" in err and "Traceback" not in err
    assert [p.name for p in (out / "checkpoints").iterdir()] == ["epoch_001.pt"]


@pytest.mark.parametrize("kind, named", [
    ("truncated", "the file is damaged or truncated"),
    ("random", "the file is damaged or truncated (e.g. a copy that stopped half-way) or not a checkpoint"),
    ("empty", "the file is empty or cut short"),
])
def test_damaged_checkpoint_is_refused(kind, named, trained_run, tool, tmp_path):
    """A truncated, random or empty checkpoint is named as unreadable, not as one that holds Python objects."""
    good = (trained_run / "checkpoints" / "epoch_002.pt").read_bytes()
    data = {"truncated": good[:len(good) // 2], "random": os.urandom(4096), "empty": b""}[kind]
    bad = tmp_path / "epoch_002.pt"
    bad.write_bytes(data)
    code, err = tool("eval", *eval_argv(bad, tmp_path / "e"))
    assert code == 2 and f"{bad}: cannot read this checkpoint" in err and named in err
    assert "Python objects" not in err and "weights_only` set to `False" not in err


def test_malicious_checkpoint_is_refused_unrun(tool, tmp_path):
    """A checkpoint holding a pickled object that would run a command is refused naming the file, and the
    command never runs."""
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    bad = tmp_path / "evil.pt"
    torch.save({"format": "detbench-checkpoint", "payload": Payload()}, bad)
    code, err = tool("eval", *eval_argv(bad, tmp_path / "e"))
    assert code == 2 and f"{bad}: holds Python objects" in err
    assert not marker.exists()


def _history(run):
    return json.loads((run / "history.json").read_text())["epochs"]


def _assert_same_run(run, reference):
    """Weights, optimizer and schedule of the final checkpoint bit-identical; the same epoch lines."""
    ours, ref = (load_checkpoint_dict(r / "checkpoints" / "epoch_002.pt") for r in (run, reference))
    for key in ("model", "optimizer", "scheduler", "state"):
        assert same_tensors(ours[key], ref[key]), key
    lines = [[(h["epoch"], h["losses"]) for h in _history(r)] for r in (run, reference)]
    assert lines[0] == lines[1]
    assert not list((run / "checkpoints").glob(".tmp-*"))


def test_kill_during_evaluation_then_resume(trained_run, fault_data, tmp_path):
    """kill -9 while epoch 1 is evaluated (after its checkpoint): its history line survives and
    --resume ends bit-identical to the uninterrupted run."""
    run = tmp_path / "run"
    proc, marker = stalling_trainer(tmp_path, "eval", train_argv(fault_data, run))
    kill_when_stalled(proc, marker)
    assert [h["epoch"] for h in _history(run)] == [1]
    assert (run / "checkpoints" / "epoch_001.pt").is_file()
    before = snapshot(run / "checkpoints")
    resumed = stalling_trainer(tmp_path, "none", train_argv(fault_data, run, "--resume"))[0]
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err[-3000:]
    assert snapshot(run / "checkpoints")["epoch_001.pt"] == before["epoch_001.pt"]
    _assert_same_run(run, trained_run)


def test_kill_mid_epoch_then_resume(trained_run, fault_data, tmp_path):
    """kill -9 in the middle of epoch 2's steps: --resume replays epoch 2 from epoch_001.pt, bit-identical."""
    run = tmp_path / "run"
    proc, marker = stalling_trainer(tmp_path, "step", train_argv(fault_data, run))
    kill_when_stalled(proc, marker)
    assert [h["epoch"] for h in _history(run)] == [1] and _history(run)[0]["metrics"]
    resumed = stalling_trainer(tmp_path, "none", train_argv(fault_data, run, "--resume"))[0]
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err[-3000:]
    _assert_same_run(run, trained_run)


def test_kill_during_checkpoint_write_then_resume(trained_run, fault_data, tmp_path):
    """kill -9 after epoch 2's checkpoint went to its temporary file, before the rename: the previous
    checkpoint is intact, the stray file is removed on --resume, and the result is bit-identical."""
    run = tmp_path / "run"
    proc, marker = stalling_trainer(tmp_path, "save", train_argv(fault_data, run))
    kill_when_stalled(proc, marker)
    ckpts = run / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir() if not p.name.startswith(".")) == ["epoch_001.pt"]
    assert len(list(ckpts.glob(".tmp-epoch_002.pt-*"))) == 1
    resumed = stalling_trainer(tmp_path, "none", train_argv(fault_data, run, "--resume"))[0]
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err[-3000:]
    _assert_same_run(run, trained_run)
