"""How many of a study's jobs this machine has room for: the cores this process may use, less the other load.

A study runs by default one job per core it may use (`usable_cores`: the CPUs of its affinity mask,
capped by a cgroup CPU quota when /sys/fs/cgroup/cpu.max sets one). Other processes may keep some
of those cores busy (a `pip install` in another terminal, another study), and that load comes and
goes, so it is measured again whenever a slot frees up (`MachineLoad.other_cores`): the CPU time
spent on those cores (or, under a quota, by the cgroup) between two samples, less the CPU time of
this process and its descendants (the study's own jobs), per second of wall time. The first
estimate needs two samples `window_s` apart; later ones compare with the previous sample once
`min_interval_s` has passed, so a short burst does not decide for long.

Linux's /proc and /sys are read; where they are missing there is no estimate and every slot runs.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

CPU_MAX = Path("/sys/fs/cgroup/cpu.max")  # cgroup v2: "QUOTA PERIOD" in microseconds, or "max PERIOD"
CPU_STAT = Path("/sys/fs/cgroup/cpu.stat")  # cgroup v2: usage_usec, the cgroup's CPU time


def cgroup_cpu_quota(path: Path = CPU_MAX) -> float | None:
    """The cores a cgroup CPU quota allows (QUOTA / PERIOD), or None when none is set or there is no file."""
    try:
        quota, period = path.read_text(encoding="ascii").split()[:2]
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    try:
        return float(quota) / float(period) if float(period) > 0 else None
    except ValueError:
        return None


def _affinity() -> set[int]:
    try:
        return set(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return set(range(os.cpu_count() or 1))


def usable_cores(quota: float | None = None, affinity: set[int] | None = None) -> int:
    """The cores this process may use: its affinity mask, capped by the cgroup CPU quota (whole cores, at least
    1). `quota` and `affinity` default to this process's."""
    cores = len(_affinity() if affinity is None else affinity)
    quota = cgroup_cpu_quota() if quota is None else quota
    if quota is not None:
        cores = min(cores, int(quota))
    return max(1, cores)


@dataclass(frozen=True)
class CpuSample:
    """CPU seconds since boot at wall time `t` (seconds): `busy_s` on the cores this process may use (or by its
    cgroup), `ours_s` by this process and its descendants."""

    t: float
    busy_s: float
    ours_s: float


def _busy_on(cpus: set[int]) -> float | None:
    """Busy seconds since boot of the CPUs `cpus` (/proc/stat: every field but idle and iowait)."""
    tick = os.sysconf("SC_CLK_TCK")
    busy = 0.0
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            for line in fh:
                name, *fields = line.split()
                if not name.startswith("cpu") or name == "cpu" or int(name[3:]) not in cpus:
                    continue
                values = [float(x) for x in fields]
                busy += sum(values) - values[3] - (values[4] if len(values) > 4 else 0.0)
    except (OSError, ValueError):
        return None
    return busy / tick


def _cgroup_busy(path: Path = CPU_STAT) -> float | None:
    try:
        for line in path.read_text(encoding="ascii").splitlines():
            key, value = line.split()
            if key == "usage_usec":
                return float(value) / 1e6
    except (OSError, ValueError):
        return None
    return None


def _ours() -> float | None:
    """CPU seconds of this process and its descendants, the ended ones included (/proc/<pid>/stat)."""
    tick = os.sysconf("SC_CLK_TCK")
    table: dict[int, tuple[int, float]] = {}  # pid -> (parent, own + reaped children's ticks)
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            text = (entry / "stat").read_text(encoding="ascii", errors="replace")
        except OSError:
            continue  # ended meanwhile
        rest = text[text.rindex(")") + 2:].split()  # from field 3 (state) on
        table[int(entry.name)] = (int(rest[1]), sum(float(x) for x in rest[11:15]))
    me = os.getpid()
    if me not in table:
        return None
    children: dict[int, list[int]] = {}
    for pid, (parent, _) in table.items():
        children.setdefault(parent, []).append(pid)
    total, todo = 0.0, [me]
    while todo:
        pid = todo.pop()
        total += table[pid][1]
        todo += children.get(pid, [])
    return total / tick


def read_cpu_sample() -> CpuSample | None:
    """This machine's `CpuSample` now, or None where /proc (or the cgroup's cpu.stat under a quota) is missing."""
    busy = _cgroup_busy() if cgroup_cpu_quota() is not None else _busy_on(_affinity())
    ours = _ours() if busy is not None else None
    return None if busy is None or ours is None else CpuSample(time.monotonic(), busy, ours)


class MachineLoad:
    """The cores other processes keep busy, measured again on request (see the module's docstring).

    read: the sampler (`read_cpu_sample`; a test gives its own); sleep: how the first estimate waits."""

    def __init__(self, read: Callable[[], CpuSample | None] = read_cpu_sample, *, window_s: float = 0.5,
                 min_interval_s: float = 2.0, sleep: Callable[[float], None] = time.sleep):
        self.read, self.window_s, self.min_interval_s, self.sleep = read, window_s, min_interval_s, sleep
        self.last: CpuSample | None = None
        self.estimate: float | None = None

    @staticmethod
    def _between(a: CpuSample, b: CpuSample) -> float:
        return max(0.0, ((b.busy_s - a.busy_s) - (b.ours_s - a.ours_s)) / (b.t - a.t))

    def other_cores(self) -> float | None:
        """Cores busy with other processes' work, over the time since the previous estimate (None: not
        measurable here)."""
        now = self.read()
        if now is None:
            return self.estimate
        if self.last is None:
            self.sleep(self.window_s)
            later = self.read()
            if later is None or later.t <= now.t:
                return None
            self.estimate, self.last = self._between(now, later), later
        elif now.t - self.last.t >= self.min_interval_s:
            self.estimate, self.last = self._between(self.last, now), now
        return self.estimate


def slots_note(allowed: int, slots: int, other: float | None) -> str | None:
    """Why fewer jobs than slots run: "1 of 2 slots: the machine's other load uses 1 core" (None when all do)."""
    if allowed >= slots or other is None:
        return None
    busy = int(round(other))
    return f"{allowed} of {slots} slots: the machine's other load uses {busy} core{'s' if busy != 1 else ''}"


__all__ = ["CpuSample", "MachineLoad", "cgroup_cpu_quota", "read_cpu_sample", "slots_note", "usable_cores"]
