"""The study as a graph of jobs: the jobs, the scheduler that orders and times them, and the driver that runs them.

A `Job` is one stage of a study (the ability study, a training, an evaluation, the combined
report) run as one command in its own process: its id (also its log's name, OUT/logs/<id>.log),
its kind and model (for the time left), the ids of the jobs it needs finished first, the run
folders it writes, and its resource request (one CPU core, or one GPU). A job decides what it
runs only when its dependencies have finished (`prepare`: the command, or None when its output
is current and it is skipped, as a study resumes); `finish` records what it was computed from
once it succeeded. Both run in the driver process, one at a time.

`CriticalPathScheduler` decides which ready job starts first (the one with the longest remaining
path through the graph, by the durations measured so far), estimates the time left and writes one
progress line per event. `run_graph` is the driver both executors share: it starts the ready jobs
in the scheduler's order while the executor has room (a free slot; on this machine also a core the
machine's other load leaves free, which the progress line says when it holds a job back), and
on a failed job prints its log's path and last lines, starts nothing new and sends SIGTERM to the
running jobs so a training writes its checkpoint and exits (train_summary.json "interrupted");
Ctrl-C does the same, and so does SIGTERM to the driver (`kill PID`: a study started with nohup or
`&` from a script ignores Ctrl-C's SIGINT, as the shell starts it). The jobs get SIGTERM, not
SIGINT, because they inherit that ignored SIGINT: a job still starting, before the training loop
installs its handler, would not see SIGINT and would run on until the kill after STOP_GRACE_S;
SIGTERM ends it at once (it has not trained yet) and, once the loop runs, makes it save a
checkpoint. The study resumes afterwards with the same command.

detbench.studies.executor's `LocalExecutor` runs the jobs as child processes of this machine, each
with one torch and one numba thread whatever the number at once, so results do not depend on it,
one per core this process may use by default (`default_jobs`; detbench.studies.cpu_load);
detbench.studies.ray_executor runs the same graph on Ray.
"""
from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from detbench.studies.cpu_load import usable_cores
from detbench.studies.executor import STOP_GRACE_S
from detbench.utils.cli import EXIT_USER_ERROR, UserError, sigterm_as_ctrl_c

LOGS_DIR = "logs"  # OUT/logs/<job id>.log
TAIL_LINES = 20  # lines of a failed job's log printed with its path

KINDS = ("ability", "train", "eval", "cross_eval", "combine")  # the data and the splits' counts come before the graph


@dataclass
class Job:
    """One stage of a study run as one command (see the module's docstring)."""

    id: str
    kind: str  # one of KINDS
    what: str  # what the progress line calls it: "train second 0.5 m"
    prepare: Callable[[], list[str] | None] | None = None  # the command, or None: its output is current (skipped)
    deps: tuple[str, ...] = ()
    model: str | None = None
    finish: Callable[[], None] | None = None  # after it succeeded: record its inputs
    outputs: tuple[Path, ...] = ()  # the folders it writes
    gpu: bool = False  # asks for one GPU instead of one CPU core
    log: Path | None = None  # set by run_graph: OUT/logs/<id>.log

    @property
    def resources(self) -> dict[str, int]:
        return {"gpu": 1} if self.gpu else {"cpu": 1}


def check_graph(jobs: list[Job]) -> None:
    """ValueError when a job id repeats, a dependency is unknown, or the dependencies form a cycle."""
    ids = [j.id for j in jobs]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"job ids repeat: {', '.join(dup)}")
    known = set(ids)
    for j in jobs:
        if j.kind not in KINDS:
            raise ValueError(f"job {j.id}: unknown kind {j.kind!r} (one of {', '.join(KINDS)})")
        missing = [d for d in j.deps if d not in known]
        if missing:
            raise ValueError(f"job {j.id} depends on unknown job(s) {', '.join(missing)}")
    deps = {j.id: set(j.deps) for j in jobs}
    done: set[str] = set()
    while len(done) < len(jobs):
        ready = [i for i in deps if i not in done and deps[i] <= done]
        if not ready:
            raise ValueError(f"the jobs' dependencies form a cycle among {', '.join(sorted(set(deps) - done))}")
        done.update(ready)


