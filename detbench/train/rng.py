"""The random-number generators of a training run: seeds and saved state, for repeatable runs and exact resumes on CPU.

Randomness in training comes from three places, each pinned down here:

- data order: the sampler's permutation is a function of (seed, epoch) (`DistributedSampler`
  semantics, also used with one process);
- augmentation: each sample's generator is `sample_rng(seed, epoch, index)`, so a frame's
  augmentation does not depend on which worker loads it or on what ran before;
- everything else (model initialisation, dropout, the point sampling and proposal sampling of the
  two-stage models): the global python / numpy / torch generators, seeded by `seed_everything`
  and saved in checkpoints with `capture_rng_state`. With several processes each rank seeds them
  with its own `rank_seed`, so the ranks do not draw the same dropout masks and samples for
  different frames (the weights are rank 0's either way: DDP copies them to every rank).

Exact replay holds on the CPU. On CUDA, kernels that add in parallel (`index_add_` in the sparse
convolution, atomics in scatter reductions) and cuDNN's algorithm choice make the last bits vary
from run to run; `deterministic_algorithms` asks torch for deterministic kernels where it has them.
"""
from __future__ import annotations

import os
import random
import signal

import numpy as np
import torch

from detbench.runtime import worker_threads

__all__ = ["seed_everything", "rank_seed", "sample_rng", "worker_init_fn", "capture_rng_state", "restore_rng_state",
           "deterministic_algorithms"]

_RANK_SEED_STRIDE = 1_000_003  # a prime: rank seeds of nearby run seeds do not collide


def seed_everything(seed: int) -> None:
    """Seed python's `random`, numpy's legacy global generator and torch (CPU and every CUDA device)."""
    seed = int(seed)
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)  # also seeds every CUDA device


def rank_seed(seed: int, rank: int) -> int:
    """The seed of the global generators on `rank`: `seed` itself on rank 0 (a single process is unchanged)."""
    return int(seed) + _RANK_SEED_STRIDE * int(rank)


def deterministic_algorithms() -> None:
    """Ask torch for deterministic kernels from now on (CUDA: cuDNN without benchmarking, deterministic
    `index_add_` and scatters, cuBLAS with a fixed workspace). An op without a deterministic kernel warns once
    naming itself instead of failing. Slower; call it before the first CUDA operation."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.use_deterministic_algorithms(True, warn_only=True)


def sample_rng(seed: int, epoch: int, index: int) -> np.random.Generator:
    """The numpy generator for augmenting dataset item `index` in `epoch` (all >= 0)."""
    if seed < 0 or epoch < 0 or index < 0:
        raise ValueError(f"sample_rng needs non-negative seed, epoch and index, got {seed}, {epoch}, {index}")
    return np.random.default_rng([int(seed), int(epoch), int(index)])


def worker_init_fn(worker_id: int) -> None:
    """DataLoader worker start-up: seed python and numpy from the worker's torch seed.

    torch gives each worker `base_seed + worker_id` (base_seed drawn from the DataLoader's
    generator, which the loop seeds per epoch), so workers differ and runs repeat. Workers
    ignore Ctrl-C: the main process handles it (finishes the step, saves, stops the workers).
    Each worker uses one torch and one numba thread (`detbench.runtime.worker_threads`): the
    training process already uses the cores.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    worker_threads()
    s = torch.initial_seed() % (2 ** 32)
    random.seed(s)
    np.random.seed(s)


def capture_rng_state() -> dict:
    """The global generators' states as tensors, lists and ints (loadable with weights_only=True)."""
    version, mt, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "python": {"version": int(version), "state": [int(v) for v in mt], "gauss": gauss},
        "numpy": {"name": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }
    return state


def restore_rng_state(state: dict) -> None:
    """Inverse of `capture_rng_state`; CUDA states are restored when the device count matches."""
    py = state["python"]
    random.setstate((py["version"], tuple(py["state"]), py["gauss"]))
    npst = state["numpy"]
    keys = npst["keys"].numpy().astype(np.uint32)
    np.random.set_state((npst["name"], keys, npst["pos"], npst["has_gauss"], npst["cached_gaussian"]))
    torch.set_rng_state(state["torch"].cpu())
    cuda = state.get("cuda") or []
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([s.cpu() for s in cuda])
