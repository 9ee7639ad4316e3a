"""The trade sweep: train and measure every point within a wall-time budget, resuming, and write the report.

Tasks (the preset's points, the inference-only knobs, the trained knobs, the learning curves,
the joint points; cheapest first within a tier) are planned by estimated cost and re-planned
after each task with the costs measured so far (detbench.studies.tradeoff). A training run is
`tools/train.py` in its own process, built as the study builds it (detbench.studies.commands); a
measurement is `python -m detbench.studies.tradeoff_worker`. The study's local executor
(detbench.studies.executor) runs each task alone, its log in OUT/logs/, stopped at the budget's
end (a training keeps its checkpoint). A finished point or run in OUT is reused, an interrupted
run continues. OUT holds tradeoff.json, tradeoff.md, tradeoff.png,
learning_curve.png, points/, runs/, curve/ and logs/.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from detbench.config import CONFIG_DIR, ConfigError
from detbench.data.layout import read_info
from detbench.eval.run import data_source
from detbench.data.regions import RANGE_NAMES
from detbench.studies.commands import TrainSpec, train_command, train_finished, train_resumes, worker_command
from detbench.studies.executor import CommandResult, LocalExecutor, log_tail, run_to_end
from detbench.studies.jobs import Job
from detbench.studies.registry import ModelRegistry
from detbench.studies.tradeoff import (
    PRIOR_SECONDS, CostModel, Task, mark_pareto, plan_within_budget, plot_learning_curves, plot_tradeoff,
    train_seconds_at_step, tradeoff_markdown, world_label,
)
from detbench.studies.tradeoff_points import KNOBS, Point, sweep_points
from detbench.train.run_config import load_run_config
from detbench.utils.cli import UserError
from detbench.utils.atomic import atomic_write_json, atomic_write_text, read_json


@dataclass
class TradeoffOptions:
    """The sweep's settings (tools/tradeoff.py's arguments; minutes, seconds and frame counts)."""

    preset: str = "smoke"
    models: list[str] | None = None  # None: every registered model
    knobs: tuple[str, ...] | list[str] = KNOBS
    budget: float | None = None  # minutes of wall time; None: every point runs
    height: float = 1.8
    data: str | None = None  # dataset root; None: the preset's simulated dataset
    device: str = "auto"
    frames: int = 20
    warmup: int = 3
    eval_frames: int = 0
    curve_scale: float = 2.0
    curve_points: int = 8
    load_start: float | None = None  # the load average when the sweep started (reported)


@dataclass
class Sweep:
    """What one invocation works on: paths, settings, the points, training runs and curve runs."""

    opts: TradeoffOptions
    repo: Path  # the checkout holding tools/train.py: the children's working folder
    registry: str  # the detector registry's module, imported by the workers
    out: Path
    root: Path
    device: str
    preset_cfgs: dict  # model -> run config of the preset
    points: list[Point]
    n_train: int
    costs: CostModel
    t0: float
    deadline: float | None
    executor: LocalExecutor | None = None  # runs each task alone (None: a new one on the first task)
    done: set = field(default_factory=set)
    failed: dict = field(default_factory=dict)  # task id -> error text


def _run_dir(sw: Sweep, model: str, train_id: str) -> Path:
    return sw.out / "runs" / model / train_id


def _point_file(sw: Sweep, p: Point) -> Path:
    return sw.out / "points" / p.model / f"{p.id}.json"


def _curve_epochs(sw: Sweep, model: str) -> int:
    return max(1, int(round(sw.preset_cfgs[model]["train"]["epochs"] * sw.opts.curve_scale)))


def _curve_train_id(sw: Sweep, model: str) -> str:
    """The learning-curve run's folder: the preset's own run at --curve-scale 1, else curve-<epochs>ep."""
    epochs = _curve_epochs(sw, model)
    return "preset" if epochs == int(sw.preset_cfgs[model]["train"]["epochs"]) else f"curve-{epochs}ep"


def _curve_dir(sw: Sweep, model: str) -> Path:
    """Where the learning-curve run's checkpoint evaluations go (one JSON per checkpoint)."""
    return sw.out / "curve" / model / _curve_train_id(sw, model)


