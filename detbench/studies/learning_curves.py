"""Learning curves over training seeds: a metric of the per-epoch evaluations against training CPU-minutes.

Each training run writes its epochs to history.json with their wall and CPU seconds (`seconds`,
`cpu_seconds`: the training process's own, its data workers apart) and, when it evaluated during training
(`train.eval_every`), the evaluation's metrics. A run that kept its epoch checkpoints
(`train.keep_checkpoints: 0`, as a study's runs may) is evaluated afterwards instead
(`evaluate_run_checkpoints`: each epoch checkpoint on evenly spaced test frames, cached in the run's
curve_eval.json), and those metrics take the place of the training's own.

`collect_curves` groups runs by model (and a label, e.g. the preset), lines up their epochs, and gives per
epoch the cumulative CPU-minutes and each metric's mean, minimum and maximum over the runs (the training
seeds); `curves_markdown` and `plot_curves` turn that into a table and a figure. Only epochs that every run
of a group evaluated are kept, so a point is always a mean over the same seeds.

Units: minutes of CPU time (or of wall time where a run records no CPU time); metrics are fractions.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detbench.utils.atomic import read_json

__all__ = ["CURVE_EVAL", "CurvePoint", "Curve", "DEFAULT_METRICS", "collect_curves", "curves_markdown",
           "evaluate_run_checkpoints", "plot_curves"]

CURVE_EVAL = "curve_eval.json"  # a run's epoch checkpoints evaluated afterwards: {checkpoint name: metrics}

DEFAULT_METRICS = ("ap_r40_small", "recall_small", "recall_large")


@dataclass(frozen=True)
class CurvePoint:
    """One epoch of a group of runs: its cumulative training minutes (mean over runs) and each metric's
    mean, minimum and maximum over the runs."""

    epoch: int
    minutes: float
    mean: dict[str, float]
    low: dict[str, float]
    high: dict[str, float]


@dataclass(frozen=True)
class Curve:
    """A group of runs (one model, one label) and its points; `clock` is "cpu" or "wall"."""

    model: str
    label: str
    runs: tuple[str, ...]
    seeds: tuple[int | None, ...]
    epochs: int
    clock: str
    points: tuple[CurvePoint, ...]


def _run_facts(run: Path) -> tuple[str, str, int | None, list[dict]]:
    """(model, preset, seed, epochs of history.json) of a training run folder; ValueError naming what lacks."""
    summary, history = run / "train_summary.json", run / "history.json"
    if not summary.is_file() or not history.is_file():
        raise ValueError(f"{run}: not a finished training run (needs train_summary.json and history.json, "
                         f"as tools/train.py writes them)")
    s = read_json(summary)
    epochs = list(read_json(history).get("epochs", []))
    evaluated = read_json(run / CURVE_EVAL).get("checkpoints", {}) if (run / CURVE_EVAL).is_file() else {}
    for e in epochs:  # metrics of the checkpoints evaluated afterwards take the place of the training's own
        if e.get("checkpoint") in evaluated:
            e["metrics"] = evaluated[e["checkpoint"]]
    cfg_seed = None
    config = run / "config.yaml"
    if config.is_file():
        import yaml

        cfg_seed = ((yaml.safe_load(config.read_text(encoding="utf-8")) or {}).get("train") or {}).get("seed")
    return str(s.get("model")), str(s.get("preset") or ""), cfg_seed, epochs


def evaluate_run_checkpoints(run: str | Path, frames: int, load_model, progress=None) -> dict:
    """Evaluate every epoch checkpoint of the training run `run` (epoch_EEE.pt in its checkpoints/) on
    `frames` evenly spaced frames of the test split at the run's height, as the training's own evaluation
    does (`detbench.train.run.make_eval_fn`: recall and AP@R40 of all vehicles per range). `load_model(path)`
    returns (model in eval mode, checkpoint dict) (the registry's `load_from_checkpoint`). Results are kept in
    RUN/curve_eval.json and reused while the frame count is the same. Returns {checkpoint name: metrics}."""
    from detbench.data import Height3Dataset
    from detbench.eval.evaluate import EvalConfig
    from detbench.train.checkpoint import CheckpointManager
    from detbench.train.run import make_eval_fn
    from detbench.utils.atomic import atomic_write_json

    run = Path(run)
    cache = run / CURVE_EVAL
    kept = read_json(cache) if cache.is_file() else {}
    done = kept.get("checkpoints", {}) if kept.get("frames") == int(frames) else {}
    files = [p for p in CheckpointManager(run / "checkpoints").list() if "_step_" not in p.name]
    if not files:
        raise ValueError(f"{run}: holds no epoch checkpoint to evaluate; train with --set train.keep_checkpoints=0 "
                         f"to keep every epoch's")
    eval_fn, ecfg = None, None
    for path in files:
        if path.name in done:
            continue
        model, ck = load_model(path)
        if eval_fn is None:
            from detbench.data.road import RoadConfig

            ecfg = EvalConfig.from_dict({**ck["config"]["eval"], "max_frames": int(frames)})
            test = Height3Dataset(ck["data"]["source"], float(ck["data"]["height"]), "test")
            n = len(test)
            picked = [test[int(i)] for i in np.linspace(0, n - 1, min(int(frames), n)).astype(int)]
            eval_fn = make_eval_fn(picked, ecfg, ck["config"]["model"]["point_cloud_range"], "cpu", 4,
                                   road=RoadConfig.of_run_config(ck["config"]))
        done[path.name] = {k: float(v) for k, v in eval_fn(model, 0).items()}
        atomic_write_json(cache, {"frames": int(frames), "checkpoints": done})
        if progress:
            progress(f"{run.name}: {path.name}")
    return done


def collect_curves(runs: Iterable[str | Path], metrics: Sequence[str] = DEFAULT_METRICS,
                   label_of=None) -> list[Curve]:
    """The learning curves of `runs` (training run folders), grouped by (model, label); `label_of(run, preset)`
    names a run's group (default: its preset). ValueError for a folder that is not a finished run or whose runs
    evaluated none of `metrics`."""
    groups: dict[tuple[str, str], list[tuple[Path, int | None, list[dict]]]] = {}
    for r in runs:
        run = Path(r)
        model, preset, seed, epochs = _run_facts(run)
        label = label_of(run, preset) if label_of else preset
        groups.setdefault((model, label), []).append((run, seed, epochs))
    curves = []
    for (model, label), members in sorted(groups.items()):
        curves.append(_curve(model, label, members, metrics))
    return curves


def _curve(model: str, label: str, members: list, metrics: Sequence[str]) -> Curve:
    clock = "cpu" if all("cpu_seconds" in e for _, _, eps in members for e in eps) else "wall"
    key = "cpu_seconds" if clock == "cpu" else "seconds"
    per_run = []
    for run, _, epochs in members:
        total, evaluated = 0.0, {}
        for e in sorted(epochs, key=lambda e: e["epoch"]):
            total += float(e.get(key) or 0.0)
            m = e.get("metrics") or {}
            if all(_finite(m.get(k)) for k in metrics):
                evaluated[int(e["epoch"])] = (total / 60.0, {k: float(m[k]) for k in metrics})
        if not evaluated:
            raise ValueError(f"{run}: its history.json holds no epoch evaluated on {', '.join(metrics)}; train "
                             f"with --set train.eval_every=1 (or another period) to record a learning curve")
        per_run.append(evaluated)
    common = sorted(set.intersection(*(set(r) for r in per_run)))
    points = []
    for ep in common:
        vals = {k: [r[ep][1][k] for r in per_run] for k in metrics}
        points.append(CurvePoint(ep, round(sum(r[ep][0] for r in per_run) / len(per_run), 3),
                                 {k: round(sum(v) / len(v), 4) for k, v in vals.items()},
                                 {k: round(min(v), 4) for k, v in vals.items()},
                                 {k: round(max(v), 4) for k, v in vals.items()}))
    return Curve(model, label, tuple(str(run) for run, _, _ in members), tuple(s for _, s, _ in members),
                 max(len(eps) for _, _, eps in members), clock, tuple(points))


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def curves_markdown(curves: Sequence[Curve], metrics: Sequence[str] = DEFAULT_METRICS) -> str:
    """One table per curve: epoch, training minutes, each metric's mean over the runs [min, max]."""
    lines = ["# Learning curves", "",
             "Each row: an epoch evaluated during training, the cumulative training time (minutes of the training "
             "process's CPU time, its data workers apart, or wall time where a run records none) averaged over "
             "the runs, and each metric's mean over the runs (the training seeds) with [min, max]. Metrics are "
             "fractions, on the evaluation each run made during training (`eval.max_frames`).", ""]
    for c in curves:
        seeds = ", ".join("?" if s is None else str(s) for s in c.seeds)
        lines += [f"## {c.model} ({c.label}): {len(c.runs)} run(s), seeds {seeds}, {c.epochs} epochs", "",
                  "| epoch | " + ("CPU" if c.clock == "cpu" else "wall") + " minutes | "
                  + " | ".join(metrics) + " |", "|---:|---:|" + "---|" * len(metrics)]
        for p in c.points:
            cells = [f"{p.mean[k]:.3f} [{p.low[k]:.3f}, {p.high[k]:.3f}]" if len(c.runs) > 1 else f"{p.mean[k]:.3f}"
                     for k in metrics]
            lines.append(f"| {p.epoch} | {p.minutes:.1f} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot_curves(curves: Sequence[Curve], path: str | Path, metrics: Sequence[str] = DEFAULT_METRICS,
                title: str = "") -> Path:
    """One panel per metric: each curve's mean over its runs against training minutes, its [min, max] band."""
    from matplotlib.figure import Figure

    from detbench.utils.figures import save_figure

    fig = Figure(figsize=(5.2 * len(metrics), 4.4), layout="constrained")
    axes = fig.subplots(1, len(metrics), squeeze=False)[0]
    for ax, k in zip(axes, metrics):
        for c in curves:
            xs = [p.minutes for p in c.points]
            (line,) = ax.plot(xs, [p.mean[k] for p in c.points], "o-", label=f"{c.model} ({c.label}, "
                                                                             f"{len(c.runs)} seeds)")
            if len(c.runs) > 1:
                ax.fill_between(xs, [p.low[k] for p in c.points], [p.high[k] for p in c.points],
                                color=line.get_color(), alpha=0.15)
        ax.set_xlabel(f"training time ({'CPU' if all(c.clock == 'cpu' for c in curves) else 'wall'}-minutes)")
        ax.set_ylabel(k)
        ax.set_ylim(0, 1)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title or "learning curves: mean over training seeds, band = min..max")
    return save_figure(fig, path)
