"""detbench.runtime (thread-runtime defaults set at import, the user's environment wins) and the
competing load of the benchmarks (detbench.utils.bench.BusyLoad, the tools' --load)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from detbench import runtime
from detbench.utils.bench import BusyLoad, idle_and_loaded, load_line, ratio, runtime_line
import tools.bench_sim

KEYS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS", "NUMBA_THREADING_LAYER", "NUMBA_NUM_THREADS",
        runtime.MARKER, *runtime.MALLOC, "DETBENCH_MALLOC")


def python(code: str, **env) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter whose environment has none of the runtime variables but ``env``."""
    base = {k: v for k, v in os.environ.items() if k not in KEYS}
    return subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                          timeout=120)


REPORT = ("import json, os, detbench.runtime as r; "
          "print(json.dumps({k: [os.environ.get(k), v['set_by']] for k, v in r.describe()['env'].items()}))")


def test_defaults_are_in_the_environment_after_import():
    p = python(REPORT)
    assert p.returncode == 0, p.stderr
    env = json.loads(p.stdout)
    for key, value in runtime.DEFAULTS.items():
        assert env[key] == [value, "detbench"]
    assert env["OMP_WAIT_POLICY"] == [None, None]


def test_the_users_values_win():
    p = python(REPORT + "; import numba; print(numba.config.THREADING_LAYER)",
               OMP_WAIT_POLICY="ACTIVE", NUMBA_THREADING_LAYER="omp", OMP_NUM_THREADS="1")
    assert p.returncode == 0, p.stderr
    lines = p.stdout.split("\n")
    env = json.loads(lines[0])
    assert env["OMP_WAIT_POLICY"] == ["ACTIVE", "user"]
    assert env["NUMBA_THREADING_LAYER"] == ["omp", "user"]
    assert env["OMP_NUM_THREADS"] == ["1", "user"]
    assert lines[1] == "omp"


def test_child_processes_inherit_the_defaults_as_detbench_s():
    code = ("import subprocess, sys, detbench; "
            f"print(subprocess.run([sys.executable, '-c', {REPORT!r}], capture_output=True, text=True).stdout)")
    p = python(code)
    assert p.returncode == 0, p.stderr
    env = json.loads(p.stdout)
    assert env["GOMP_SPINCOUNT"] == [runtime.DEFAULTS["GOMP_SPINCOUNT"], "detbench"]


MMAPPED = ("import ctypes, json, detbench.runtime as r; libc = ctypes.CDLL('libc.so.6'); "
           "libc.malloc.restype = ctypes.c_void_p; p = libc.malloc(16 << 20); "
           "print(json.dumps([r.describe()['malloc'], bool(ctypes.c_size_t.from_address(p - 8).value & 2)]))")


@pytest.mark.skipif(not (sys.platform.startswith("linux") and os.confstr("CS_GNU_LIBC_VERSION")),
                    reason="glibc's allocator only")
def test_the_allocator_serves_mib_tensors_from_the_heap_unless_the_user_set_it():
    # A 16 MiB block comes from the heap after import detbench (glibc's size field: bit 2 = mmapped),
    # from its own mmap with glibc's defaults, which a MALLOC_ variable of the user's keeps.
    p = python(MMAPPED)
    assert p.returncode == 0, p.stderr
    malloc, mmapped = json.loads(p.stdout)
    assert malloc == {"set_by": "detbench", "MALLOC_MMAP_THRESHOLD_": 64 << 20, "MALLOC_TRIM_THRESHOLD_": 256 << 20}
    assert mmapped is False
    p = python(MMAPPED, MALLOC_TRIM_THRESHOLD_="131072")
    assert p.returncode == 0, p.stderr
    malloc, mmapped = json.loads(p.stdout)
    assert malloc == {"set_by": "user", "MALLOC_MMAP_THRESHOLD_": None, "MALLOC_TRIM_THRESHOLD_": "131072"}
    assert mmapped is True
    p = python(MMAPPED, DETBENCH_MALLOC="glibc")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout) == [{"set_by": "user", "MALLOC_MMAP_THRESHOLD_": None,
                                     "MALLOC_TRIM_THRESHOLD_": None}, True]


