"""Running one stage of a study as its own process: the study's stages and the trade sweep's tasks.

A stage in its own process owns its peak memory and thread count, and a failure or a stop at a
deadline ends only that stage. `run_command` runs one command, its output either streamed
through to the terminal (the study) or appended to a log file (the trade sweep), optionally
stopped at a deadline; it reports the exit status, the wall time and the child's CPU time.
"""
from __future__ import annotations

import os
import resource
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

STOP_GRACE_S = 120.0  # seconds a stopped child has to finish (a training run writes its checkpoint) before a kill


@dataclass(frozen=True)
class CommandResult:
    """returncode: the child's exit status; timed_out: stopped at the deadline; wall_s: wall seconds;
    cpu_s: the child's user + system seconds, its own children included."""

    returncode: int
    timed_out: bool
    wall_s: float
    cpu_s: float


def _stop(proc: subprocess.Popen, sig: int) -> None:
    """Send `sig`, then kill when the child has not ended within STOP_GRACE_S."""
    proc.send_signal(sig)
    try:
        proc.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def run_command(cmd: list[str], *, cwd: str | os.PathLike | None = None, log: str | os.PathLike | None = None,
                deadline: float | None = None, stop_signal: int = signal.SIGTERM) -> CommandResult:
    """Run `cmd` in `cwd` and wait for it.

    log: None streams the child's output through to this process's; a path appends "$ <cmd>" and
    then the child's output (stderr with stdout) to that file, creating its folder. deadline: a
    `time.perf_counter()` time at which the child gets `stop_signal` (and a kill STOP_GRACE_S later).
    An exception here (Ctrl-C) terminates a child still running, then re-raises.
    """
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    timed_out = False
    fh = None
    if log is not None:
        log = Path(log)
        log.parent.mkdir(parents=True, exist_ok=True)
        fh = open(log, "a", encoding="utf-8")
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
    try:
        out = dict(stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL) if fh is not None else {}
        proc = subprocess.Popen(cmd, cwd=cwd, **out)
        try:
            left = None if deadline is None else max(0.0, deadline - time.perf_counter())
            try:
                proc.wait(timeout=left)
            except subprocess.TimeoutExpired:
                timed_out = True
                _stop(proc, stop_signal)
        except BaseException:
            if proc.poll() is None:
                _stop(proc, signal.SIGTERM)
            raise
    finally:
        if fh is not None:
            fh.close()
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    return CommandResult(proc.returncode, timed_out, time.perf_counter() - t0, cpu)


def log_tail(log: str | os.PathLike, n: int = 3000) -> str:
    """The last `n` characters of a log file ("" when it cannot be read)."""
    try:
        return Path(log).read_text(encoding="utf-8", errors="replace")[-n:]
    except OSError:
        return ""


__all__ = ["CommandResult", "STOP_GRACE_S", "log_tail", "run_command"]