def _checkpoint_every(sw: Sweep, model: str) -> int:
    """Steps between the learning-curve run's extra checkpoints: about --curve-points in all."""
    bs = int(sw.preset_cfgs[model]["train"]["batch_size"])
    total = _curve_epochs(sw, model) * math.ceil(sw.n_train / bs)
    return max(1, math.ceil(total / max(1, sw.opts.curve_points)))


def _curve_checkpoints(sw: Sweep, model: str) -> int:
    bs = int(sw.preset_cfgs[model]["train"]["batch_size"])
    per = math.ceil(sw.n_train / bs)
    every = _checkpoint_every(sw, model)
    total = _curve_epochs(sw, model) * per
    return len(set(range(every, total + 1, every)) | {per * (e + 1) for e in range(_curve_epochs(sw, model))})


def _train_overrides(sw: Sweep, model: str, train_id: str, point_over: dict) -> list[str]:
    sets = {"train.tensorboard": False, "train.bev_image": False, "train.keep_checkpoints": 1, **point_over}
    if "curve" in sw.opts.knobs and train_id == _curve_train_id(sw, model):
        sets.update({"train.keep_checkpoints": 0, "train.checkpoint_every_steps": _checkpoint_every(sw, model)})
    if train_id.startswith("curve-"):
        sets["train.epochs"] = _curve_epochs(sw, model)
    return [f"{k}={json.dumps(v)}" for k, v in sets.items()]


def _point_key(sw: Sweep, p: Point) -> dict:
    """What a point's stored result must match to be reused on a rerun."""
    return {"preset": sw.opts.preset, "height": sw.opts.height, "data": str(sw.root), "device": sw.device,
            "train": p.train, "infer": p.infer, "frames": sw.opts.frames, "warmup": sw.opts.warmup,
            "eval_frames": sw.opts.eval_frames}


def _point_done(sw: Sweep, p: Point) -> bool:
    f = _point_file(sw, p)
    return f.is_file() and read_json(f).get("spec") == _point_key(sw, p)


def _curve_done(sw: Sweep, model: str) -> bool:
    run = _run_dir(sw, model, _curve_train_id(sw, model))
    if not train_finished(run):
        return False
    ckpts = sorted((run / "checkpoints").glob("epoch_*.pt"))
    return bool(ckpts) and all((_curve_dir(sw, model) / f"{c.stem}.json").is_file() for c in ckpts)


def _run(sw: Sweep, task: str, kind: str, cmd: list[str], log: Path, stop_signal: int) -> CommandResult:
    """Run one task alone on the sweep's executor, stopped with `stop_signal` at the budget's end."""
    if sw.executor is None:
        # one task at a time, each with the thread counts it sets itself (no study job's one-thread setting)
        sw.executor = LocalExecutor(1, cwd=sw.repo, stream=False, env={}, append_logs=True)
    return run_to_end(sw.executor, Job(task, kind, task, log=log), cmd, deadline=sw.deadline, stop_signal=stop_signal)


def do_train(sw: Sweep, model: str, train_id: str, over: dict, factor: float) -> None:
    run = _run_dir(sw, model, train_id)
    resume = train_resumes(run)
    cmd = train_command(TrainSpec(model=model, height=sw.opts.height, preset=sw.opts.preset, data=sw.root,
                                  device=sw.device, out=run,
                                  overrides=tuple(_train_overrides(sw, model, train_id, over))))
    if cmd is None:  # finished since the plan was made
        return
    res = _run(sw, f"train {model} {train_id}", "train", cmd, sw.out / "logs" / f"train_{model}_{train_id}.log",
               signal.SIGTERM)
    rec_path = run / "tradeoff_train.json"
    rec = read_json(rec_path) if rec_path.is_file() else {"overrides": over, "wall_s": 0.0, "cpu_s": 0.0,
                                                           "invocations": 0}
    rec.update(wall_s=rec["wall_s"] + res.wall_s, cpu_s=rec["cpu_s"] + res.cpu_s,
               invocations=rec["invocations"] + 1)
    if run.is_dir():  # a refused start leaves no run folder, and only tools/train.py makes one
        atomic_write_json(rec_path, rec)
    if res.timed_out:
        raise TimeoutError(f"stopped at the budget's end after {res.wall_s:.0f} s (its checkpoint is kept; "
                           f"run again with a larger --budget to continue it)")
    if res.returncode != 0 or not train_finished(run):
        raise RuntimeError(f"training failed (exit {res.returncode}); log {sw.out / 'logs'}:\n"
                           + log_tail(sw.out / "logs" / f"train_{model}_{train_id}.log"))
    if not resume:  # a resumed run's time is partial: not a cost sample
        sw.costs.observe("train", model, factor, res.wall_s)


