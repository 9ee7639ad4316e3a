"""Helpers of the fault suite: the shared training command, processes to run or kill, and `snapshot`
(to prove that a refused command changed nothing)."""
from __future__ import annotations

import hashlib
import subprocess
import time
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# the run every training test starts from: SECOND, smoke preset (2 epochs), no TensorBoard
TRAIN_FLAGS = ["--model", "second", "--height", "1.8", "--preset", "smoke", "--no-progress",
               "--set", "train.tensorboard=false"]

# a training process whose hooks stall it at a chosen point, so a test can kill -9 it exactly there:
# argv: HOOK MARKER TRAIN_ARGS...; HOOK is none | step (the 6th of 8 optimisation steps, mid epoch 2) |
# eval (the first evaluation) | save (epoch 2's checkpoint, written to its temporary file and not yet
# renamed); MARKER is created when the process stalls
STALLING_TRAINER = '''
import runpy, sys, time
hook, marker = sys.argv[1], sys.argv[2]
import detbench, torch
import detbench.train.inference as inference
import detbench.train.loop as loop

def stall():
    open(marker, "w").close()
    time.sleep(300)

if hook == "step":
    real_step, steps = loop._step, []

    def step(run, batch, *rest):
        steps.append(1)
        if len(steps) == 6:
            stall()
        return real_step(run, batch, *rest)

    loop._step = step
elif hook == "eval":
    inference.predict_frames = lambda *a, **k: stall()
elif hook == "save":
    real_save = torch.save

    def save(obj, f, *a, **k):
        real_save(obj, f, *a, **k)
        if "epoch_002" in str(f):
            stall()

    torch.save = save
sys.argv = ["tools/train.py", *sys.argv[3:]]
sys.path.insert(0, ".")  # the repository root (the working directory): tools.train
runpy.run_module("tools.train", run_name="__main__", alter_sys=True)
'''


def train_argv(data: Path, out: Path, *extra: str) -> list[str]:
    return [*TRAIN_FLAGS, "--data", str(data), "--out", str(out), *extra]


def run_python(args: list[str], timeout: float = 300, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout, **kw)


def stalling_trainer(tmp_path: Path, hook: str, argv: list[str]) -> tuple[subprocess.Popen, Path]:
    """(the process, its marker file) of a training run that stalls at `hook`."""
    script, marker = tmp_path / "stalling_trainer.py", tmp_path / f"stalled_{hook}"
    script.write_text(STALLING_TRAINER)
    proc = subprocess.Popen([sys.executable, str(script), hook, str(marker), *argv], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, marker


def snapshot(folder: Path) -> dict[str, tuple[int, int, str]]:
    """relative path -> (size, mtime ns, sha1) of every file under `folder`."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            st = p.stat()
            out[str(p.relative_to(folder))] = (st.st_size, st.st_mtime_ns, hashlib.sha1(p.read_bytes()).hexdigest())
    return out




def kill_when_stalled(proc: subprocess.Popen, marker: Path, timeout: float = 240) -> None:
    """Wait until the stalling trainer reaches its hook, then kill -9 it."""
    t0 = time.monotonic()
    while not marker.exists():
        if proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"the trainer ended (exit {proc.returncode}) before its hook:\n{err[-3000:]}")
        assert time.monotonic() - t0 < timeout, "the trainer never reached its hook"
        time.sleep(0.05)
    proc.kill()
    proc.communicate()


def load_checkpoint_dict(path: Path) -> dict:
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


def same_tensors(a, b) -> bool:
    """Every tensor (nested in dicts and lists) bit-identical."""
    import torch

    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same_tensors(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_tensors(x, y) for x, y in zip(a, b))
    return a == b
