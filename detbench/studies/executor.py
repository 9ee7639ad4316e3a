"""Running the studies' jobs as child processes of this machine: the study's graph and the trade sweep's tasks.

A job in its own process owns its peak memory and thread count, and a failure or a stop ends
only that job. `LocalExecutor` runs up to `slots` jobs at once (detbench.studies.jobs.run_graph
drives it for a study; detbench.studies.ray_executor is the same interface on Ray), each job's
output into its log, or with `stream` also through to this process's terminal. Each job gets
`env` on top of this process's environment: for a study `JOB_ENV` (one torch and one numba thread,
so results do not depend on the number of jobs at once), for the trade sweep nothing (its points
measure the thread counts they set); and always the driver's pid (`detbench.utils.cli.PARENT_ENV`),
so a job ends with its driver however the driver ends (a kill -9 included: the kernel sends the job
SIGTERM, and a training saves first). A job's log from an earlier run is kept as `<id>.log.prev`,
never truncated. An ended job's exit status comes with its wall time and its CPU time, its own
children included (`usage`).

`run_to_end` runs one job alone and waits for it: at a deadline it gets a stop signal (SIGTERM: a
training writes its checkpoint and exits) and a kill STOP_GRACE_S later; Ctrl-C stops it the same
way and is raised again. The trade sweep runs its tasks with it, one at a time within its budget.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from detbench.studies.cpu_load import MachineLoad, slots_note
from detbench.utils.cli import PARENT_ENV

STOP_GRACE_S = 120.0  # seconds a stopped job has to finish (a training writes its checkpoint) before a kill
# Every study job's environment on top of the driver's: one torch (OpenMP) and one numba thread, unbuffered
# output (the log is current while the job runs). The same for every number of jobs at once.
JOB_ENV = {"OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


@dataclass(frozen=True)
class CommandResult:
    """returncode: the job's exit status; timed_out: stopped at the deadline; wall_s: wall seconds;
    cpu_s: the job's user + system seconds, its own children included."""

    returncode: int
    timed_out: bool
    wall_s: float
    cpu_s: float


@dataclass
class _Running:
    proc: subprocess.Popen
    device: str | None
    pump: threading.Thread | None
    t0: float