def _ckpt_of(sw: Sweep, model: str, train_id: str) -> str:
    return read_json(_run_dir(sw, model, train_id) / "train_summary.json")["checkpoint"]


def _worker(sw: Sweep, spec: dict, log: Path) -> CommandResult:
    # a measurement keeps nothing worth a grace period: killed at the budget's end
    res = _run(sw, log.stem, "measure", worker_command({**spec, "registry": sw.registry}), log, signal.SIGKILL)
    if res.timed_out:
        raise TimeoutError(f"stopped at the budget's end after {res.wall_s:.0f} s")
    if res.returncode != 0:
        raise RuntimeError(f"exit {res.returncode}; log {log}:\n{log_tail(log)}")
    return res


def do_measure(sw: Sweep, p: Point) -> None:
    spec = {"mode": "point", "key": _point_key(sw, p), "ckpt": _ckpt_of(sw, p.model, p.train_id), "infer": p.infer,
            "device": sw.device, "data": str(sw.root), "height": sw.opts.height, "frames": sw.opts.frames,
            "warmup": sw.opts.warmup, "eval_frames": sw.opts.eval_frames, "out": str(_point_file(sw, p))}
    res = _worker(sw, spec, sw.out / "logs" / f"measure_{p.model}_{p.id}.log")
    sw.costs.observe("measure", p.model, p.measure_factor, res.wall_s)


def do_curve(sw: Sweep, model: str) -> None:
    run = _run_dir(sw, model, _curve_train_id(sw, model))
    n = len(list((run / "checkpoints").glob("epoch_*.pt")))
    spec = {"mode": "curve", "run": str(run), "device": sw.device, "data": str(sw.root), "height": sw.opts.height,
            "eval_frames": sw.opts.eval_frames, "out": str(_curve_dir(sw, model))}
    todo = sum(not (_curve_dir(sw, model) / f"{c.stem}.json").is_file()
               for c in (run / "checkpoints").glob("epoch_*.pt"))
    res = _worker(sw, spec, sw.out / "logs" / f"curve_{model}.log")
    if todo == n and n:
        sw.costs.observe("curve_eval", model, n, res.wall_s)


def build_tasks(sw: Sweep) -> tuple[list[Task], dict]:
    """Tasks in priority order with their current estimates, and id -> (kind, args) to run them."""
    action: dict = {}
    trains: dict = {}  # (model, train_id) -> Task
    tiers: dict[int, list[tuple[float, list[Task]]]] = {t: [] for t in range(5)}

    def train_task(model, train_id, over, factor) -> str:
        tid = f"train {model} {train_id}"
        if (model, train_id) not in trains:
            done = train_finished(_run_dir(sw, model, train_id))
            trains[(model, train_id)] = Task(tid, 0.0 if done else sw.costs.estimate("train", model, factor))
            action[tid] = ("train", (model, train_id, over, factor))
            if done:
                sw.done.add(tid)
        return tid

    for p in sw.points:
        t = train_task(p.model, p.train_id, p.train, p.train_factor)
        pid = f"measure {p.model} {p.name}"
        done = _point_done(sw, p)
        task = Task(pid, 0.0 if done else sw.costs.estimate("measure", p.model, p.measure_factor), (t,))
        action[pid] = ("measure", (p,))
        if done:
            sw.done.add(pid)
        cost = task.cost_s + trains[(p.model, p.train_id)].cost_s
        tiers[p.tier].append((cost, [task]))
    if "curve" in sw.opts.knobs:
        for model in sw.preset_cfgs:
            train_id = _curve_train_id(sw, model)
            t = train_task(model, train_id, {}, sw.opts.curve_scale)
            cid = f"curve {model}"
            done = _curve_done(sw, model)
            task = Task(cid, 0.0 if done else sw.costs.estimate("curve_eval", model, _curve_checkpoints(sw, model)),
                        (t,))
            action[cid] = ("curve", (model,))
            if done:
                sw.done.add(cid)
            tiers[3].append((task.cost_s + trains[(model, train_id)].cost_s, [task]))
    ordered = [task for tier in range(5)
               for _, group in (tiers[tier] if tier == 0 else sorted(tiers[tier], key=lambda x: x[0]))
               for task in group]
    # the preset's training first within tier 0 comes through the measure tasks' needs
    return list(trains.values()) + ordered, action


