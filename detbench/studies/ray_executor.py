"""The study's job graph on Ray: each job a Ray task that asks for one CPU (or one GPU) and runs the job's command.

detbench.studies.jobs.run_graph drives the graph as with the local executor; this executor only
submits a job once its dependencies have finished, as a Ray remote task requesting num_cpus=1 (and
num_gpus=1 for a job on the GPU; Ray sets CUDA_VISIBLE_DEVICES for it), and Ray picks the worker
machine. The task runs the job's command as a subprocess there, in the same checkout path, writing into the study's
folder: that folder (and the dataset) must be one all workers share (NFS or similar). The task
function is pickled by value and imports only the standard library, so a worker needs Ray and
the project's Python environment, not this module. Why Ray: docs/cluster.md.

A stopped study (a failed job, Ctrl-C) cancels the running tasks: Ray raises KeyboardInterrupt in
each, which sends SIGTERM to its command (a training writes its checkpoint) and waits for it.
"""
from __future__ import annotations

import os
import time

from detbench.studies.executor import JOB_ENV, STOP_GRACE_S
from detbench.studies.jobs import Job
from detbench.utils.cli import UserError

# the editable install of the checkout (a plain `pip install .[cluster]` would replace it with a copy, after which a
# detector added to models/ is not what runs); quoted for zsh, which reads [cluster] as a pattern
INSTALL_HINT = "pip install -e '.[cluster]'"


def import_ray():
    """The ray module, or UserError naming the install command."""
    try:
        import ray
    except ImportError:
        raise UserError(f"--executor ray needs Ray, which is not installed: {INSTALL_HINT} (or pip install "
                        f"'ray>=2.9'), or use the local executor (leave --executor out)") from None
    return ray


def _job_task(grace_s: float):
    """The function each Ray task runs (defined here so cloudpickle sends it by value)."""

    def run_job(cmd: list[str], cwd: str, env: dict, log: str) -> int:
        import os as _os
        import signal as _signal
        import subprocess as _subprocess

        _os.makedirs(_os.path.dirname(log), exist_ok=True)
        with open(log, "w", encoding="utf-8") as fh:
            fh.write(f"$ {' '.join(cmd)}\n")
            fh.flush()
            proc = _subprocess.Popen(cmd, cwd=cwd, env={**_os.environ, **env}, stdout=fh,
                                     stderr=_subprocess.STDOUT, stdin=_subprocess.DEVNULL)
            try:
                return proc.wait()
            except BaseException:  # ray.cancel: KeyboardInterrupt in this task
                proc.send_signal(_signal.SIGTERM)
                try:
                    proc.wait(timeout=grace_s)
                except _subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                raise

    return run_job


class RayExecutor:
    """Runs jobs as Ray tasks (see the module's docstring).

    address: None starts a local Ray instance (or uses the one this process already started);
    "auto" or host:port connects to a running cluster. slots: at most this many jobs at once
    (None: the cluster's CPUs, or GPUs with gpu=True)."""

    def __init__(self, *, address: str | None, cwd: str | os.PathLike, gpu: bool = False, slots: int | None = None):
        self.ray = ray = import_ray()
        self.started = False
        if not ray.is_initialized():
            kw = {"log_to_driver": False}
            if address is None:
                kw["include_dashboard"] = False
            try:
                ray.init(address=address, **kw)
            except (ConnectionError, ValueError, RuntimeError) as e:
                raise UserError(f"--address {address}: cannot connect to a Ray cluster ({e}); start one with "
                                f"`ray start --head`, or leave --address out for a local Ray instance") from None
            self.started = True
        res = ray.cluster_resources()
        have = int(res.get("GPU" if gpu else "CPU", 0))
        if have < 1:
            raise UserError(f"the Ray cluster has no {'GPU' if gpu else 'CPU'} to run jobs on "
                            f"(its resources: {dict(res)})")
        self.slots = min(have, slots) if slots else have
        self.gpu = gpu
        self.cwd = str(cwd)
        self.env = dict(JOB_ENV)
        if os.environ.get("PYTHONPATH"):  # the checkout the driver imports, at the same path on every worker
            self.env["PYTHONPATH"] = os.environ["PYTHONPATH"]
        self.task = ray.remote(max_retries=0, num_cpus=1)(_job_task(STOP_GRACE_S))
        self.refs: dict[str, object] = {}  # job id -> ObjectRef

    def start(self, job: Job, cmd: list[str]) -> None:
        assert job.log is not None
        task = self.task.options(num_gpus=1) if job.gpu else self.task  # a GPU job: one GPU (and one CPU)
        self.refs[job.id] = task.remote(cmd, self.cwd, self.env, str(job.log))

    def wait(self, timeout: float) -> list[tuple[str, int]]:
        if not self.refs:
            return []
        ids = {r: i for i, r in self.refs.items()}
        ready, _ = self.ray.wait(list(ids), num_returns=1, timeout=timeout)
        if ready:  # everything else that is ready too
            ready, _ = self.ray.wait(list(ids), num_returns=len(ids), timeout=0)
        out = []
        for ref in ready:
            jid = ids[ref]
            del self.refs[jid]
            try:
                rc = int(self.ray.get(ref))
            except self.ray.exceptions.TaskCancelledError:
                rc = 130
            except self.ray.exceptions.RayError as e:
                print(f"ray: job {jid}: {e}", flush=True)
                rc = 1
            out.append((jid, rc))
        return out

    def interrupt(self) -> None:
        for ref in self.refs.values():
            self.ray.cancel(ref, force=False)

    def kill(self) -> None:
        for ref in self.refs.values():
            self.ray.cancel(ref, force=True)
        time.sleep(0.5)

    @property
    def running(self) -> list[str]:
        return list(self.refs)

    def close(self) -> None:
        if self.started:
            self.ray.shutdown()
            self.started = False


__all__ = ["INSTALL_HINT", "RayExecutor", "import_ray"]