def cuda_devices() -> list[str]:
    """The GPUs jobs may use: CUDA_VISIBLE_DEVICES when set, else every device torch sees (as indices)."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [d.strip() for d in visible.split(",") if d.strip() and d.strip() != "-1"]
    import torch

    return [str(i) for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []


def default_jobs(device: str) -> int:
    """How many jobs run at once at most by default: one per GPU with --device cuda, else one per CPU core this
    process may use (`cpu_load.usable_cores`; the local executor runs fewer while other processes keep some of
    them busy)."""
    if device.startswith("cuda"):
        return max(1, len(cuda_devices()))
    return usable_cores()


def tail(path: Path, n: int = TAIL_LINES) -> list[str]:
    """The last `n` lines of a log file ([] when it cannot be read); progress bars' carriage returns
    keep only their last state."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return []
    return [ln.rsplit("\r", 1)[-1] for ln in text.splitlines() if ln.strip()][-n:]


def _minutes(s: float) -> str:
    return "under a minute" if s < 60 else f"~{s / 60:.0f} min"


class CriticalPathScheduler:
    """The order in which ready jobs start, the time left, and one line per event (what started or finished,
    the jobs running, why fewer than the slots run, how many are done, the time left).

    Ready jobs start longest remaining path first (`by_path`: critical-path list scheduling).

    The time left is the longest remaining path through the graph over the workers: the larger of
    the critical path (each job's estimated duration, the running ones less their elapsed time, along
    the longest chain of dependencies still to run) and the remaining work spread over `slots`
    workers. A job's duration is the mean measured duration of finished jobs of the same kind and
    model; a kind not measured for that model borrows the mean of that kind (a guess, said so until
    every model has run each kind once), a cross-height evaluation that of an evaluation, and an
    evaluation before any has finished `EVAL_SHARE` of its model's training (a guess); with
    neither measured (e.g. a resumed study whose trainings are all done) the time left is unknown
    until the first training or evaluation finishes. Short kinds (data,
    ability, combine) count only once measured."""

    def __init__(self, jobs: list[Job], slots: int, *, stream=None):
        self.jobs = {j.id: j for j in jobs}
        self.order = [j.id for j in jobs]
        self.slots = max(1, slots)
        self.measured: dict[tuple[str, str | None], list[float]] = {}
        self.finished: set[str] = set()
        self.running: dict[str, float] = {}  # id -> start time
        self.t0 = time.perf_counter()
        self.stream = stream if stream is not None else sys.stdout
        self.note: str | None = None  # why fewer jobs than slots run now ("1 of 2 slots: ...")
        self.said_note: str | None = None

    def estimate(self, job: Job) -> tuple[float | None, bool]:
        """(seconds, a guess?) for one job; None: no measurement to go by."""
        return self._estimate(job.kind, job.model)

    def _estimate(self, kind: str, model: str | None) -> tuple[float | None, bool]:
        own = self.measured.get((kind, model))
        if own:
            return sum(own) / len(own), False
        same = [t for (k, _), ts in self.measured.items() if k == kind for t in ts]
        if same:
            return sum(same) / len(same), True
        if kind == "cross_eval":  # an evaluation at another height costs about what one at its own does
            return self._estimate("eval", model)[0], True
        if kind == "eval":  # no evaluation measured yet: a share of the model's training time
            train, _ = self._estimate("train", model)
            return (None if train is None else self.EVAL_SHARE * train), True
        return (None, True) if kind == "train" else (0.0, False)

    def left_s(self, now: float | None = None) -> tuple[float | None, bool]:
        """(seconds left, a guess?): see the class docstring."""
        now = time.perf_counter() if now is None else now
        rest = [i for i in self.order if i not in self.finished]
        rem: dict[str, float] = {}
        guess = False
        for i in rest:
            est, g = self.estimate(self.jobs[i])
            if est is None:
                return None, True
            guess |= g
            rem[i] = max(0.0, est - (now - self.running[i])) if i in self.running else est
        succ: dict[str, list[str]] = {i: [] for i in rest}
        for i in rest:
            for d in self.jobs[i].deps:
                if d in succ:
                    succ[d].append(i)
        path: dict[str, float] = {}
        for i in reversed(self._topo(rest)):
            path[i] = rem[i] + max((path[s] for s in succ[i]), default=0.0)
        critical = max(path.values(), default=0.0)
        return max(critical, sum(rem.values()) / self.slots), guess

    # A job kind's duration before any is measured: what orders the first jobs (a training's chain is
    # longer than an evaluation's); seconds, rough orders of magnitude, used only for that order.
    PRIOR_S = {"train": 300.0, "eval": 60.0, "cross_eval": 60.0, "ability": 90.0}
    # An evaluation's duration as a share of its model's training before any evaluation has finished (a
    # guess, said so in the line; docs/results.md has measured ones); longest-path-first scheduling runs
    # every training before the first evaluation.
    EVAL_SHARE = 0.25

    def by_path(self, pending: list[Job]) -> list[Job]:
        """`pending` with the longest remaining path first (the job's estimated duration plus its longest
        chain of pending successors; list order among equals): critical-path list scheduling, so a
        training that others wait on starts before an evaluation that nothing waits on."""
        by_id = {j.id: j for j in pending}
        succ: dict[str, list[str]] = {i: [] for i in by_id}
        for j in pending:
            for d in j.deps:
                if d in succ:
                    succ[d].append(j.id)
        path: dict[str, float] = {}

        def length(i: str) -> float:
            if i not in path:
                est, _ = self.estimate(by_id[i])
                own = est if est is not None else self.PRIOR_S.get(by_id[i].kind, 1.0)
                path[i] = own + max((length(s) for s in succ[i]), default=0.0)
            return path[i]

        return sorted(pending, key=lambda j: -length(j.id))

    def _topo(self, ids: list[str]) -> list[str]:
        left, out, placed = list(ids), [], set(self.finished)
        while left:
            ready = [i for i in left if all(d in placed for d in self.jobs[i].deps)]
            out += ready
            placed.update(ready)
            left = [i for i in left if i not in placed]
            if not ready:  # cannot happen in a checked graph
                out += left
                break
        return out

    def line(self, event: str) -> str:
        now = time.perf_counter()
        left, guess = self.left_s(now)
        running = ", ".join(self.jobs[i].what for i in self.running) or "nothing"
        if left is None:
            eta = "time left: known once a training or an evaluation has finished"
        else:
            eta = f"{_minutes(left)} left" + (" (a guess: some model has not run this kind of job yet)"
                                              if guess else "")
        note = f"{self.note} | " if self.note else ""
        return (f"=== {event} | running: {running} | {note}{len(self.finished)}/{len(self.order)} done | "
                f"{(now - self.t0) / 60:.1f} min elapsed, {eta}")

    def say(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def start(self, job: Job) -> None:
        self.running[job.id] = time.perf_counter()
        self.say(self.line(f"start {job.what}"))

    def skip(self, job: Job) -> None:
        self.finished.add(job.id)

    def done(self, job: Job) -> float:
        seconds = time.perf_counter() - self.running.pop(job.id)
        self.finished.add(job.id)
        self.measured.setdefault((job.kind, job.model), []).append(seconds)
        self.say(self.line(f"done {job.what} in {seconds:.0f} s"))
        return seconds

    def stopped(self, job: Job) -> None:
        self.running.pop(job.id, None)


@dataclass
class GraphResult:
    """ran: ids of the jobs that ran and succeeded; kept: ids skipped as current; seconds per job that ran."""

    ran: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)


