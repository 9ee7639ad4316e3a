"""Which path an op takes for a tensor: the numba kernels or vectorised torch.

Every op of detbench.ops has two paths for tensor inputs: numba kernels for CPU tensors (the
tensor goes through `.numpy()` and the result comes back as a tensor) and vectorised torch for
tensors on any other device (CUDA). The torch path is the one a GPU runs; on a machine without a
GPU the environment variable `DETBENCH_OPS=torch` makes every op take it for CPU tensors too, so
the whole GPU path (models, training, inference) runs and is tested on the CPU:

    DETBENCH_OPS=torch python3 -m pytest -q tests/models

`DETBENCH_OPS` is `auto` (the default: numba for CPU tensors, torch elsewhere) or `torch`. It is
read at every call, so a test can set it for one block (`forced_backend`). numpy inputs keep
the numba path (they return numpy; there is no torch path to compare with there), and an op's
own `backend="numba"` / `"torch"` argument, where it has one, wins over the variable.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["OPS_ENV", "OPS_MODES", "forced_backend", "ops_mode", "use_torch"]

OPS_ENV = "DETBENCH_OPS"
OPS_MODES = ("auto", "torch")


def ops_mode() -> str:
    """The value of DETBENCH_OPS ("auto" when unset or empty); ValueError naming the variable for another value."""
    mode = os.environ.get(OPS_ENV, "").strip().lower() or "auto"
    if mode not in OPS_MODES:
        raise ValueError(f"{OPS_ENV}={os.environ[OPS_ENV]!r}: not a backend; use {OPS_ENV}=torch (every op on its "
                         f"torch path, the GPU's) or {OPS_ENV}=auto / unset (numba for CPU tensors)")
    return mode


def use_torch(device: torch.device) -> bool:
    """True when a tensor op on `device` takes its torch path: any device but the CPU, and the CPU under
    DETBENCH_OPS=torch."""
    return device.type != "cpu" or ops_mode() == "torch"


@contextmanager
def forced_backend(mode: str) -> Iterator[None]:
    """Run the block with DETBENCH_OPS=`mode` ("auto" or "torch"), then put the variable back as it was."""
    if mode not in OPS_MODES:
        raise ValueError(f"forced_backend: mode must be one of {OPS_MODES}, got {mode!r}")
    before = os.environ.get(OPS_ENV)
    os.environ[OPS_ENV] = mode
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(OPS_ENV, None)
        else:
            os.environ[OPS_ENV] = before