def test_torch_keeps_its_thread_count_after_a_numba_kernel():
    # numba's omp layer resets OpenMP's thread count when its pool starts; the runtime puts it back.
    code = ("import detbench, torch, numba, numpy as np\n"
            "@numba.njit(parallel=True)\n"
            "def total(a):\n"
            "    s = 0.0\n"
            "    for i in numba.prange(a.shape[0]):\n"
            "        s += a[i]\n"
            "    return s\n"
            "total(np.ones(10000))\n"
            "print(torch.get_num_threads(), numba.get_num_threads(), numba.threading_layer())")
    p = python(code, NUMBA_NUM_THREADS="2", OMP_NUM_THREADS="1")
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["1", "2", "omp"]


def test_numba_imported_first_still_gets_the_threading_layer():
    p = python("import numba; import detbench; print(numba.config.THREADING_LAYER)")
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == runtime.DEFAULTS["NUMBA_THREADING_LAYER"]


def test_torch_imported_first_warns_once_unless_the_user_chose():
    p = python("import warnings; warnings.simplefilter('always'); import torch; import detbench; "
               "import detbench.runtime")
    assert p.returncode == 0 and p.stderr.count("RuntimeWarning") == 1 and "OMP_WAIT_POLICY" in p.stderr
    p = python("import warnings; warnings.simplefilter('always'); import torch; import detbench",
               OMP_WAIT_POLICY="ACTIVE")
    assert p.returncode == 0 and "RuntimeWarning" not in p.stderr


def test_apply_defaults_on_a_mapping_keeps_set_values():
    env = {"GOMP_SPINCOUNT": "0"}
    applied = runtime.apply_defaults(env)
    assert env["GOMP_SPINCOUNT"] == "0" and "GOMP_SPINCOUNT" not in applied
    assert all(env[k] == v for k, v in applied.items()) and set(applied) == set(runtime.DEFAULTS) - {"GOMP_SPINCOUNT"}
    assert runtime.apply_defaults(env) == {}


def test_dataloader_workers_use_one_thread_each():
    p = python("from detbench.train.rng import worker_init_fn; worker_init_fn(0); import numba, torch; "
               "print(torch.get_num_threads(), numba.get_num_threads())", NUMBA_NUM_THREADS="2")
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["1", "1"]


def _busy_children() -> list[int]:
    """Live busy-loop processes started by this process (BusyLoad passes its parent's pid)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if any(b"getppid" in c for c in cmd) and str(os.getpid()).encode() in cmd:
                pids.append(int(d.name))
    return pids


linux_only = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


@linux_only
def test_busy_load_starts_and_stops_its_processes():
    with BusyLoad(2, settle_s=0.2) as load:
        assert len(_busy_children()) == 2
        assert all(p.poll() is None for p in load.procs)
    assert _busy_children() == []
    info = load.info()
    assert info["processes"] == 2 and info["wall_s"] >= 0 and info["busy_cores_used"] is not None
    assert "2 busy-loop processes" in load_line(info)
    with pytest.raises(KeyError):
        with BusyLoad(1, settle_s=0.0):
            raise KeyError("the measurement failed")
    assert _busy_children() == []


def test_idle_and_loaded_and_ratio():
    calls = []
    idle, loaded, info = idle_and_loaded(lambda: calls.append(1) or len(calls), 0)
    assert (idle, loaded, info) == (1, None, None)
    idle, loaded, info = idle_and_loaded(lambda: calls.append(1) or len(calls), 1)
    assert (idle, loaded, info["processes"]) == (2, 3, 1)
    assert ratio(3.0, 2.0) == 1.5 and ratio(None, 2.0) is None and ratio(1.0, 0.0) is None
    assert "torch threads" in runtime_line(runtime.describe())


@linux_only
@pytest.mark.slow  # about 20 s: the simulator timed idle and beside a busy process
def test_bench_sim_load_reports_idle_and_loaded(tmp_path):
    bench = tools.bench_sim
    assert bench.main(["--frames", "2", "--frames-per-scene", "2", "--heights", "1.0", "--mode", "counts",
                       "--load", "1", "--out", str(tmp_path), "--no-progress"]) == 0
    assert _busy_children() == []
    rep = json.loads((tmp_path / "bench_sim.json").read_text())
    assert rep["load"]["processes"] == 1 and "load_average_1min_before" in rep["load"]
    run = rep["runs"][0]
    assert run["loaded"]["wall_s"] > 0 and run["loaded"]["wall_ratio"] == ratio(run["loaded"]["wall_s"], run["wall_s"])
    assert rep["runtime"]["env"]["GOMP_SPINCOUNT"]["value"] is not None
    md = (tmp_path / "bench_sim.md").read_text()
    assert "1 busy-loop process" in md and "x idle" in md