def plan(sw: Sweep):
    tasks, action = build_tasks(sw)
    trains = [t for t in tasks if t.id.startswith("train ")]
    targets = [t for t in tasks if not t.id.startswith("train ")]
    # a training task is planned only as a need of a measurement or curve; failed work is left out
    live = [t for t in targets if t.id not in sw.failed and not any(n in sw.failed for n in t.needs)]
    pending = [t for t in live if t.id not in sw.done]
    left = None
    if sw.deadline is not None:
        left = max(0.0, sw.deadline - time.perf_counter() - _reserve(sw))
    p = plan_within_budget([*trains, *targets], left, goals=[t.id for t in pending]) if pending else None
    return p, {t.id: t for t in tasks}, action


def _reserve(sw: Sweep) -> float:
    """Seconds kept back for writing the report at the end of a budgeted sweep."""
    return min(30.0, 0.05 * sw.opts.budget * 60) if sw.opts.budget else 0.0


def run_sweep(sw: Sweep, progress: bool) -> list[dict]:
    """Run planned tasks one at a time, re-planning after each; returns the skipped tasks."""
    from tqdm import tqdm

    bar = tqdm(total=0, desc="tradeoff", unit="task", disable=not progress, dynamic_ncols=True)
    try:
        while True:
            p, by_id, action = plan(sw)
            if p is None or not p.run:
                break
            bar.total = bar.n + sum(1 for t in p.run if t not in sw.done)
            bar.refresh()
            tid = next((t for t in p.run if t not in sw.done), None)
            if tid is None:
                break
            est = by_id[tid].cost_s
            kind, a = action[tid]
            t0 = time.perf_counter()
            try:
                if kind == "train":
                    do_train(sw, *a)
                elif kind == "measure":
                    do_measure(sw, *a)
                else:
                    do_curve(sw, *a)
                sw.done.add(tid)
                status = "done"
            except TimeoutError as e:
                sw.failed[tid] = str(e)
                status = "stopped at the deadline"
                tqdm.write(f"{tid}: {e}")
                _write_outputs(sw, [], final=False)
                break
            except RuntimeError as e:
                sw.failed[tid] = str(e)
                status = "FAILED"
                tqdm.write(f"{tid}: failed: {str(e).splitlines()[0]} (log in {sw.out / 'logs'})")
            bar.update(1)
            left = "" if sw.deadline is None else f"; {max(0, sw.deadline - time.perf_counter()) / 60:.1f} min left"
            tqdm.write(f"{tid}: {status} in {time.perf_counter() - t0:.0f} s (estimated {est:.0f} s){left}")
            _write_outputs(sw, [], final=False)
    finally:
        bar.close()
    p, by_id, _ = plan(sw)
    skipped = []
    if p is not None:
        for tid in p.skipped:
            skipped.append({"task": tid, "estimated_s": round(by_id[tid].cost_s + sum(
                by_id[n].cost_s for n in by_id[tid].needs), 1), "reason": p.reasons.get(tid, "")})
        for tid in p.run:  # planned but never reached (the loop stopped at the deadline)
            if tid not in sw.done and not tid.startswith("train "):
                skipped.append({"task": tid, "estimated_s": round(by_id[tid].cost_s, 1),
                                "reason": "the sweep stopped at the budget's end"})
    for tid, t in by_id.items():  # work that needs a failed task
        if tid not in sw.failed and any(n in sw.failed for n in t.needs) and tid not in sw.done:
            skipped.append({"task": tid, "estimated_s": round(t.cost_s, 1),
                            "reason": f"needs {next(n for n in t.needs if n in sw.failed)}, which failed or stopped"})
    return skipped


