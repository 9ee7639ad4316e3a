"""A full disk while training or simulating (issue 17.8), emulated by a small file-size limit
(RLIMIT_FSIZE) in a subprocess: this machine offers no small file system to fill. The error says
what could not be written and why; no temporary file is left; earlier files are intact."""
import resource

import pytest

from faultkit import run_python, snapshot, train_argv

LIMIT = 200_000  # bytes: config.yaml and history.json fit, a SECOND smoke checkpoint (1.3 MB) does not


def _limited():
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def test_disk_full_during_training(trained_run, fault_data, tmp_path):
    """The ground-truth database already exists (trained_run built it), so the first file too large is
    the first checkpoint."""
    data_before = snapshot(fault_data)
    run = tmp_path / "run"
    proc = run_python(["tools/train.py", *train_argv(fault_data, run)], preexec_fn=_limited)
    ckpt = run / "checkpoints" / "epoch_001.pt"
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert f"error: {ckpt}: could not be written: File too large" in proc.stderr and "--resume" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not list((run / "checkpoints").glob("*")) and (run / "history.json").is_file()
    assert snapshot(fault_data) == data_before


def test_disk_full_while_simulating(tmp_path):
    """The dataset is built beside OUT (`.tmp-new-sim-PID`): the error names the file in it that could not be
    written, the half-built folder is removed and OUT is never created."""
    out = tmp_path / "sim"
    proc = run_python(["tools/simulate.py", "--out", str(out), "--frames", "2", "--heights", "1.8",
                       "--no-progress"], preexec_fn=_limited)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert f"error: {tmp_path / '.tmp-new-sim-'}" in proc.stderr and "/points/1.8/0000_000.npy" in proc.stderr
    assert "File too large" in proc.stderr and f"{out} is unchanged" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_abandoned_and_failed_default_dataset_builds_are_removed(tmp_path, monkeypatch):
    """A `.tmp-sim-*-PID` folder of a killed build is removed by the next build; a failed build removes
    its own; a finished dataset is kept."""
    import detbench.sim.dataset as simds

    cfg = {"frames": 4, "frames_per_scene": 2, "heights": [1.8], "cache_dir": str(tmp_path)}
    dead = tmp_path / ".tmp-sim-paper-2f-0123456789ab-999999999"  # no process has this id
    dead.mkdir()
    (dead / "points").mkdir()
    real = simds.simulate_dataset

    def fails(root, **kw):
        real(root, **kw)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(simds, "simulate_dataset", fails)
    with pytest.raises(OSError, match="No space left"):
        simds.default_dataset(cfg, progress=False)
    assert not dead.exists() and not list(tmp_path.glob(".tmp-*"))
    monkeypatch.setattr(simds, "simulate_dataset", real)
    final = simds.default_dataset(cfg, progress=False)
    assert (final / "dataset.json").is_file() and not list(tmp_path.glob(".tmp-*"))
