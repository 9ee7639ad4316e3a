"""The study's job graph (detbench.studies.jobs): dependencies, jobs at once, the time left, a failed job, Ctrl-C."""
from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import detbench.studies.jobs as jobs_mod
from detbench.studies.cpu_load import CpuSample, MachineLoad, cgroup_cpu_quota, usable_cores
from detbench.studies.executor import LocalExecutor
from detbench.studies.jobs import CriticalPathScheduler, Job, check_graph, run_graph
from detbench.utils.cli import UserError
from tests.helpers import ROOT

# A job that stands for a training: it marks itself started, and on SIGINT or SIGTERM writes its "checkpoint"
# and exits 130 (as tools/train.py does); given "resume" it finishes at once, noting that it resumed.
TRAINING = """
import signal, sys, time
from pathlib import Path
d = Path(sys.argv[1])
def stop(signum, _frame):
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the first signal decides; the checkpoint is written once
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    (d / "checkpoint").write_text("step 3")
    (d / "stopped_by").write_text(signal.Signals(signum).name)
    sys.exit(130)
signal.signal(signal.SIGINT, stop)
signal.signal(signal.SIGTERM, stop)
if sys.argv[2:] == ["resume"]:
    (d / "done").write_text("resumed from " + (d / "checkpoint").read_text())
    sys.exit(0)
(d / "started").write_text("1")
for _ in range(600):
    time.sleep(0.05)
(d / "done").write_text("ran through")
"""


def py(code: str, *args) -> list[str]:
    return [sys.executable, "-c", code, *map(str, args)]


def job(jid, cmd, deps=(), kind="train", model="m", out: Path | None = None):
    """A job that is skipped once `out` exists (as a study's stage with its output)."""
    return Job(jid, kind, jid.replace("_", " "), lambda: None if out is not None and out.exists() else cmd,
               deps=tuple(deps), model=model)


def test_the_graph_refuses_unknown_dependencies_and_cycles():
    noop = py("pass")
    with pytest.raises(ValueError, match="depends on unknown job"):
        check_graph([job("a", noop, deps=["b"])])
    with pytest.raises(ValueError, match="cycle"):
        check_graph([job("a", noop, deps=["b"]), job("b", noop, deps=["a"])])
    with pytest.raises(ValueError, match="repeat"):
        check_graph([job("a", noop), job("a", noop)])


def test_time_left_is_the_longest_remaining_path_over_the_workers():
    """Two trainings of 100 s, each followed by its evaluation of 10 s: on two workers the critical path
    (110 s) decides, on one the work (220 s); a model not measured borrows its kind's mean, flagged a guess."""
    jobs = [job("train_a", [], model="a"), job("train_b", [], model="b"),
            job("eval_a", [], deps=["train_a"], kind="eval", model="a"),
            job("eval_b", [], deps=["train_b"], kind="eval", model="b")]
    prog = CriticalPathScheduler(jobs, slots=2)
    assert prog.left_s() == (None, True)  # nothing measured: unknown
    prog.measured = {("train", "a"): [100.0], ("eval", "a"): [10.0], ("train", "b"): [100.0], ("eval", "b"): [10.0]}
    assert prog.left_s() == (pytest.approx(110.0), False)
    assert CriticalPathScheduler(jobs, slots=1).left_s() == (None, True)
    one = CriticalPathScheduler(jobs, slots=1)
    one.measured = prog.measured
    assert one.left_s() == (pytest.approx(220.0), False)
    # a running job counts what it has left; a finished one nothing
    prog.finished.add("train_a")
    prog.running["eval_a"] = 0.0
    left, _ = prog.left_s(now=4.0)
    assert left == pytest.approx(110.0)  # train_b + eval_b; eval_a's 6 s run beside them
    del prog.measured[("train", "b")]
    assert prog.left_s(now=4.0) == (pytest.approx(110.0), True)  # b's training borrows a's: a guess
    # trainings measured but no evaluation yet: each evaluation guessed at EVAL_SHARE of its model's training,
    # a cross-height evaluation at that of an evaluation, a model with no training measured borrowing another's
    share = CriticalPathScheduler.EVAL_SHARE
    chain = [job("train_a", [], model="a"), job("train_b", [], model="b"),
             job("eval_a", [], deps=["train_a"], kind="eval", model="a"),
             job("cross_a", [], deps=["train_a"], kind="cross_eval", model="a"),
             job("eval_b", [], deps=["train_b"], kind="eval", model="b")]
    early = CriticalPathScheduler(chain, slots=1)
    early.measured = {("train", "a"): [200.0]}
    assert early.left_s() == (pytest.approx(200.0 + 200.0 + 3 * share * 200.0), True)  # one worker: the work
    wide = CriticalPathScheduler(chain, slots=4)
    wide.measured = {("train", "a"): [200.0], ("train", "b"): [40.0]}
    assert wide.left_s() == (pytest.approx(200.0 + share * 200.0), True)  # four workers: a's chain, not the work