def run_graph(jobs: list[Job], executor, logs: str | os.PathLike, *, scheduler: CriticalPathScheduler | None = None,
              poll_s: float = 1.0) -> GraphResult:
    """Run `jobs` (the longest remaining path first among those ready) on `executor`; each job's output in
    `logs`/<id>.log. Raises UserError (a job that ended on the user's error, exit 2) or SystemExit
    naming the failed job's log after the running jobs stopped; KeyboardInterrupt after Ctrl-C (or SIGTERM)
    stopped them; any other error of the driver stops them too before it propagates. See the module's docstring."""
    with sigterm_as_ctrl_c():  # `kill PID` of a driver run outside a tool's run_main, too
        return _run_graph(jobs, executor, logs, scheduler=scheduler, poll_s=poll_s)


def _run_graph(jobs: list[Job], executor, logs: str | os.PathLike, *, scheduler: CriticalPathScheduler | None,
               poll_s: float) -> GraphResult:
    check_graph(jobs)
    for j in jobs:
        j.log = Path(logs) / f"{j.id}.log"
    progress = scheduler or CriticalPathScheduler(jobs, executor.slots)
    by_id = {j.id: j for j in jobs}
    pending = list(jobs)
    done: set[str] = set()
    result = GraphResult()
    failed: tuple[Job, int] | None = None
    kill_at = float("inf")  # after a failure: when the jobs still running are killed
    try:
        while True:
            if failed is None:
                _start_ready(pending, done, executor, progress, result)
            if not executor.running:
                break
            if time.monotonic() >= kill_at:
                executor.kill()
            for jid, rc in executor.wait(poll_s):
                job = by_id[jid]
                if rc == 0 and failed is None:
                    if job.finish is not None:
                        job.finish()
                    result.seconds[jid] = progress.done(job)
                    result.ran.append(jid)
                    done.add(jid)
                elif rc == 0:  # it finished while the others were stopping: its output stands
                    if job.finish is not None:
                        job.finish()
                    progress.stopped(job)
                    progress.say(f"=== {job.what} finished while the study stopped; kept")
                elif failed is None:
                    progress.stopped(job)
                    failed = (job, rc)
                    _report_failure(job, rc, progress, [by_id[i].what for i in executor.running])
                    executor.interrupt()
                    kill_at = time.monotonic() + STOP_GRACE_S
                else:
                    progress.stopped(job)
                    progress.say(f"=== {job.what} stopped (exit {rc}); its log: {job.log}")
    except BaseException as e:  # Ctrl-C, SIGTERM, or an error of the driver itself: no job outlives it
        if executor.running:
            why = "interrupted" if isinstance(e, KeyboardInterrupt) else f"the study driver failed ({e!r})"
            progress.say(f"\n=== {why}: stopping {', '.join(by_id[i].what for i in executor.running)} "
                         f"(a training writes its checkpoint first)")
            _stop_all(executor, progress, by_id)
        executor.close()
        progress.say("=== the study stopped; run the same command again to resume: finished jobs are kept")
        raise
    executor.close()
    if failed is not None:
        job, rc = failed
        msg = (f"study: {job.what} failed (exit {rc}); its log: {job.log}. Fix the error and run the same command "
               f"again: finished jobs are kept and skipped, a stopped training resumes from its checkpoint")
        raise UserError(msg) if rc == EXIT_USER_ERROR else SystemExit(msg)
    if pending:  # cannot happen in a checked graph
        raise RuntimeError(f"jobs never became ready: {', '.join(j.id for j in pending)}")
    return result


