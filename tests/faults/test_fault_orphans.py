"""A study whose driver died: `--fresh` never deletes a run folder a surviving training still writes."""
import subprocess
import sys
import time

import pytest

from tests.faults.faultkit import ROOT, snapshot

# holds the folder lock of argv[1] as a training run does, creates argv[2], then sleeps
HOLD_RUN_LOCK = ("import sys, time\nfrom detbench.utils.folder_locks import acquire_folder_lock\n"
                 "lock = acquire_folder_lock(sys.argv[1], 'a training run')\nopen(sys.argv[2], 'w').close()\n"
                 "time.sleep(120)\n")


def hold_lock(folder, flag):
    proc = subprocess.Popen([sys.executable, "-c", HOLD_RUN_LOCK, str(folder), str(flag)], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not flag.exists():
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() - t0 < 60
        time.sleep(0.05)
    return proc


def test_fresh_refuses_a_study_whose_training_still_runs(fault_data, tmp_path, tool):
    """A training of the study still holds its run folder (its study driver was killed): `study --fresh` is
    refused in one line naming the run folder and the training's pid, and deletes nothing; once the training
    has ended, --fresh empties the study."""
    from detbench.train.run_layout import STUDY_FOLDER

    study = tmp_path / "study"
    run = study / "second_h1.8"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "epoch_001.pt").write_bytes(b"x")
    (study / "ability").mkdir()
    (study / "study.json").write_text("{}")
    proc = hold_lock(run, tmp_path / "held")
    try:
        before = snapshot(study)
        code, err = tool("study", "--preset", "smoke", "--models", "second", "--heights", "1.8", "--data",
                         fault_data, "--out", study, "--no-progress", "--fresh")
        assert code == 2, err
        assert f"{run}: in use by a training run pid {proc.pid} on host " in err and "Traceback" not in err
        assert "--fresh would delete it under that process: stop it (or wait for it to end)" in err
        after = snapshot(study)
        after.pop(".detbench-owner.json", None)  # the study's claim marks its folder as a study's
        assert after == before
    finally:
        proc.kill()
        proc.communicate()
    from detbench.utils.folder_locks import clear_folder

    removed = clear_folder(study, STUDY_FOLDER, flag="--fresh")
    assert sorted(p.rsplit("/", 1)[-1] for p in removed) == ["ability", "second_h1.8", "study.json"]
    assert [p.name for p in study.iterdir()] == [".detbench-owner.json"]


# a job as a study starts one: a tool's main under run_main that writes its pid into argv[1] and sleeps
JOB = ("import os, sys, time\nfrom detbench.utils.cli import run_main\n"
       "def main(argv):\n    open(sys.argv[1] + '.tmp', 'w').write(str(os.getpid()))\n"
       "    os.replace(sys.argv[1] + '.tmp', sys.argv[1])\n    time.sleep(120)\n    return 0\n"
       "sys.exit(run_main(main, []))\n")
