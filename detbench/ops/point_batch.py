"""What the point operations share: the batch layout, indices, arithmetic and backends they
follow, and the argument checks and helpers they call (detbench.ops.sampling, grouping,
interpolate, roi_pool, cylinder).

Contents
- `EMPTY_INDEX`: the index of an empty slot; `TORCH_CHUNK_ELEMS`: the torch paths' chunk size.
- `to_tensor`, `check_xyz`, `check_counts`, `check_same_frames`, `pick_backend`: argument
  checks whose errors name the function, the argument and the fix.
- `frame_offsets`, `xyz_float64`, `num_chunks`: small helpers of the numba paths.

Batches. The points of B frames are concatenated along the first axis, with a per-frame count
vector (`counts`, `xyz_counts`, ..., (B,) non-negative integers summing to the row count; None
means one frame holding every row). Centres, targets and RoIs are batched the same way, each
with its own counts and the same B. Every op works within a frame only. (`cylinder_query`
takes one frame per call.)

Indices. Returned point indices are int64 rows of the concatenated array, so `xyz[index]`
gathers directly. A slot that holds no point is `EMPTY_INDEX` (the rule of detbench.ops).
Frame b's rows are offsets[b]:offsets[b + 1] with offsets = [0, cumsum(counts)]; subtract
offsets[b] for per-frame indices.

Units and arithmetic. Coordinates in metres (the ego ground frame of docs/architecture.md),
headings in radians. Distances are computed in float64 in both backends, in the same order of
operations (dx*dx + dy*dy + dz*dz with d = point - reference), so the two backends agree bit
for bit on one device (`three_nn` takes its square root with torch.sqrt on the output device;
`cylinder_query` compares BEV distances in the points' float type).

Backends. `backend="auto"` runs the numba kernels for CPU tensors (via .numpy(), outputs come
back as tensors) and vectorised torch for tensors on other devices (CUDA), memory linear in the
points (chunked where a pairwise step is needed); `DETBENCH_OPS=torch` makes "auto" take the
torch path on the CPU too (detbench.ops.backend). `backend="torch"` forces the torch path on
any device (the tests run it on CPU against the numba path); `backend="numba"` needs CPU tensors.
numpy arrays are accepted wherever a tensor is and are taken as CPU tensors.
"""
from __future__ import annotations

import numba
import numpy as np
import torch

from detbench.ops.backend import use_torch

__all__ = [
    "EMPTY_INDEX",
    "TORCH_CHUNK_ELEMS",
    "check_counts",
    "check_same_frames",
    "check_xyz",
    "frame_offsets",
    "num_chunks",
    "pick_backend",
    "to_tensor",
    "xyz_float64",
]

# The index of an empty slot (detbench.ops, "Empty slots"). Every real index is >= 0, so
# `index >= 0` marks the filled slots. The numba kernels compile the value in.
EMPTY_INDEX = -1
# Pairwise elements per chunk of the torch paths (their memory bound).
TORCH_CHUNK_ELEMS = 1 << 22


def to_tensor(x, func: str, name: str) -> torch.Tensor:
    """`x` as a tensor (a numeric numpy array or sequence becomes a CPU tensor)."""
    if isinstance(x, torch.Tensor):
        return x
    a = np.asarray(x)
    if a.dtype == object or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{func}: `{name}` must be a numeric tensor or array, got dtype {a.dtype}")
    return torch.from_numpy(np.ascontiguousarray(a))


def check_xyz(x, func: str, name: str, device: torch.device | None = None, cols: int = 3) -> torch.Tensor:
    """(N, >=cols) finite float tensor on `device` (a numpy array is taken as a CPU tensor)."""
    t = to_tensor(x, func, name)
    if t.ndim == 1 and t.shape[0] == 0:
        t = t.reshape(0, cols)
    if t.ndim != 2 or t.shape[1] < cols:
        what = "x, y, z" if cols == 3 else "x, y, z, dx, dy, dz, heading"
        raise ValueError(f"{func}: `{name}` must have shape (N, {cols}) with columns {what} (metres"
                         f"{', radians' if cols == 7 else ''}); got shape {tuple(t.shape)}. "
                         f"Concatenate the frames along the first axis and pass their counts.")
    if not t.dtype.is_floating_point:
        t = t.to(torch.float64)
    if device is not None and t.device != device:
        raise ValueError(f"{func}: `{name}` is on {t.device} but the points are on {device}; move them to one device")
    if t.device.type == "cpu":  # numpy: one thread, no wake-up of torch's pool for a check
        bad = np.flatnonzero(~np.isfinite(t.detach().numpy()[:, :cols]).all(axis=1))
    else:
        bad = (~torch.isfinite(t[:, :cols]).all(dim=1)).nonzero()[:, 0].cpu().numpy()
    if bad.size:
        raise ValueError(f"{func}: `{name}` contain NaN or infinite values (first at row {int(bad[0])}, "
                         f"{bad.size} rows in all); drop or repair those rows first")
    return t


def check_counts(counts, total: int, func: str, name: str, rows: str) -> np.ndarray:
    """(B,) int64 numpy per-frame counts summing to `total` (None: one frame of all rows)."""
    if counts is None:
        return np.array([total], dtype=np.int64)
    c = counts.detach().cpu().numpy() if isinstance(counts, torch.Tensor) else np.asarray(counts)
    if c.ndim == 0:
        c = c.reshape(1)
    if c.ndim != 1 or (c.size and not np.issubdtype(c.dtype, np.integer)):
        raise ValueError(f"{func}: `{name}` must be a 1-D sequence of per-frame integer counts, "
                         f"got shape {c.shape} dtype {c.dtype}")
    c = c.astype(np.int64)
    if (c < 0).any() or int(c.sum()) != total:
        raise ValueError(f"{func}: `{name}` must be non-negative and sum to the number of {rows} ({total}); "
                         f"got {c.tolist()[:8]}{'...' if c.size > 8 else ''} summing to {int(c.sum())}")
    return c


def check_same_frames(a: np.ndarray, b: np.ndarray, func: str, na: str, nb: str) -> None:
    """Two count vectors describe the same number of frames."""
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{func}: `{na}` has {a.shape[0]} frames but `{nb}` has {b.shape[0]}; give one count "
                         "per frame for both (or None for both when there is one frame)")


def pick_backend(backend: str, device: torch.device, func: str) -> str:
    """The path to run, "numba" or "torch", for the `backend` argument and the points' device."""
    if backend not in ("auto", "numba", "torch"):
        raise ValueError(f"{func}: backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    if backend == "auto":
        return "torch" if use_torch(device) else "numba"
    if backend == "numba" and device.type != "cpu":
        raise ValueError(f"{func}: backend='numba' needs CPU tensors, got {device}; use backend='auto' or 'torch'")
    return backend


def frame_offsets(counts: np.ndarray) -> np.ndarray:
    """(B + 1,) int64 [0, cumsum(counts)]: frame b's rows are offsets[b]:offsets[b + 1]."""
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def xyz_float64(t: torch.Tensor) -> np.ndarray:
    """C-contiguous float64 (N, 3) numpy copy of the x, y, z columns of a CPU tensor."""
    return np.ascontiguousarray(t.detach().numpy()[:, :3], dtype=np.float64)


def num_chunks(n: int) -> int:
    """Chunks of work for a parallel numba kernel over n items (4 per thread, at most n)."""
    return int(max(1, min(numba.get_num_threads() * 4, n)))