def _room(executor, progress: CriticalPathScheduler) -> int:
    """How many jobs the executor has room for now (`room()` where it has one, else its slots); the scheduler
    notes why fewer than the slots."""
    allowed, progress.note = executor.room() if hasattr(executor, "room") else (executor.slots, None)
    return allowed


def _start_ready(pending: list[Job], done: set[str], executor, progress: CriticalPathScheduler,
                 result: GraphResult) -> None:
    """Start (or skip, when current) the pending jobs whose dependencies are done, the longest remaining path
    first (`CriticalPathScheduler.by_path`), while the executor has room."""
    progress.note = None
    room = None  # asked once a ready job waits for a free slot
    again = True
    while again and len(executor.running) < executor.slots:
        again = False
        for job in progress.by_path(pending):
            if not all(d in done for d in job.deps):
                continue
            room = _room(executor, progress) if room is None else room
            if len(executor.running) >= room:
                if progress.note and progress.note != progress.said_note:  # say once why it waits
                    progress.say(progress.line(f"{job.what} waits"))
                    progress.said_note = progress.note
                return
            pending.remove(job)
            cmd = job.prepare()
            if cmd is None:
                progress.skip(job)
                result.kept.append(job.id)
                done.add(job.id)
                again = True  # its dependants may be ready now
                continue
            progress.start(job)
            executor.start(job, cmd)


def _report_failure(job: Job, rc: int, progress: CriticalPathScheduler, others: list[str]) -> None:
    lines = tail(job.log) if job.log is not None else []
    progress.say(f"\n=== FAILED: {job.what} (exit {rc}); its log: {job.log}")
    if lines:
        progress.say(f"--- last {len(lines)} lines of {job.log}:")
        for ln in lines:
            progress.say(f"    {ln}")
        progress.say("---")
    if others:
        progress.say(f"=== starting no new job; stopping {', '.join(others)} (a training writes its checkpoint "
                     f"first)")


def _stop_all(executor, progress: CriticalPathScheduler, by_id: dict[str, Job]) -> None:
    """SIGTERM to the running jobs, then wait for them (a kill after STOP_GRACE_S); a second Ctrl-C kills at once."""
    executor.interrupt()
    deadline = time.monotonic() + STOP_GRACE_S
    try:
        while executor.running:
            if time.monotonic() >= deadline:
                executor.kill()
            for jid, rc in executor.wait(0.5):
                job = by_id[jid]
                if rc == 0 and job.finish is not None:
                    job.finish()
                progress.stopped(job)
    except KeyboardInterrupt:
        executor.kill()
        while executor.running:
            executor.wait(0.5)


def job_counts(jobs: Iterable[Job]) -> dict[str, int]:
    """How many jobs of each kind (for the study's plan line)."""
    counts: dict[str, int] = {}
    for j in jobs:
        counts[j.kind] = counts.get(j.kind, 0) + 1
    return counts


__all__ = ["CriticalPathScheduler", "GraphResult", "Job", "KINDS", "LOGS_DIR", "TAIL_LINES", "check_graph",
           "cuda_devices", "default_jobs", "job_counts", "run_graph", "tail"]