# a study driver: runs JOB (argv[1]: its pid file) through a LocalExecutor and waits
DRIVER = ("import sys\nfrom pathlib import Path\nfrom detbench.studies.executor import LocalExecutor, run_to_end\n"
          "from detbench.studies.jobs import Job\n"
          "job = Job('train_x', 'train', 'train x', log=Path(sys.argv[2]))\n"
          "run_to_end(LocalExecutor(1, stream=False), job, [sys.executable, '-c', sys.argv[3], sys.argv[1]])\n")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_a_job_ends_with_its_killed_driver(tmp_path):
    """kill -9 of a study driver: its job gets the parent-death signal and ends (as on Ctrl-C), instead of
    running on under pid 1."""
    import os
    import signal

    pid_file, log = tmp_path / "job.pid", tmp_path / "job.log"
    driver = subprocess.Popen([sys.executable, "-c", DRIVER, str(pid_file), str(log), JOB], cwd=ROOT,
                              stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not pid_file.exists():
        assert driver.poll() is None, driver.communicate()[1][-3000:]
        assert time.monotonic() - t0 < 60, "the job never started"
        time.sleep(0.05)
    job = int(pid_file.read_text())
    try:
        os.kill(driver.pid, signal.SIGKILL)
        driver.communicate()
        t0 = time.monotonic()
        while _alive(job) and time.monotonic() - t0 < 20:
            time.sleep(0.1)
        assert not _alive(job), "the job outlived its driver"
        assert "interrupted" in log.read_text()
    finally:
        if _alive(job):
            os.kill(job, signal.SIGKILL)


def test_a_driver_error_stops_the_running_jobs(tmp_path):
    """An error of the driver itself (here: recording a finished job fails) stops the jobs still running
    before it propagates, not only Ctrl-C does."""
    from detbench.studies.executor import LocalExecutor
    from detbench.studies.jobs import Job, run_graph

    pid_file = tmp_path / "slow.pid"

    def broken():
        raise OSError(28, "No space left on device")

    import os
    import signal

    wait_for_slow = f"import os, time\nwhile not os.path.exists({str(pid_file)!r}): time.sleep(0.05)"
    jobs = [Job("train_slow", "train", "train slow", prepare=lambda: [sys.executable, "-c", JOB, str(pid_file)]),
            Job("train_fast", "train", "train fast", prepare=lambda: [sys.executable, "-c", wait_for_slow],
                finish=broken)]
    with pytest.raises(OSError, match="No space left"):
        run_graph(jobs, LocalExecutor(2, cwd=ROOT, stream=False), tmp_path / "logs", poll_s=0.05)
    slow = int(pid_file.read_text())
    try:
        assert not _alive(slow), "the running job outlived the driver's error"
    finally:
        if _alive(slow):
            os.kill(slow, signal.SIGKILL)


def test_a_rerun_keeps_the_log_of_the_job_before(tmp_path):
    """A job's log from an earlier run is kept beside the new one (`.log.prev`), never truncated: a job of a
    killed driver may still be writing to it."""
    from detbench.studies.executor import LocalExecutor, run_to_end
    from detbench.studies.jobs import Job

    job = Job("train_x", "train", "train x", log=tmp_path / "logs" / "train_x.log")
    for word in ("first", "second"):
        run_to_end(LocalExecutor(1, stream=False), job, [sys.executable, "-c", f"print('{word} run')"])
    assert "second run" in job.log.read_text() and "first run" not in job.log.read_text()
    assert "first run" in (tmp_path / "logs" / "train_x.log.prev").read_text()


def test_a_rerun_refuses_a_study_whose_training_still_runs(fault_data, tmp_path, tool):
    """A training of an earlier run of the study still holds its run folder: the rerun is refused in one line
    naming the folder and the pid, before any job starts (no job's log is touched)."""
    from detbench.train.run_layout import RUN_FOLDER, STUDY_FOLDER
    from detbench.utils.folder_ownership import write_owner

    study = tmp_path / "study"
    run = study / "second_h1.8"
    (run / "checkpoints").mkdir(parents=True)
    write_owner(study, STUDY_FOLDER)
    write_owner(run, RUN_FOLDER)
    (study / "logs").mkdir()
    (study / "logs" / "train_second_h1.8.log").write_text("the running training's log\n")
    proc = hold_lock(run, tmp_path / "held")
    try:
        code, err = tool("study", "--preset", "smoke", "--models", "second", "--heights", "1.8", "--data",
                         fault_data, "--out", study, "--no-progress")
    finally:
        proc.kill()
        proc.communicate()
    assert code == 2, err[-3000:]
    assert f"{run}: in use by a training run pid {proc.pid} on host " in err
    assert "a job of an earlier run of this study that has not ended yet" in err and "Traceback" not in err
    assert sorted(p.name for p in (study / "logs").iterdir()) == ["train_second_h1.8.log"]


def test_the_core_count_honours_a_nested_cgroup_quota(tmp_path):
    """A 2-CPU quota set on the process's own cgroup (v2, below the root) or on its v1 cpu controller caps the
    cores a study counts, whatever the node has."""
    from detbench.studies.cpu_load import cgroup_quota

    v2 = tmp_path / "v2"
    (v2 / "kubepods" / "pod1" / "ctr").mkdir(parents=True)
    (v2 / "cpu.max").write_text("max 100000\n")
    (v2 / "kubepods" / "pod1" / "cpu.max").write_text("200000 100000\n")
    (v2 / "kubepods" / "pod1" / "cpu.stat").write_text("usage_usec 5000000\n")
    proc = tmp_path / "cgroup_v2"
    proc.write_text("0::/kubepods/pod1/ctr\n")
    q = cgroup_quota(v2, proc)
    assert q is not None and q.cores == 2.0 and q.usage_file == v2 / "kubepods" / "pod1" / "cpu.stat"
    v1 = tmp_path / "v1"
    (v1 / "cpu,cpuacct").mkdir(parents=True)
    (v1 / "cpu,cpuacct" / "cpu.cfs_quota_us").write_text("150000\n")
    (v1 / "cpu,cpuacct" / "cpu.cfs_period_us").write_text("100000\n")
    proc.write_text("4:memory:/x\n3:cpu,cpuacct:/docker/abc\n0::/\n")  # the container sees its cgroup at the root
    assert cgroup_quota(v1, proc).cores == 1.5


def test_more_workers_than_cores_are_refused(fault_data, tmp_path, tool):
    """--workers above the cores this process may use is refused in one line before the run starts."""
    from detbench.studies.cpu_load import usable_cores

    n = usable_cores() + 1
    code, err = tool("train", "--model", "second", "--height", 1.8, "--preset", "smoke", "--data", fault_data,
                     "--out", tmp_path / "run", "--workers", n, "--no-progress")
    assert code == 2, err[-3000:]
    assert f"error: train.workers {n}: this process may use {n - 1} CPU core(s)" in err
    assert not (tmp_path / "run").exists()