def collect_points(sw: Sweep) -> list[dict]:
    out = []
    for p in sw.points:
        if not _point_done(sw, p):
            continue
        r = read_json(_point_file(sw, p))
        r.pop("spec", None)
        acc = r.get("accuracy")
        if acc is not None and p.region_range:  # ranges beyond the shrunk grid are not modelled
            inside = RANGE_NAMES[:RANGE_NAMES.index(p.region_range) + 1]
            acc = {k: (v if k in inside else None) for k, v in acc.items()}
        elif acc is None:
            acc = {k: None for k in RANGE_NAMES}
        out.append({"model": p.model, "point": p.name, "knob": p.knob, "value": p.value,
                    "trained": "at this point" if p.train else "preset model", "device": sw.device,
                    "train_overrides": p.train, "inference": p.infer, "region_range": p.region_range,
                    **{k: v for k, v in r.items() if k != "accuracy"}, "accuracy": acc})
    return mark_pareto(out)


def _history(run: Path) -> list[dict]:
    h = run / "history.json"
    return read_json(h).get("epochs", []) if h.is_file() else []


def _cpu_ratio(run: Path) -> float | None:
    rec = run / "tradeoff_train.json"
    if not rec.is_file():
        return None
    r = read_json(rec)
    return r["cpu_s"] / r["wall_s"] if r.get("wall_s") else None


def collect_curves(sw: Sweep) -> tuple[dict, dict]:
    """({model: curve}, {model: the preset run's end: train_cpu_s, accuracy}) from what is on disk."""
    curves, ends = {}, {}
    for model in sw.preset_cfgs:
        run = _run_dir(sw, model, _curve_train_id(sw, model))
        files = sorted(_curve_dir(sw, model).glob("*.json"))
        hist, ratio = _history(run), _cpu_ratio(run)
        if files and hist and ratio is not None:
            per_epoch = hist[0]["global_step"]
            pts = []
            for f in files:
                e = read_json(f)
                try:
                    wall = train_seconds_at_step(hist, e["global_step"])
                except ValueError:
                    continue
                pts.append({**e, "epochs_done": e["global_step"] / per_epoch, "train_wall_s": round(wall, 1),
                            "train_cpu_s": round(wall * ratio, 1)})
            pts.sort(key=lambda e: e["global_step"])
            curves[model] = {"run": str(run.relative_to(sw.out)), "epochs": _curve_epochs(sw, model),
                             "cpu_per_wall": round(ratio, 2), "points": pts}
        prun = _run_dir(sw, model, "preset")
        preset_pt = next((p for p in sw.points if p.model == model and p.knob == "preset"), None)
        if preset_pt is not None and _point_done(sw, preset_pt) and _history(prun) and _cpu_ratio(prun) is not None:
            wall = sum(e["seconds"] for e in _history(prun))
            ends[model] = {"train_wall_s": round(wall, 1), "train_cpu_s": round(wall * _cpu_ratio(prun), 1),
                           "accuracy": read_json(_point_file(sw, preset_pt)).get("accuracy")}
    return curves, ends


