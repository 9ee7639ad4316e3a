"""Thread runtimes: thread counts and OpenMP spinning, set once before torch or numba starts.

detbench runs two thread pools in one process: torch's intra-op pool (the GNU libgomp that
the torch wheel bundles) and numba's parallel kernels (``parallel=True``, its ``omp`` layer on
the system libgomp). Both read their settings from environment variables when they start,
so `apply_defaults` sets them in ``os.environ`` when ``import detbench`` runs (this module is
the first thing ``detbench/__init__.py`` imports, and every tool imports detbench before
torch):

- ``OMP_NUM_THREADS`` = cores - 1 (at least 1; 1 on a 2-core machine): torch's intra-op
  threads. detbench's torch work is many small ops (gathers, scatters, sorts, small GEMMs);
  two threads that must meet at the end of every op lose a whole scheduler time slice each
  time another process holds one of the cores.
- ``GOMP_SPINCOUNT=3000``: an OpenMP thread waiting for work spins about 3,000 iterations
  (tens of microseconds) before it sleeps, instead of libgomp's default 300,000 (a few
  milliseconds, taken from a competing process). Sleeping at once (``OMP_WAIT_POLICY=PASSIVE``)
  is what a waiting thread should do under load, but waking a sleeping thread costs ~0.1 ms
  on an idle (virtual) machine, and that made idle torch ops 3-9x slower.
- ``NUMBA_THREADING_LAYER=omp``: numba's kernels on OpenMP, one thread per core
  (``NUMBA_NUM_THREADS`` is numba's default). numba's ``workqueue`` layer wakes its threads
  through condition variables, which made the simulator 2x slower on the idle machine.

The C allocator (glibc on Linux) is set once at import too (`tune_malloc`): allocations up to
64 MiB come from the heap rather than from fresh ``mmap`` pages, and up to 256 MiB of freed heap
stays mapped. A forward pass allocates and frees tensors of a few MiB hundreds of times; with
glibc's defaults many of them are new pages, zeroed by the kernel on first touch, which made
PointRCNN's inference about 1.4x slower (docs/benchmarks.md, "The allocator"). The outputs do
not change. ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` in the environment (glibc
reads them itself) or ``DETBENCH_MALLOC=glibc`` (glibc's own defaults) leaves the allocator alone.

numba's omp layer resets OpenMP's thread count to numba's when its pool starts, and torch
reads that count; so the pool is started here, at import (about 0.1 s), and the count put
back (`_start_numba_pool`).

Why, in figures: docs/benchmarks.md, "Thread runtimes on a shared CPU". Every default is
set only where the variable is missing: a variable the user set (even to the same value)
wins, and `describe` reports which values came from the user. DataLoader workers use one
torch and one numba thread each (`worker_threads`).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import warnings

__all__ = ["DEFAULTS", "MALLOC", "apply_defaults", "describe", "tune_malloc", "worker_threads", "set_threads"]

# Environment defaults, applied with setdefault before torch or numba reads them.
DEFAULTS: dict[str, str] = {
    "OMP_NUM_THREADS": str(max(1, (os.cpu_count() or 1) - 1)),
    "GOMP_SPINCOUNT": "3000",
    "NUMBA_THREADING_LAYER": "omp",
}
# glibc mallopt parameters (bytes) set at import: M_MMAP_THRESHOLD (-3), M_TRIM_THRESHOLD (-1).
MALLOC: dict[str, tuple[int, int]] = {"MALLOC_MMAP_THRESHOLD_": (-3, 64 << 20),
                                      "MALLOC_TRIM_THRESHOLD_": (-1, 256 << 20)}
_malloc_state: dict[str, object] = {"set_by": None}
# Names of the DEFAULTS that detbench (not the user) set, for child processes that inherit them.
MARKER = "DETBENCH_RUNTIME_DEFAULTS"
# Variables that describe() reports (the defaults and the ones a user may set instead).
REPORTED = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS", "NUMBA_THREADING_LAYER", "NUMBA_NUM_THREADS")

# Which of REPORTED the user had set before detbench was imported, and which defaults detbench
# set (both filled by the first apply_defaults on os.environ, at import).
_user_set: dict[str, str] = {}
_applied: dict[str, str] = {}
_imported_first = [True]
# Settings numba cannot even be imported with (NUMBA_NUM_THREADS=0), set aside at import so the tool can start
# and refuse them in one line (detbench.utils.cli.environment_problem) instead of failing inside numba's import.
SET_ASIDE: dict[str, str] = {}


def _set_aside_invalid(env) -> None:
    threads = env.get("NUMBA_NUM_THREADS")
    if threads is not None and not (threads.strip().isdigit() and int(threads) >= 1):
        SET_ASIDE["NUMBA_NUM_THREADS"] = env.pop("NUMBA_NUM_THREADS")


def apply_defaults(environ=None) -> dict[str, str]:
    """Set every missing `DEFAULTS` variable in ``environ`` (``os.environ``); return those set.

    Idempotent. When torch was imported before this ran and the user chose no OpenMP wait
    (GOMP_SPINCOUNT or OMP_WAIT_POLICY), torch's OpenMP runtime has already started with
    libgomp's long spin: one RuntimeWarning says so and how to fix it.
    """
    env = os.environ if environ is None else environ
    # Defaults a parent detbench process set (a tool's worker, a DataLoader worker) are not the user's.
    inherited = {k for k in env.get(MARKER, "").split(",") if k in DEFAULTS and k in env}
    first = environ is None and _imported_first[0]
    if first:
        _set_aside_invalid(env)
        _imported_first[0] = False
        _user_set.update({k: env[k] for k in REPORTED if k in env and k not in inherited})
    applied = {}
    for key, value in DEFAULTS.items():
        if key not in env:
            env[key] = value
            applied[key] = value
    env[MARKER] = ",".join(sorted(inherited | set(applied)))
    if environ is None:
        _applied.update({k: env[k] for k in inherited})
        _applied.update(applied)
        _sync_numba_config(applied)
        if first and "torch" in sys.modules and not {"GOMP_SPINCOUNT", "OMP_WAIT_POLICY"} & set(_user_set):
            warnings.warn(
                "torch was imported before detbench, so torch's OpenMP runtime started without detbench's "
                "settings: its waiting threads spin for milliseconds, which makes torch ops up to 10-30x slower "
                "when another process shares the CPU (docs/benchmarks.md). Import detbench before torch, or "
                "set GOMP_SPINCOUNT=3000 (or OMP_WAIT_POLICY) in the environment.", RuntimeWarning, stacklevel=4)
    return applied


def _sync_numba_config(applied: dict[str, str]) -> None:
    """numba reads NUMBA_* variables when it is imported: if it already was, set its config too
    (the threading layer is chosen at the first parallel launch, so this still takes effect)."""
    numba = sys.modules.get("numba")
    if numba is None or "NUMBA_THREADING_LAYER" not in applied:
        return
    try:
        numba.config.THREADING_LAYER = applied["NUMBA_THREADING_LAYER"]
    except AttributeError:  # a partially imported numba: it will read the environment itself
        pass


def _start_numba_pool() -> None:
    """Start numba's thread pool now and give OpenMP back torch's thread count.

    numba's ``omp`` layer sets OpenMP's thread count to numba's (one per core) when its pool
    starts, and torch's libgomp reads that count (measured: torch 1 -> 2 threads after the
    first numba kernel), which would undo OMP_NUM_THREADS at the first parallel kernel. So the
    pool starts here (about 0.1 s) and the count is put back: through torch when it is
    already imported, else through OpenMP itself, where torch reads it when it starts."""
    try:
        import numba
        from numba.np.ufunc import parallel

        parallel._launch_threads()
        if numba.threading_layer() != "omp":
            return
        n = int(os.environ.get("OMP_NUM_THREADS", "").split(",")[0])
    except (ImportError, AttributeError, ValueError, RuntimeError):
        # no numba, a layer numba cannot load (its first kernel reports it), or no usable count
        return
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
        return
    try:
        import ctypes

        ctypes.CDLL("libgomp.so.1").omp_set_num_threads(n)
    except (OSError, AttributeError):
        pass


def tune_malloc() -> str | None:
    """Set glibc's mmap and trim thresholds to `MALLOC` (module docstring); idempotent. Returns who set
    the allocator: "detbench", "user" (a MALLOC_ variable or DETBENCH_MALLOC=glibc: nothing changed) or
    None (not glibc, e.g. macOS, Windows or musl: nothing changed)."""
    if _malloc_state["set_by"] is not None:
        return _malloc_state["set_by"]
    if any(k in os.environ for k in MALLOC) or os.environ.get("DETBENCH_MALLOC") == "glibc":
        _malloc_state["set_by"] = "user"
        return "user"
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        if not hasattr(libc, "gnu_get_libc_version"):  # mallopt's parameters are glibc's
            return None
    except (OSError, AttributeError):
        return None
    if all(mallopt(param, value) == 1 for param, value in MALLOC.values()):
        _malloc_state["set_by"] = "detbench"
    return _malloc_state["set_by"]


def set_threads(n: int) -> None:
    """Use ``n`` threads in torch's intra-op pool and in numba's parallel kernels (numba: at most
    its pool size, NUMBA_NUM_THREADS, fixed when its pool starts)."""
    import numba
    import torch

    torch.set_num_threads(int(n))
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))


def worker_threads() -> None:
    """A DataLoader worker process: one torch thread (torch's DataLoader already does this) and one
    numba thread, so workers beside the training process do not oversubscribe the cores."""
    set_threads(1)


def describe() -> dict:
    """The runtime settings in force, for reports: each variable's value and whether it came from
    the user's environment or from detbench; torch's and numba's thread counts; numba's
    threading layer (None until its first parallel launch); the allocator's thresholds (bytes) and who
    set them; the 1-minute load average."""
    out: dict = {"env": {}}
    for key in REPORTED:
        value = os.environ.get(key)
        source = "user" if key in _user_set else ("detbench" if key in _applied else None)
        out["env"][key] = {"value": value, "set_by": source if value is not None else None}
    torch = sys.modules.get("torch")
    out["torch_threads"] = torch.get_num_threads() if torch is not None else None
    numba = sys.modules.get("numba")
    if numba is not None:
        out["numba_threads"] = numba.get_num_threads()
        try:
            out["numba_threading_layer"] = numba.threading_layer()
        except ValueError:  # no parallel kernel has run yet
            out["numba_threading_layer"] = None
    set_by = _malloc_state["set_by"]
    thresholds = {k: v for k, (_, v) in MALLOC.items()} if set_by == "detbench" else \
        {k: os.environ.get(k) for k in MALLOC}  # the user's (or glibc's defaults: None)
    out["malloc"] = {"set_by": set_by, **thresholds}
    out["load_average_1min"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    return out


apply_defaults()
tune_malloc()
_start_numba_pool()