def test_jobs_run_at_once_after_their_dependencies_and_the_output_goes_to_their_logs(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    # b needs a's output; c and a run together (each waits for the other to have started)
    wait_for = "import sys, time, pathlib\nfor _ in range(400):\n    if pathlib.Path(sys.argv[1]).exists(): break\n" \
               "    time.sleep(0.02)\nelse: sys.exit(5)\n"
    jobs = [job("job_a", py("import pathlib,sys; pathlib.Path(sys.argv[1]).write_text('a'); print('hello from a')\n"
                            + wait_for.replace("sys.argv[1]", "sys.argv[2]"), a, tmp_path / "c"), out=a),
            job("job_b", py("import pathlib,sys; assert pathlib.Path(sys.argv[1]).read_text() == 'a'; "
                            "pathlib.Path(sys.argv[2]).write_text('b')", a, b), deps=["job_a"], out=b),
            job("job_c", py("import pathlib,sys; pathlib.Path(sys.argv[1]).write_text('c')\n"
                            + wait_for.replace("sys.argv[1]", "sys.argv[2]"), tmp_path / "c", a))]
    res = run_graph(jobs, LocalExecutor(2), tmp_path / "logs", poll_s=0.05)
    assert sorted(res.ran) == ["job_a", "job_b", "job_c"] and b.read_text() == "b"
    out = capsys.readouterr().out
    assert "hello from a" not in out  # two at once: output in the logs only
    assert "hello from a" in (tmp_path / "logs" / "job_a.log").read_text()
    assert "running: job a, job c | 0/3 done" in out and "3/3 done" in out
    # again: every output exists, nothing runs
    res = run_graph(jobs[:2], LocalExecutor(2), tmp_path / "logs", poll_s=0.05)
    assert res.ran == [] and res.kept == ["job_a", "job_b"]


def test_one_job_at_a_time_streams_its_output_and_keeps_its_log(tmp_path, capfd):
    run_graph([job("only", py("print('line one'); print('line two')"))], LocalExecutor(1), tmp_path / "logs",
              poll_s=0.05)
    out = capfd.readouterr().out
    assert "line one\nline two" in out and "line two" in (tmp_path / "logs" / "only.log").read_text()


def test_a_failed_job_stops_the_study_and_the_running_training_checkpoints_then_it_resumes(tmp_path, capsys):
    """The failed job's log is named and its last lines shown; the training running beside it gets SIGTERM and
    writes its checkpoint; the job waiting for a slot never starts. The same graph again (the error fixed)
    keeps what finished, resumes the training and runs the rest."""
    run, fixed = tmp_path / "train", tmp_path / "fixed"
    run.mkdir()
    fail = ("import pathlib, sys, time\nif pathlib.Path(sys.argv[2]).exists(): sys.exit(0)\n"
            "for _ in range(500):\n    if pathlib.Path(sys.argv[1]).exists(): break\n    time.sleep(0.02)\n"
            "print('\\n'.join(f'log line {i}' for i in range(30))); print('ValueError: the config is wrong')\n"
            "sys.exit(3)")

    def train_prepare():
        if (run / "done").exists():
            return None
        return py(TRAINING, run, *(["resume"] if (run / "checkpoint").exists() else []))

    def graph():
        return [Job("train_m", "train", "train m", train_prepare, model="m"),
                job("eval_bad", py(fail, run / "started", fixed), kind="eval"),
                job("waiting", py("import pathlib,sys; pathlib.Path(sys.argv[1]).write_text('w')",
                                  tmp_path / "waiting"), kind="combine", out=tmp_path / "waiting"),
                job("after_bad", py("pass"), deps=["eval_bad"], kind="combine")]

    with pytest.raises(SystemExit) as e:
        run_graph(graph(), LocalExecutor(2), tmp_path / "logs", poll_s=0.05)
    log = tmp_path / "logs" / "eval_bad.log"
    assert f"eval bad failed (exit 3); its log: {log}" in str(e.value.code)
    assert "run the same command again" in str(e.value.code)
    out = capsys.readouterr().out
    assert f"FAILED: eval bad (exit 3); its log: {log}" in out
    assert "ValueError: the config is wrong" in out and "log line 29" in out and "log line 5\n" not in out
    assert "stopping train m" in out
    assert (run / "checkpoint").read_text() == "step 3" and not (run / "done").exists()
    assert (run / "stopped_by").read_text() == "SIGTERM"
    assert not (tmp_path / "waiting").exists()

    fixed.write_text("1")
    res = run_graph(graph(), LocalExecutor(2), tmp_path / "logs", poll_s=0.05)
    assert (run / "done").read_text() == "resumed from step 3"
    assert sorted(res.ran) == ["after_bad", "eval_bad", "train_m", "waiting"]


@pytest.mark.parametrize("status, error", [(2, UserError), (1, SystemExit)])
def test_a_failed_job_keeps_the_users_error_apart_from_a_bug(tmp_path, status, error):
    with pytest.raises(error, match="train m failed"):
        run_graph([job("train_m", py(f"import sys; sys.exit({status})"))], LocalExecutor(1), tmp_path, poll_s=0.05)


class RecordingExecutor(LocalExecutor):
    """A LocalExecutor that keeps every ended job's exit status."""

    def __init__(self, slots: int):
        super().__init__(slots)
        self.ended: dict[str, int] = {}

    def wait(self, timeout: float) -> list[tuple[str, int]]:
        ended = super().wait(timeout)
        self.ended.update(ended)
        return ended


def test_a_job_still_starting_under_nohup_ends_on_the_stop_at_once(tmp_path, monkeypatch):
    """A job started by a study run with nohup or `&` inherits SIGINT ignored; before the training loop installs
    its handler it sees only SIGTERM, which the stop sends: it ends by that signal, not by the kill that follows
    STOP_GRACE_S (set long here, so a missed signal would show as the kill's status, or the test's timeout)."""
    monkeypatch.setattr(jobs_mod, "STOP_GRACE_S", 60.0)
    starting = ("import pathlib, signal, sys, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                "pathlib.Path(sys.argv[1]).write_text('1')\ntime.sleep(120)\npathlib.Path(sys.argv[2]).write_text('ran')")
    fail = ("import pathlib, sys, time\nfor _ in range(500):\n    if pathlib.Path(sys.argv[1]).exists(): break\n"
            "    time.sleep(0.02)\nsys.exit(3)")
    executor = RecordingExecutor(2)
    with pytest.raises(SystemExit):
        run_graph([job("train_m", py(starting, tmp_path / "started", tmp_path / "ran")),
                   job("eval_bad", py(fail, tmp_path / "started"), kind="eval")], executor, tmp_path / "logs",
                  poll_s=0.05)
    assert executor.ended["train_m"] == -signal.SIGTERM and not (tmp_path / "ran").exists()


def as_in_a_terminal() -> None:
    """The driver's SIGINT as a terminal's foreground process has it: a suite started with nohup or `&` from a
    script passes SIGINT on ignored, and Ctrl-C would then be tested against a process that cannot see it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


DRIVER = """
import sys
from pathlib import Path
from detbench.studies.executor import LocalExecutor
from detbench.studies.jobs import Job, run_graph
d = Path(sys.argv[1])
training = sys.argv[2]
run_graph([Job("train_m", "train", "train m", lambda: [sys.executable, "-c", training, str(d)], model="m")],
          LocalExecutor(2), d / "logs", poll_s=0.05)
"""


def start_driver(script: str, d: Path, *, own_group: bool = False) -> subprocess.Popen:
    """`script` run with the fake training in `d`, SIGINT as in a terminal (`own_group`: in a process group of
    its own, as a terminal's foreground job); returns once the training started."""
    proc = subprocess.Popen([sys.executable, "-c", script, str(d), TRAINING], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT,
                            preexec_fn=as_in_a_terminal, start_new_session=own_group)
    for _ in range(600):
        if (d / "started").exists():
            break
        time.sleep(0.05)
    return proc


def test_ctrl_c_stops_the_jobs_after_their_checkpoint_and_says_how_to_resume(tmp_path):
    proc = start_driver(DRIVER, tmp_path)
    os.kill(proc.pid, signal.SIGINT)  # the driver only: it passes the stop on to its jobs as SIGTERM
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode != 0 and "KeyboardInterrupt" in out
    assert (tmp_path / "checkpoint").read_text() == "step 3" and not (tmp_path / "done").exists()
    assert "interrupted: stopping train m" in out and "run the same command again to resume" in out
    assert (tmp_path / "stopped_by").read_text() == "SIGTERM"  # what the driver sends its jobs


def test_ctrl_c_in_a_terminal_reaches_driver_and_training_and_the_checkpoint_is_written_once(tmp_path):
    """A terminal's Ctrl-C goes to the whole foreground group: the training gets SIGINT itself, then the
    driver's SIGTERM; it checkpoints on the first and the second does not stop it short."""
    proc = start_driver(DRIVER, tmp_path, own_group=True)
    os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode != 0 and "interrupted: stopping train m" in out
    assert (tmp_path / "checkpoint").read_text() == "step 3" and not (tmp_path / "done").exists()
    assert (tmp_path / "stopped_by").read_text() in ("SIGINT", "SIGTERM")


TOOL_DRIVER = """
import sys
from pathlib import Path
from detbench.studies.executor import LocalExecutor
from detbench.studies.jobs import Job, run_graph
from detbench.utils.cli import run_main
d = Path(sys.argv[1])
training = sys.argv[2]

def main(_argv):
    run_graph([Job("train_m", "train", "train m", lambda: [sys.executable, "-c", training, str(d)], model="m")],
              LocalExecutor(2), d / "logs", poll_s=0.05)
    return 0

sys.exit(run_main(main))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_ctrl_c_or_sigterm_ends_a_tool_with_one_line_and_status_130(tmp_path, sig):
    """As tools/study.py ends on Ctrl-C or `kill PID`: the running training writes its checkpoint, the study says
    how to resume, then one 'interrupted' line, no traceback."""
    proc = start_driver(TOOL_DRIVER, tmp_path)
    os.kill(proc.pid, sig)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out
    assert "run the same command again to resume" in out and out.rstrip().endswith("interrupted")
    assert (tmp_path / "checkpoint").read_text() == "step 3"


def test_a_cross_height_evaluation_borrows_the_time_of_an_evaluation():
    jobs = [job("train_a", [], model="a"), job("eval_a", [], deps=["train_a"], kind="eval", model="a"),
            job("cross_a", [], deps=["train_a"], kind="cross_eval", model="a")]
    prog = CriticalPathScheduler(jobs, slots=1)
    prog.measured = {("train", "a"): [100.0], ("eval", "a"): [10.0]}
    assert prog.left_s() == (pytest.approx(120.0), True)


def test_the_longest_remaining_path_starts_first(tmp_path):
    # one worker: both trainings before either evaluation (a training's chain, train + eval, is longer than
    # an evaluation's), though the list puts each evaluation right after its training
    noop = py("pass")
    jobs = [job("train_a", noop), job("eval_a", noop, deps=["train_a"], kind="eval"),
            job("train_b", noop), job("eval_b", noop, deps=["train_b"], kind="eval")]
    res = run_graph(jobs, LocalExecutor(1), tmp_path / "logs", poll_s=0.02)
    assert res.ran == ["train_a", "train_b", "eval_a", "eval_b"]
    # measured durations take over from the priors: an evaluation measured longer than a training and its
    # evaluation together goes first; equal paths keep the list order
    prog = CriticalPathScheduler(jobs, 1)
    prog.measured = {("train", "m"): [10.0], ("eval", "m"): [100.0]}
    order = [j.id for j in prog.by_path([jobs[1], jobs[2], jobs[3]])]
    assert order == ["train_b", "eval_a", "eval_b"]  # 10 + 100 > 100; eval_a before eval_b (list order)
    prog.measured = {("train", "m"): [10.0], ("eval", "m"): [10.0]}
    lone = Job("eval_c", "eval", "evaluate c", lambda: None, model="m")
    assert [j.id for j in prog.by_path([lone, jobs[2], jobs[3]])] == ["train_b", "eval_c", "eval_b"]


def test_the_default_is_the_cores_this_process_may_use(tmp_path):
    """One job per core of the affinity mask, capped by a cgroup CPU quota (whole cores, at least one)."""
    assert usable_cores(quota=None, affinity={0, 1, 2, 3}) == 4
    assert usable_cores(quota=2.5, affinity={0, 1, 2, 3}) == 2 and usable_cores(quota=0.5, affinity={0, 1}) == 1
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text("150000 100000\n")
    assert cgroup_cpu_quota(cpu_max) == 1.5
    cpu_max.write_text("max 100000\n")
    assert cgroup_cpu_quota(cpu_max) is None and cgroup_cpu_quota(tmp_path / "none") is None
    assert 1 <= usable_cores() <= (os.cpu_count() or 1)


def test_the_other_load_is_the_busy_time_less_this_studys_own_measured_again_later():
    """Busy CPU seconds per wall second on the usable cores, less this process tree's: the first estimate over
    two samples a window apart (one wait, here not slept), later ones once min_interval_s has passed."""
    samples = iter([CpuSample(0.0, 100.0, 10.0), CpuSample(0.5, 101.0, 10.5),  # 2 cores busy, 1 of them ours
                    CpuSample(1.0, 102.0, 11.0),  # too soon: the estimate stands
                    CpuSample(3.0, 103.5, 13.0)])  # 2.5 s after the estimate: 1 core busy, all of it ours
    waits = []
    load = MachineLoad(lambda: next(samples), window_s=0.5, min_interval_s=2.0, sleep=waits.append)
    assert load.other_cores() == pytest.approx(1.0) and waits == [0.5]
    assert load.other_cores() == pytest.approx(1.0)
    assert load.other_cores() == pytest.approx(0.0) and waits == [0.5]
    assert MachineLoad(lambda: None, sleep=waits.append).other_cores() is None  # no /proc: no estimate


class ScriptedLoad:
    """The machine's other load as a test sets it, in cores."""

    def __init__(self, cores: float):
        self.cores = cores

    def other_cores(self) -> float:
        return self.cores


def _intervals(d: Path) -> list[tuple[float, float]]:
    return sorted(tuple(map(float, p.read_text().split())) for p in d.glob("*.t"))


def test_other_load_holds_slots_back_until_it_leaves_and_the_line_says_why(tmp_path):
    """Two slots on a machine whose other load keeps one core busy: one job at a time, and the progress line
    says why; once the load is gone, two at once again."""
    timed = ("import sys, time, pathlib\nt0 = time.time()\ntime.sleep(0.3)\n"
             "pathlib.Path(sys.argv[1]).write_text(f'{t0} {time.time()}')")
    load = ScriptedLoad(1.0)
    out = io.StringIO()
    jobs = [job(f"train_{k}", py(timed, tmp_path / "busy" / f"{k}.t")) for k in "abc"]
    (tmp_path / "busy").mkdir()
    run_graph(jobs, LocalExecutor(2, stream=False, load=load), tmp_path / "logs", poll_s=0.02,
              scheduler=CriticalPathScheduler(jobs, 2, stream=out))
    spans = _intervals(tmp_path / "busy")
    assert len(spans) == 3 and all(b[0] >= a[1] for a, b in zip(spans, spans[1:])), spans  # never two at once
    assert "1 of 2 slots: the machine's other load uses 1 core" in out.getvalue()
    load.cores = 0.0
    (tmp_path / "free").mkdir()
    both = [job(f"train_{k}", py(timed, tmp_path / "free" / f"{k}.t")) for k in "ab"]
    out = io.StringIO()
    run_graph(both, LocalExecutor(2, stream=False, load=load), tmp_path / "logs", poll_s=0.02,
              scheduler=CriticalPathScheduler(both, 2, stream=out))
    (a0, a1), (b0, b1) = _intervals(tmp_path / "free")
    assert b0 < a1 and "slots:" not in out.getvalue()  # they ran together
