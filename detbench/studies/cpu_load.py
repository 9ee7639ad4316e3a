"""How many of a study's jobs this machine has room for: the cores this process may use, less the other load.

A study runs by default one job per core it may use (`usable_cores`: the CPUs of its affinity mask,
capped by the tightest cgroup CPU quota of its cgroup and its ancestors, v2's cpu.max or v1's
cpu.cfs_quota_us: a container limited to 2 CPUs on a 64-core node runs 2 jobs, not 64). Other processes may keep some
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

CGROUP_ROOT = Path("/sys/fs/cgroup")  # where the cgroup file systems are mounted
PROC_CGROUP = Path("/proc/self/cgroup")  # this process's cgroups: "0::/path" (v2), "N:cpu,cpuacct:/path" (v1)


@dataclass(frozen=True)
class CpuQuota:
    """The tightest CPU quota over this process's cgroup and its ancestors: `cores` (quota / period) and the
    cgroup folder that sets it, whose CPU time is `usage_file` (v2 cpu.stat, v1 cpuacct.usage) or None."""

    cores: float
    folder: Path
    usage_file: Path | None


def _read_quota(folder: Path) -> float | None:
    """The cores the quota of one cgroup folder allows: v2 cpu.max ("QUOTA PERIOD" or "max PERIOD"), v1
    cpu.cfs_quota_us / cpu.cfs_period_us (-1: none); None without one."""
    try:
        if (folder / "cpu.max").is_file():
            quota, period = (folder / "cpu.max").read_text(encoding="ascii").split()[:2]
        elif (folder / "cpu.cfs_quota_us").is_file():
            quota = (folder / "cpu.cfs_quota_us").read_text(encoding="ascii").strip()
            period = (folder / "cpu.cfs_period_us").read_text(encoding="ascii").strip()
            quota = "max" if quota.startswith("-") else quota
        else:
            return None
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    try:
        return float(quota) / float(period) if float(quota) > 0 and float(period) > 0 else None
    except ValueError:
        return None


def _cgroup_folders(root: Path, proc: Path, controller: str = "cpu") -> list[Path]:
    """This process's cgroup folder of `controller` (cpu, memory) and its ancestors up to the mount, innermost
    first, those that exist: the v1 controller's where it is mounted, else the v2 hierarchy's. A path that does
    not exist under the mount (a container that sees its own cgroup at the mount's root) leaves the mount's
    root."""
    try:
        lines = proc.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        lines = []
    v1 = v2 = None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            v2 = (root, parts[2])
        elif controller in parts[1].split(","):
            names = (parts[1], "cpu,cpuacct", "cpuacct,cpu", "cpu") if controller == "cpu" else (parts[1],)
            mount = next((root / n for n in names if (root / n).is_dir()), None)
            if mount is not None:
                v1 = (mount, parts[2])
    base, rel = v1 or v2 or (root, "/")
    inner = base / rel.strip("/")
    chain = [inner, *inner.parents] if inner.is_relative_to(base) else [base]
    return [d for d in chain if d.is_relative_to(base) and d.is_dir()] or [base]


def cgroup_quota(root: Path = CGROUP_ROOT, proc: Path = PROC_CGROUP) -> CpuQuota | None:
    """The tightest CPU quota of this process's cgroups (v2 or v1, its own and every ancestor's), or None."""
    best: CpuQuota | None = None
    for folder in _cgroup_folders(root, proc):
        cores = _read_quota(folder)
        if cores is not None and (best is None or cores < best.cores):
            usage = next((folder / n for n in ("cpu.stat", "cpuacct.usage") if (folder / n).is_file()), None)
            best = CpuQuota(cores, folder, usage)
    return best


def cgroup_cpu_quota(path: Path | None = None) -> float | None:
    """The cores a cgroup CPU quota allows (QUOTA / PERIOD), or None when none is set: of the cgroup folder
    `path` (its cpu.max or cpu.cfs_quota_us; a file path names its folder), or by default the tightest of this
    process's cgroups (`cgroup_quota`)."""
    if path is None:
        q = cgroup_quota()
        return None if q is None else q.cores
    folder = path.parent if path.name in ("cpu.max", "cpu.cfs_quota_us") else path
    return _read_quota(folder)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text(encoding="ascii").strip()
        return None if text == "max" else int(text)
    except (OSError, ValueError):
        return None


def available_memory(root: Path = CGROUP_ROOT, proc: Path = PROC_CGROUP,
                     meminfo: Path = Path("/proc/meminfo")) -> int | None:
    """Bytes this process may still allocate: the machine's MemAvailable, capped by the room left under the
    tightest memory limit of its cgroups (v2 memory.max - memory.current, v1 memory.limit_in_bytes -
    memory.usage_in_bytes); None where none of them is readable."""
    free = None
    try:
        for line in meminfo.read_text(encoding="ascii").splitlines():
            if line.startswith("MemAvailable:"):
                free = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    for folder in _cgroup_folders(root, proc, "memory"):
        for limit_name, used_name in (("memory.max", "memory.current"), ("memory.limit_in_bytes",
                                                                          "memory.usage_in_bytes")):
            limit, used = _read_int(folder / limit_name), _read_int(folder / used_name)
            if limit is not None and used is not None and limit < (1 << 60):  # v1 writes "no limit" as ~2^63
                room = max(0, limit - used)
                free = room if free is None else min(free, room)
    return free


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


def _cgroup_busy(path: Path | None) -> float | None:
    """CPU seconds of a cgroup: v2 cpu.stat's usage_usec, or v1 cpuacct.usage (nanoseconds)."""
    if path is None:
        return None
    try:
        text = path.read_text(encoding="ascii")
        if path.name == "cpuacct.usage":
            return float(text.strip()) / 1e9
        for line in text.splitlines():
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
    quota = cgroup_quota()
    busy = _cgroup_busy(quota.usage_file) if quota is not None else _busy_on(_affinity())
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


__all__ = ["CpuQuota", "CpuSample", "MachineLoad", "available_memory", "cgroup_cpu_quota", "cgroup_quota",
           "read_cpu_sample", "slots_note", "usable_cores"]