def _meta(sw: Sweep) -> dict:
    import torch

    sim = CONFIG_DIR / "sim.yaml"
    return {"preset": sw.opts.preset, "height": sw.opts.height, "models": list(sw.preset_cfgs),
            "knobs": list(sw.opts.knobs), "device": sw.device, "data": str(sw.root),
            "sim_config_sha256": hashlib.sha256(sim.read_bytes()).hexdigest()[:12] if sim.is_file() else None,
            "data_source": data_source(read_info(sw.root).source),
            "frames": sw.opts.frames, "warmup": sw.opts.warmup, "eval_frames": sw.opts.eval_frames,
            "budget_min": sw.opts.budget, "elapsed_s": round(time.perf_counter() - sw.t0, 1),
            "machine": platform.machine(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "default_threads": torch.get_num_threads(), "load_average_start": sw.opts.load_start,
            "load_average_end": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
            "date": time.strftime("%Y-%m-%d %H:%M"), "curve_scale": sw.opts.curve_scale}


def _write_outputs(sw: Sweep, skipped: list[dict], final: bool) -> dict:
    points = collect_points(sw)
    curves, ends = collect_curves(sw)
    result = {"meta": _meta(sw), "points": points, "curves": curves, "preset_run_ends": ends, "skipped": skipped,
              "failed": [{"task": k, "error": v} for k, v in sw.failed.items()]}
    atomic_write_json(sw.out / "tradeoff.json", result)
    atomic_write_text(sw.out / "tradeoff.md", tradeoff_markdown(result))
    if final:
        if points:
            plot_tradeoff(points, sw.out / "tradeoff.png", world_label(result["meta"]))
        if curves:
            plot_learning_curves(curves, sw.out / "learning_curve.png", ends, world_label(result["meta"]))
    return result



def prepare_sweep(opts: TradeoffOptions, out: str | os.PathLike, *, registry: ModelRegistry, repo: str | os.PathLike,
                  progress: bool = True) -> Sweep:
    """Check the options, load the presets, find (or simulate) the dataset and list the points.
    repo: the checkout whose tools/train.py trains the points. Raises UserError naming the fix."""
    import torch

    t0 = time.perf_counter()
    opts.load_start = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    names = opts.models or list(registry.REGISTRY)
    for bad, ok in ((opts.frames < 1, "--frames must be >= 1"), (opts.warmup < 0, "--warmup must be >= 0"),
                    (opts.eval_frames < 0, "--eval-frames must be >= 0"),
                    (opts.budget is not None and not opts.budget > 0, "--budget must be > 0 minutes"),
                    (not opts.curve_scale > 0, "--curve-scale must be > 0"),
                    (opts.curve_points < 1, "--curve-points must be >= 1")):
        if bad:
            raise UserError(ok)
    try:
        for n in names:
            registry.get_model_class(n)
        cfgs = {n: load_run_config(n, opts.preset) for n in names}
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    device = ("cuda" if torch.cuda.is_available() else "cpu") if opts.device == "auto" else opts.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {opts.device}: CUDA is not available here; use --device cpu")

    from detbench.data import Height3Dataset
    from detbench.sim.dataset import default_dataset

    if opts.data:
        root = Path(opts.data).resolve()
        if not root.is_dir():
            raise UserError(f"--data {opts.data}: no such folder; give the dataset root (docs/data-format.md)")
    else:
        root = default_dataset(cfgs[names[0]]["data"], progress=progress)
    try:
        n_train = len(Height3Dataset(root, opts.height, "train"))
        Height3Dataset(root, opts.height, "test")
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UserError(str(e)) from None
    cores, default_threads = os.cpu_count() or 1, torch.get_num_threads()
    points = []
    try:
        for n in names:
            points += sweep_points(n, cfgs[n]["model"], opts.knobs, device, cores, default_threads, registry=registry,
                                   road_drop=bool((cfgs[n].get("road") or {}).get("drop", False)))
    except ValueError as e:
        raise UserError(str(e)) from None
    budget_s = opts.budget * 60 if opts.budget else None
    return Sweep(opts=opts, repo=Path(repo).resolve(), registry=registry.__name__, out=Path(out).resolve(), root=root,
                 device=device, preset_cfgs=cfgs, points=points, n_train=n_train,
                 costs=CostModel(PRIOR_SECONDS.get(opts.preset, PRIOR_SECONDS["cpu"])), t0=t0,
                 deadline=None if budget_s is None else t0 + budget_s)


def plan_lines(sw: Sweep) -> list[str]:
    """The plan with estimated costs, as printed by --dry-run."""
    p, by_id, _ = plan(sw)
    budget = sw.opts.budget
    lines = [f"{len(sw.points)} points over {len(sw.preset_cfgs)} model(s); budget "
             f"{'none' if not budget else f'{budget:g} min'}; plan (estimated seconds):"]
    for tid in (p.run if p else []):
        lines.append(f"  run   {by_id[tid].cost_s:8.0f}  {tid}")
    for tid in (p.skipped if p else []):
        lines.append(f"  skip  {by_id[tid].cost_s:8.0f}  {tid}: {p.reasons[tid]}")
    lines.append(f"estimated total {p.cost_s if p else 0:.0f} s")
    return lines


def run_tradeoff(sw: Sweep, progress: bool = True) -> tuple[dict, list[dict]]:
    """Run the sweep and write its outputs: (the tradeoff.json result, the skipped tasks). On Ctrl-C
    what finished is written and KeyboardInterrupt propagates."""
    sw.out.mkdir(parents=True, exist_ok=True)
    try:
        skipped = run_sweep(sw, progress=progress)
    except KeyboardInterrupt:
        _write_outputs(sw, [], final=True)
        raise
    return _write_outputs(sw, skipped, final=True), skipped


__all__ = ["Sweep", "TradeoffOptions", "collect_curves", "collect_points", "plan", "plan_lines", "prepare_sweep",
           "run_sweep", "run_tradeoff"]
