"""Measuring helpers shared by the benchmarks (tools/bench_*.py, tools/benchmark.py, tools/tradeoff.py):
timed repeats, achieved GFLOP/s, a competing CPU load (`BusyLoad`) for idle-vs-loaded figures, a
detector's latency split by stage (`StageTimer`) and the median / 90th percentile of timed rows."""
from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def timed(fn: Callable[[], object], repeats: int, sync: Callable[[], None]) -> dict:
    """Run ``fn`` once to warm up, then ``repeats`` times; milliseconds (median, best).

    ``sync`` is called after each run (e.g. ``torch.cuda.synchronize``; a no-op on CPU) so
    asynchronous work is inside the measured time."""
    fn()
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append((time.perf_counter() - t0) * 1e3)
    return {"ms": statistics.median(ts), "ms_best": min(ts)}


def gflops(pairs: int, cin: int, cout: int, ms: float) -> float:
    """Useful GFLOP/s: 2 FLOP per multiply-add, pairs * cin * cout multiply-adds."""
    return 2.0 * pairs * cin * cout / (ms * 1e-3) / 1e9 if ms > 0 else float("nan")


# A busy loop that ends by itself when its parent dies (it is re-parented): no process is left
# spinning if the benchmark is killed before its clean-up runs.
_BUSY_LOOP = ("import os, sys\nparent = int(sys.argv[1])\nwhile os.getppid() == parent:\n"
              "    for _ in range(100000): pass\n")


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a live process (Linux /proc; None elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _load_average() -> float | None:
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None


class BusyLoad:
    """``with BusyLoad(n) as load:`` runs ``n`` busy-loop Python processes (each wants a whole
    core) for the duration of the block, then stops them, even on an exception or Ctrl-C.

    ``load.info()`` (after the block) records what the measurement competed with: the number
    of processes, the 1-minute load average before and after, the wall seconds, and the cores
    the busy processes actually got (their CPU seconds / wall seconds, summed; Linux)."""

    def __init__(self, processes: int, settle_s: float = 0.3):
        if processes < 0:
            raise ValueError(f"BusyLoad needs processes >= 0, got {processes}")
        self.processes = int(processes)
        self.settle_s = settle_s
        self.procs: list[subprocess.Popen] = []
        self._info: dict = {"processes": self.processes}

    def __enter__(self) -> BusyLoad:
        self._info["load_average_1min_before"] = _load_average()
        try:
            for _ in range(self.processes):
                self.procs.append(subprocess.Popen([sys.executable, "-S", "-c", _BUSY_LOOP, str(os.getpid())],
                                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                                   stderr=subprocess.DEVNULL))
            if self.procs:
                time.sleep(self.settle_s)  # let them reach their loops before the measurement starts
        except BaseException:
            self.stop()
            raise
        self._t0 = time.perf_counter()
        self._cpu0 = [_cpu_seconds(p.pid) for p in self.procs]
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """Terminate every busy process and wait for it (kill after 5 s); safe to call twice."""
        if hasattr(self, "_t0") and "wall_s" not in self._info:
            wall = time.perf_counter() - self._t0
            cpu1 = [_cpu_seconds(p.pid) for p in self.procs]
            got = [b - a for a, b in zip(self._cpu0, cpu1) if a is not None and b is not None]
            self._info["wall_s"] = round(wall, 2)
            self._info["busy_cores_used"] = round(sum(got) / wall, 2) if got and wall > 0 else None
            self._info["load_average_1min_after"] = _load_average()
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = []

    def info(self) -> dict:
        return dict(self._info)


def idle_and_loaded(measure: Callable[[], T], load: int) -> tuple[T, T | None, dict | None]:
    """``measure()`` on the machine as it is, then (``load`` > 0) again beside ``load`` busy
    processes: (idle result, loaded result or None, `BusyLoad.info()` or None)."""
    idle = measure()
    if load <= 0:
        return idle, None, None
    with BusyLoad(load) as busy:
        loaded = measure()
    return idle, loaded, busy.info()


def ratio(loaded: float | None, idle: float | None) -> float | None:
    """loaded / idle rounded to 0.01 (None when either is missing or idle is not positive)."""
    if loaded is None or idle is None or not idle > 0:
        return None
    return round(loaded / idle, 2)


def load_line(info: dict) -> str:
    """One Markdown phrase for a `BusyLoad.info()`: the processes, the cores they got, the load average."""
    n = info.get("processes", 0)
    text = f"{n} busy-loop process{'es' if n != 1 else ''}"
    if info.get("busy_cores_used") is not None:
        text += f" (together they got {info['busy_cores_used']:.2f} cores over {info.get('wall_s')} s"
        text += f"; 1-min load average {info.get('load_average_1min_before')} -> {info.get('load_average_1min_after')})"
    return text


def runtime_line(desc: dict) -> str:
    """One Markdown phrase for `detbench.runtime.describe()`: the variables set and by whom, thread counts."""
    env = ", ".join(f"{k}={v['value']} ({v['set_by']})" for k, v in desc.get("env", {}).items()
                    if v["value"] is not None)
    parts = [env or "no runtime variables set", f"torch threads {desc.get('torch_threads')}"]
    if "numba_threads" in desc:
        parts.append(f"numba threads {desc['numba_threads']} "
                     f"({desc.get('numba_threading_layer') or 'layer not started'})")
    return "; ".join(parts)


def median_p90(rows: list[dict]) -> dict:
    """{key: {"median", "p90"}} over the rows (dicts of numbers with the same keys), rounded to 0.01;
    p90 is the 90th percentile with linear interpolation between the sorted values."""
    out = {}
    for k in rows[0] if rows else []:
        vals = sorted(float(r[k]) for r in rows)
        pos = 0.9 * (len(vals) - 1)
        lo = int(pos)
        hi = min(lo + 1, len(vals) - 1)
        p90 = vals[lo] + (vals[hi] - vals[lo]) * (pos - lo)
        out[k] = {"median": round(statistics.median(vals), 2), "p90": round(p90, 2)}
    return out


def _proc_status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def reset_peak_rss() -> bool:
    """Start this process's peak resident memory (Linux VmHWM) again from its current RSS, so a
    later `peak_rss_mib()` covers only what ran since (not the start-up's imports). False when the
    system cannot (not Linux, or /proc/self/clear_refs refused): the peak then covers the whole process."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def rss_mib() -> float | None:
    """This process's resident memory now, MiB (Linux; None elsewhere)."""
    kib = _proc_status_kib("VmRSS")
    return None if kib is None else kib / 1024


def peak_rss_mib() -> float:
    """This process's peak resident memory, MiB: VmHWM since the last `reset_peak_rss()` (Linux), else
    the high-water mark since the process started (`getrusage`)."""
    kib = _proc_status_kib("VmHWM")
    if kib is None:
        import resource

        kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return kib / 1024


class StageTimer:
    """Wall time of a model's top-level stages via forward hooks (CUDA synchronised).

    `stages` maps a stage name to the model's top-level child modules it covers (a detector's
    `STAGES`); `times` holds the seconds of each stage since the last `reset()`."""

    def __init__(self, model, stages: dict[str, list[str]], device):
        import torch

        self.sync = (lambda: torch.cuda.synchronize(device)) if str(device).startswith("cuda") else (lambda: None)
        self.times: dict[str, float] = {k: 0.0 for k in stages}
        self._start: dict[str, float] = {}
        owner = {child: stage for stage, children in stages.items() for child in children}
        for name, module in model.named_children():
            if name in owner:
                module.register_forward_pre_hook(self._pre(name))
                module.register_forward_hook(self._post(name, owner[name]))

    def _pre(self, name):
        def hook(module, inputs):
            self.sync()
            self._start[name] = time.perf_counter()
        return hook

    def _post(self, name, stage):
        def hook(module, inputs, output):
            self.sync()
            self.times[stage] += time.perf_counter() - self._start[name]
        return hook

    def reset(self):
        for k in self.times:
            self.times[k] = 0.0

    def time_inference(self, model, batch) -> dict[str, float]:
        """One timed inference of `batch` (forward, then `model.predict`), in milliseconds: each
        stage of the hooks, `post` (predict: decoding and NMS) and `total` (forward + post)."""
        self.reset()
        self.sync()
        t0 = time.perf_counter()
        out = model(batch)
        self.sync()
        t1 = time.perf_counter()
        model.predict(out, batch)
        self.sync()
        t2 = time.perf_counter()
        return {**{k: v * 1000 for k, v in self.times.items()}, "post": (t2 - t1) * 1000, "total": (t2 - t0) * 1000}


__all__ = ["timed", "gflops", "BusyLoad", "idle_and_loaded", "ratio", "load_line", "runtime_line", "median_p90",
           "StageTimer", "reset_peak_rss", "rss_mib", "peak_rss_mib"]