class LocalExecutor:
    """Runs jobs as child processes of this machine, `slots` at once (see the module's docstring).

    devices: with --device cuda, the GPU indices; each job gets one of them as CUDA_VISIBLE_DEVICES.
    stream: each job's output through to this terminal too (default: with one slot). append_logs: a job's
    log grows over reruns (the trade sweep's) instead of starting anew (the study's). load: the machine's
    other load (detbench.studies.cpu_load.MachineLoad), measured again whenever a slot is free: the slots
    a core of which it keeps busy stay empty (`room`); None: every slot runs (--jobs N)."""

    def __init__(self, slots: int, *, cwd: str | os.PathLike | None = None, devices: list[str] | None = None,
                 stream: bool | None = None, env: dict | None = None, append_logs: bool = False,
                 load: MachineLoad | None = None):
        self.slots = max(1, int(slots))
        self.cwd = cwd
        self.devices = list(devices) if devices else None
        if self.devices:
            self.slots = min(self.slots, len(self.devices))
        self.stream = (self.slots == 1) if stream is None else stream
        self.env = dict(JOB_ENV if env is None else env)
        self.append_logs = append_logs
        self.load = load
        self.procs: dict[str, _Running] = {}
        self.usage: dict[str, tuple[float, float]] = {}  # job id -> (wall s, CPU s) of the jobs that ended

    def start(self, job, cmd: list[str]) -> None:
        assert job.log is not None
        job.log.parent.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, **self.env, PARENT_ENV: str(os.getpid())}  # the job ends with this driver
        device = None
        if self.devices:
            used = {r.device for r in self.procs.values()}
            device = next(d for d in self.devices if d not in used)
            env["CUDA_VISIBLE_DEVICES"] = device
        if not self.append_logs and job.log.is_file() and job.log.stat().st_size:
            # the log of an earlier run of the job is kept beside, never truncated: a job of a driver that was
            # killed may still be writing to it
            os.replace(job.log, job.log.with_name(job.log.name + ".prev"))
        fh = open(job.log, "a" if self.append_logs else "w", encoding="utf-8")
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        t0 = time.perf_counter()
        if self.stream:
            print(f"$ {' '.join(cmd)}", flush=True)
            proc = subprocess.Popen(cmd, cwd=self.cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            pump = threading.Thread(target=_tee, args=(proc.stdout, fh), daemon=True)
            pump.start()
        else:
            proc = subprocess.Popen(cmd, cwd=self.cwd, env=env, stdout=fh, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL)
            fh.close()
            pump = None
        self.procs[job.id] = _Running(proc, device, pump, t0)

    def room(self) -> tuple[int, str | None]:
        """(how many jobs may run now, why fewer than the slots or None): the slots less the cores the machine's
        other load keeps busy (rounded to whole cores), at least one."""
        other = None if self.load is None else self.load.other_cores()
        if other is None:
            return self.slots, None
        allowed = max(1, min(self.slots, self.slots - int(round(other))))
        return allowed, slots_note(allowed, self.slots, other)

    def _reap(self, jid: str) -> int | None:
        """The job's exit status once it ended (its wall and CPU time then in `usage`), else None."""
        run = self.procs[jid]
        try:
            pid, status, ru = os.wait4(run.proc.pid, os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere: its status without its CPU time
            rc = run.proc.poll()
            if rc is not None:
                self.usage[jid] = (time.perf_counter() - run.t0, 0.0)
            return rc
        if pid == 0:
            return None
        run.proc.returncode = os.waitstatus_to_exitcode(status)
        self.usage[jid] = (time.perf_counter() - run.t0, ru.ru_utime + ru.ru_stime)
        return run.proc.returncode

    def wait(self, timeout: float) -> list[tuple[str, int]]:
        """(job id, exit status) of the jobs that ended, waiting up to `timeout` s for the first."""
        deadline = time.monotonic() + timeout
        while True:
            ended = [(i, rc) for i in list(self.procs) if (rc := self._reap(i)) is not None]
            if ended or not self.procs or time.monotonic() >= deadline:
                for i, _ in ended:
                    pump = self.procs.pop(i).pump
                    if pump is not None:
                        pump.join()
                return [(i, int(rc)) for i, rc in ended]
            time.sleep(0.05)

    def _signal(self, sig: int) -> None:
        for run in self.procs.values():
            if run.proc.returncode is None:  # not reaped yet: the pid is still the job's
                try:
                    os.kill(run.proc.pid, sig)
                except ProcessLookupError:
                    pass

    def interrupt(self, sig: int = signal.SIGTERM) -> None:
        """`sig` to every running job (SIGTERM: a training writes its checkpoint and exits; a job still starting
        ends)."""
        self._signal(sig)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)

    @property
    def running(self) -> list[str]:
        return list(self.procs)

    def close(self) -> None:
        pass


def _tee(src, fh) -> None:
    """Copy a child's output to this process's stdout and to its log, as it comes."""
    out = getattr(sys.stdout, "buffer", None)
    try:
        for chunk in iter(lambda: src.read1(65536), b""):
            if out is not None:
                out.write(chunk)
                out.flush()
            else:
                sys.stdout.write(chunk.decode("utf-8", "replace"))
                sys.stdout.flush()
            fh.write(chunk.decode("utf-8", "replace"))
            fh.flush()
    finally:
        fh.close()


def _stop(executor: LocalExecutor, sig: int) -> dict[str, int]:
    """`sig` to the running jobs, a kill STOP_GRACE_S later; {job id: exit status} once they ended."""
    executor.interrupt(sig)
    kill_at = time.monotonic() + STOP_GRACE_S
    ended: dict[str, int] = {}
    while executor.running:
        if time.monotonic() >= kill_at:
            executor.kill()
        ended.update(executor.wait(0.2))
    return ended


def run_to_end(executor: LocalExecutor, job, cmd: list[str], *, deadline: float | None = None,
               stop_signal: int = signal.SIGTERM, poll_s: float = 0.2) -> CommandResult:
    """Run `job` (its `log` set) alone on `executor` and wait for it. deadline: a `time.perf_counter()` time at
    which it gets `stop_signal` (and a kill STOP_GRACE_S later). An exception here (Ctrl-C) stops it with
    SIGTERM the same way, then propagates."""
    executor.start(job, cmd)
    timed_out = False
    try:
        while True:
            left = None if deadline is None else deadline - time.perf_counter()
            ended = executor.wait(poll_s if left is None else max(0.0, min(poll_s, left)))
            if ended:
                rc = ended[0][1]
                break
            if left is not None and left <= 0:
                timed_out = True
                rc = _stop(executor, stop_signal)[job.id]
                break
    except BaseException:
        if executor.running:
            _stop(executor, signal.SIGTERM)
        raise
    wall_s, cpu_s = executor.usage.pop(job.id)
    return CommandResult(rc, timed_out, wall_s, cpu_s)


def log_tail(log: str | os.PathLike, n: int = 3000) -> str:
    """The last `n` characters of a log file ("" when it cannot be read)."""
    try:
        return Path(log).read_text(encoding="utf-8", errors="replace")[-n:]
    except OSError:
        return ""


__all__ = ["CommandResult", "JOB_ENV", "LocalExecutor", "STOP_GRACE_S", "log_tail", "run_to_end"]
