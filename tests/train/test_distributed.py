"""The device a training process takes (detbench.train.distributed.resolve_device and tools/train.py --device),
with CUDA faked where the test needs GPUs this machine may not have."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from detbench.train import init_distributed
from detbench.train.distributed import DeviceError, launch_ranks, resolve_device
from tests.helpers import ROOT


def _fake_gpus(monkeypatch, n: int) -> list:
    """torch sees `n` CUDA devices; returns the list set_device calls are appended to."""
    calls = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: n > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: n)
    monkeypatch.setattr(torch.cuda, "set_device", lambda d: calls.append(torch.device(d)))
    return calls


def test_without_cuda_every_cuda_device_is_refused_naming_it(monkeypatch):
    _fake_gpus(monkeypatch, 0)
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("cpu") == torch.device("cpu")
    for name in ("cuda", "cuda:0", "cuda:1"):
        with pytest.raises(DeviceError, match=f"device {name}: torch sees no CUDA device.*--device cpu"):
            resolve_device(name)
    for name, why in (("gpu", "not a device"), ("meta", "training runs on cpu or cuda")):
        with pytest.raises(DeviceError, match=f"device {name}: {why}"):
            resolve_device(name)


def test_one_process_takes_the_gpu_it_names(monkeypatch):
    calls = _fake_gpus(monkeypatch, 2)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    assert resolve_device("cuda") == resolve_device("auto") == torch.device("cuda", 0)
    with pytest.raises(DeviceError, match=r"device cuda:2: only 2 CUDA device\(s\) are visible \(cuda:0 to cuda:1\)"):
        resolve_device("cuda:2")
    for var in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(var, raising=False)
    info = init_distributed("cuda:1")
    assert info.device == torch.device("cuda", 1) and calls == [torch.device("cuda", 1)] and not info.distributed


def test_under_torchrun_each_process_takes_its_local_rank(monkeypatch):
    _fake_gpus(monkeypatch, 2)
    assert resolve_device("cuda", local_rank=1, world_size=2) == torch.device("cuda", 1)
    assert resolve_device("auto", local_rank=1, world_size=2) == torch.device("cuda", 1)
    with pytest.raises(DeviceError, match="device cuda:1: under torchrun each of the 2 processes takes "
                                          "cuda:LOCAL_RANK; give --device cuda"):
        resolve_device("cuda:1", local_rank=0, world_size=2)
    with pytest.raises(DeviceError, match="LOCAL_RANK=2 but only 2 CUDA device"):
        resolve_device("cuda", local_rank=2, world_size=3)
    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(ValueError, match="WORLD_SIZE='two'"):
        launch_ranks()


def _train_tool(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "tools" / "train.py"), *args], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_train_tool_refuses_a_cuda_device_in_one_line_before_it_writes(tmp_path):
    out = tmp_path / "run"
    r = _train_tool("--device", "cuda:1", "--height", "1.8", "--preset", "smoke", "--out", str(out))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --device cuda:1: torch sees no CUDA device"), r.stderr
    assert not out.exists()
    h = _train_tool("--device", "cuda:0", "--help")
    assert h.returncode == 0 and "cuda:N" in h.stdout and not h.stderr
