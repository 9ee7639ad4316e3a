"""A full disk while training, simulating or writing a report: a real full file system
(a small tmpfs mounted in a user and mount namespace, `unshare -rm`, where the system allows it; no root
needed) and a small file-size limit (RLIMIT_FSIZE, errno EFBIG) in a subprocess. The error says what
could not be written and why; no temporary or partial file is left; earlier files are intact."""
import json
import os
import resource
import shutil
import subprocess
import sys
import textwrap

import pytest

from tests.faults.faultkit import ROOT, run_python, snapshot, train_argv

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
    assert "could not be written: File too large (the file-size limit" in proc.stderr
    assert f"so {out} is unchanged" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_abandoned_and_failed_default_dataset_builds_are_removed(tmp_path, monkeypatch):
    """A marked staged folder of a killed build (`.tmp-new-<name>-PID` with detbench's build marker) is removed by
    the next build; a build that fails removes its own; a finished dataset is kept; a folder detbench did not
    mark, however it is named, stays."""
    import json

    import detbench.sim.dataset as simds
    from detbench.data.writer import DatasetWriter
    from detbench.utils.staged_folders import BUILD_MARKER

    cfg = {"frames": 4, "frames_per_scene": 2, "heights": [1.8], "cache_dir": str(tmp_path)}
    dead = tmp_path / ".tmp-new-sim-paper-2f-0123456789ab-999999999"  # no process has this id
    (dead / "points").mkdir(parents=True)
    (dead / BUILD_MARKER).write_text(json.dumps({"dest": "sim-paper-2f-0123456789ab", "pid": 999999999}))
    users = [tmp_path / ".tmp-thesis-backup-2023", tmp_path / ".tmp-new-sim-paper-2f-0123456789ab-42"]
    for folder in users:  # no build marker: the user's
        folder.mkdir()
        (folder / "chapter1.tex").write_text("the user's")
    real = DatasetWriter.add

    def fails(self, frames):
        if len(self) == 2:
            raise OSError(28, "No space left on device")
        real(self, frames)

    monkeypatch.setattr(DatasetWriter, "add", fails)
    with pytest.raises(OSError, match="No space left"):
        simds.default_dataset(cfg, progress=False)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert not dead.exists() and left == sorted(p.name for p in users), left
    monkeypatch.setattr(DatasetWriter, "add", real)
    final = simds.default_dataset(cfg, progress=False)
    assert (final / "dataset.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([final.name, *(p.name for p in users)])
    assert all((p / "chapter1.tex").read_text() == "the user's" for p in users)


# Runs inside the namespace, where argv[1:4] are fresh tmpfs mounts of 256 KiB, 1 MiB and 64 KiB: a simulated
# frame (about 0.5 MB of points), a checkpoint (1.3 MB) and a report too large for each; prints what each
# command said and what it left.
IN_FULL_FS = textwrap.dedent('''
    import json, os, subprocess, sys
    sim_fs, run_fs, report_fs, data = sys.argv[1:5]
    train_args = json.loads(sys.argv[5])

    def files(top):
        return sorted(os.path.relpath(os.path.join(d, f), top) for d, _, fs in os.walk(top) for f in fs + _)

    def tool(*args):
        p = subprocess.run([sys.executable, *args], capture_output=True, text=True)
        return {"code": p.returncode, "stderr": p.stderr[-3000:]}

    out = {"simulate": tool("tools/simulate.py", "--out", os.path.join(sim_fs, "sim"), "--frames", "2",
                            "--heights", "1.8", "--no-progress")}
    out["simulate"]["left"] = files(sim_fs)
    out["train"] = tool("tools/train.py", *train_args)
    out["train"]["left"] = files(run_fs)
    from detbench.utils.atomic import DiskFullError, atomic_write_json
    report = os.path.join(report_fs, "report.json")
    atomic_write_json(report, {"old": 1})
    try:
        atomic_write_json(report, {"rows": list(range(100000))})
        out["report"] = {"error": None}
    except DiskFullError as e:
        out["report"] = {"error": str(e)}
    out["report"]["left"] = files(report_fs)
    out["report"]["content"] = open(report).read()
    print(json.dumps(out))
''')


def _namespace_tmpfs_works(where) -> bool:
    if shutil.which("unshare") is None:
        return False
    p = subprocess.run(["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=64k tmpfs "$1"', "sh", str(where)],
                       capture_output=True, text=True)
    return p.returncode == 0


def test_a_real_full_file_system(trained_run, fault_data, tmp_path):
    """The three writers on a tmpfs that is really full (ENOSPC, not the file-size limit above)."""
    mounts = [tmp_path / m for m in ("sim_fs", "run_fs", "report_fs")]
    for m in mounts:
        m.mkdir()
    if not _namespace_tmpfs_works(mounts[0]):
        pytest.skip("this system does not let a user mount a tmpfs in a user namespace (unshare -rm)")
    data_before = snapshot(fault_data)
    script = tmp_path / "in_full_fs.py"
    script.write_text(IN_FULL_FS)
    run = mounts[1] / "run"
    mount = " && ".join(f'mount -t tmpfs -o size={size} tmpfs "${i + 1}"'
                        for i, size in enumerate(("256k", "1m", "64k")))
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", f'{mount} && exec "$4" "$5" "$1" "$2" "$3" "$6" "$7"', "sh",
                           *map(str, mounts), sys.executable, str(script), str(fault_data),
                           json.dumps(train_argv(fault_data, run))],
                          cwd=ROOT, capture_output=True, text=True, timeout=300, env={**os.environ})
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    no_space = "could not be written: No space left on device (0 MiB free in"

    sim = res["simulate"]  # the size estimate refuses it before a byte is written (ENOSPC mid-write: the tests above)
    assert sim["code"] == 2 and f"error: --out {mounts[0] / 'sim'}: the dataset" in sim["stderr"], sim
    assert "free; free some space there" in sim["stderr"] and "Traceback" not in sim["stderr"]
    assert sim["left"] == []  # nothing was built, and sim/ was never made

    train = res["train"]
    ckpt = run / "checkpoints" / "epoch_001.pt"
    assert train["code"] == 2 and f"error: {ckpt}: {no_space}" in train["stderr"], train
    assert "--resume" in train["stderr"] and "Traceback" not in train["stderr"]
    assert "run/checkpoints" in train["left"] and not [f for f in train["left"] if "checkpoints/" in f]
    assert "run/history.json" in train["left"] and "run/config.yaml" in train["left"]

    rep = res["report"]
    assert rep["error"] and rep["error"].startswith(f"{mounts[2] / 'report.json'}: {no_space}")
    assert "any previous version of the file is unchanged" in rep["error"]
    assert rep["left"] == ["report.json"] and json.loads(rep["content"]) == {"old": 1}
    assert snapshot(fault_data) == data_before
