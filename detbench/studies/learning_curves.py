"""Learning curves over training seeds: a metric of the per-epoch evaluations against training CPU-minutes.

Each training run evaluated during training (`train.eval_every`) writes its epochs to history.json with
their wall and CPU seconds (`seconds`, `cpu_seconds`: the training process's own, its data workers
apart) and the evaluation's metrics. `collect_curves` groups runs by model (and a label, e.g. the
preset), lines up their epochs, and gives per epoch the cumulative CPU-minutes and each metric's mean,
minimum and maximum over the runs (the training seeds); `curves_markdown` and `plot_curves` turn that into
a table and a figure. Only epochs that every run of a group evaluated are kept, so a point is always a
mean over the same seeds.

Units: minutes of CPU time (or of wall time where a run records no CPU time); metrics are fractions.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from detbench.utils.atomic import read_json

__all__ = ["CurvePoint", "Curve", "DEFAULT_METRICS", "collect_curves", "curves_markdown", "plot_curves"]

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
    cfg_seed = None
    config = run / "config.yaml"
    if config.is_file():
        import yaml

        cfg_seed = ((yaml.safe_load(config.read_text(encoding="utf-8")) or {}).get("train") or {}).get("seed")
    return str(s.get("model")), str(s.get("preset") or ""), cfg_seed, list(read_json(history).get("epochs", []))


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
