"""The speed/accuracy trade study's computations (tools/tradeoff.py runs the sweep).

Pure functions over plain dicts and dataclasses: nothing here builds, trains or runs a model.

- `pareto_flags` / `mark_pareto`: which measured points no other point beats on both
  latency and AP@R40 (per range, per device).
- `Task`, `plan_within_budget`, `CostModel`: the `--budget` planner. Tasks come in priority
  order with an estimated cost in seconds and the tasks they need; the plan takes each task
  (with its untaken needs) while the estimated total fits the seconds left. `CostModel`
  estimates a task as a per-preset prior x the knob's cost factor x a calibration ratio
  learnt from the tasks already run (their measured / estimated seconds).
- `train_seconds_at_step`: the learning curve's time axis, from a run's history.json.
- `tradeoff_markdown`, `plot_tradeoff`, `plot_learning_curves`: the report.

A *point* (one row of tradeoff.json) is a dict with at least:
  model, point (name), knob, value, trained ("at this point" | "preset model"), device,
  latency_ms {stage: {median, p90}} with a "total" stage, peak_rss_mib, parameters,
  accuracy {range_name: {ap_r40, recall} | None (range outside the modelled region)}.
`mark_pareto` adds pareto {range_name: bool | None} (None: no figure for that range) and
pareto_in_model (the same among the points of its own model: the model's curve).
Units: milliseconds per frame, MiB = 2^20 bytes, seconds; AP and recall are fractions.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterable, Mapping, Sequence

from detbench.data.regions import RANGE_NAMES, range_extent_label
from detbench.eval.report import data_label
from detbench.utils.figures import save_figure

__all__ = ["pareto_flags", "mark_pareto", "Task", "Plan", "plan_within_budget", "CostModel", "PRIOR_SECONDS",
           "train_seconds_at_step", "tradeoff_markdown", "plot_tradeoff", "plot_learning_curves", "world_label"]


# ---- Pareto front ---------------------------------------------------------------------------
def _finite(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def pareto_flags(latency: Sequence[float | None], accuracy: Sequence[float | None]) -> list[bool | None]:
    """For each point: True when no other point is at least as fast and at least as accurate
    and strictly better in one of the two (lower latency, higher accuracy); None when its
    latency or accuracy is missing or not finite (it takes no part). Identical points are
    all on the front."""
    if len(latency) != len(accuracy):
        raise ValueError(f"pareto_flags: {len(latency)} latencies but {len(accuracy)} accuracies")
    valid = [_finite(t) and _finite(a) for t, a in zip(latency, accuracy)]
    out: list[bool | None] = []
    for i, (ti, ai) in enumerate(zip(latency, accuracy)):
        if not valid[i]:
            out.append(None)
            continue
        dominated = any(valid[j] and j != i and latency[j] <= ti and accuracy[j] >= ai
                        and (latency[j] < ti or accuracy[j] > ai) for j in range(len(latency)))
        out.append(not dominated)
    return out


def _ap(point: Mapping, range_name: str) -> float | None:
    acc = (point.get("accuracy") or {}).get(range_name)
    return None if acc is None else acc.get("ap_r40")


def _latency(point: Mapping) -> float | None:
    return ((point.get("latency_ms") or {}).get("total") or {}).get("median")


def mark_pareto(points: list[dict], ranges: Sequence[str] = RANGE_NAMES) -> list[dict]:
    """Set each point's `pareto` (front of all points on its device) and `pareto_in_model`
    (front of its model's points on its device), per range, from the median total latency and
    AP@R40. Returns `points` (changed in place)."""
    for key, group_of in (("pareto", lambda p: p.get("device")),
                          ("pareto_in_model", lambda p: (p.get("device"), p.get("model")))):
        for p in points:
            p[key] = {}
        groups: dict = {}
        for i, p in enumerate(points):
            groups.setdefault(group_of(p), []).append(i)
        for idx in groups.values():
            for r in ranges:
                flags = pareto_flags([_latency(points[i]) for i in idx], [_ap(points[i], r) for i in idx])
                for i, f in zip(idx, flags):
                    points[i][key][r] = f
    return points


# ---- the budget planner -----------------------------------------------------------------------
@dataclass(frozen=True)
class Task:
    """One unit of work: `cost_s` estimated seconds still to spend (0 when done), `needs` the ids
    of the tasks that must run first (e.g. a measurement needs its model's training)."""

    id: str
    cost_s: float
    needs: tuple[str, ...] = ()


@dataclass
class Plan:
    run: list[str]  # task ids in execution order (a task's needs before it)
    skipped: list[str]  # ids that do not fit (or need a task that does not), in priority order
    cost_s: float  # estimated seconds of `run`
    budget_s: float | None  # the seconds it was planned for (None: no limit)
    reasons: dict[str, str] = field(default_factory=dict)  # id -> why it was skipped


def plan_within_budget(tasks: Sequence[Task], budget_s: float | None, goals: Sequence[str] | None = None) -> Plan:
    """Take the goals (default: every task) in their (priority) order while the estimated seconds fit `budget_s`.

    `goals` lists the ids worth running for themselves, best first; the other tasks run only
    as needs of a goal (e.g. a training run is worth its cost only with a measurement of it).
    Taking a goal takes its untaken needs (transitively) too, and costs them all; a goal
    that does not fit is skipped and the next ones are still tried (a cheaper one may fit);
    a goal whose need was skipped is skipped. `budget_s` None means no limit. Raises
    ValueError on an unknown goal or need, a cycle, a negative or non-finite cost."""
    by_id = {}
    for t in tasks:
        if t.id in by_id:
            raise ValueError(f"plan_within_budget: task {t.id!r} is listed twice")
        if not (isinstance(t.cost_s, (int, float)) and math.isfinite(t.cost_s) and t.cost_s >= 0):
            raise ValueError(f"plan_within_budget: task {t.id!r} has cost {t.cost_s!r}; costs are seconds >= 0")
        by_id[t.id] = t
    taken: set[str] = set()
    skipped: dict[str, str] = {}
    order: list[str] = []
    spent = 0.0

    def closure(tid: str, path: tuple[str, ...]) -> list[str]:
        """Untaken tasks `tid` needs (itself last), needs first."""
        if tid in path:
            raise ValueError(f"plan_within_budget: tasks need each other in a cycle: {' -> '.join(path + (tid,))}")
        if tid not in by_id:
            raise ValueError(f"plan_within_budget: task {path[-1]!r} needs {tid!r}, which is not a task")
        out: list[str] = []
        for n in by_id[tid].needs:
            if n not in taken:
                for x in closure(n, path + (tid,)):
                    if x not in out:
                        out.append(x)
        if tid not in taken and tid not in out:
            out.append(tid)
        return out

    for gid in ([t.id for t in tasks] if goals is None else goals):
        if gid not in by_id:
            raise ValueError(f"plan_within_budget: goal {gid!r} is not a task")
        t = by_id[gid]
        if t.id in taken or t.id in skipped:
            continue
        group = closure(t.id, ())
        bad = [x for x in group if x in skipped]
        if bad:
            skipped[t.id] = f"needs {bad[0]}, which did not fit"
            continue
        extra = sum(by_id[x].cost_s for x in group)
        if budget_s is not None and spent + extra > budget_s:
            left = max(0.0, budget_s - spent)
            skipped[t.id] = f"estimated {extra:.1f} s (with what it needs), {left:.1f} s of the budget left"
            continue
        spent += extra
        for x in group:
            taken.add(x)
            order.append(x)
    return Plan(run=order, skipped=list(skipped), cost_s=spent, budget_s=budget_s, reasons=skipped)


# Seconds of one task at the preset's own point before anything was measured (2 CPU cores):
# training a model, measuring one point (latency + evaluation on the test split), evaluating
# one checkpoint of the learning curve; "overhead" is the fixed start-up of any task's process
# (interpreter, torch, data), which no knob scales. The sweep corrects them by measured ratios.
PRIOR_SECONDS: dict[str, dict[str, float]] = {
    "smoke": {"train": 15.0, "measure": 8.0, "curve_eval": 3.0, "overhead": 6.0},
    "cpu": {"train": 660.0, "measure": 110.0, "curve_eval": 60.0, "overhead": 10.0},
    "paper": {"train": 36000.0, "measure": 1800.0, "curve_eval": 900.0, "overhead": 30.0},
}


class CostModel:
    """Estimated seconds of a task: overhead + prior[kind] x factor x ratio.

    `factor` is the task's cost relative to the preset's point (e.g. 4 for a voxel half as
    wide: four times the bird's-eye cells); `ratio` is the median of (measured - overhead) /
    (prior x factor) over the tasks of that kind already run for that model, else over every
    model, else 1. `prior` maps a kind to seconds, with an optional "overhead" (default 0)."""

    def __init__(self, prior: Mapping[str, float]):
        self.prior = {k: float(v) for k, v in prior.items() if k != "overhead"}
        self.overhead = float(prior.get("overhead", 0.0))
        self.ratios: dict[tuple[str, str], list[float]] = {}

    def _base(self, kind: str) -> float:
        if kind not in self.prior:
            raise KeyError(f"CostModel: no prior for task kind {kind!r} (known: {', '.join(self.prior)})")
        return self.prior[kind]

    def ratio(self, kind: str, model: str) -> float:
        own = self.ratios.get((kind, model))
        if own:
            return statistics.median(own)
        every = [r for (k, _), rs in self.ratios.items() if k == kind for r in rs]
        return statistics.median(every) if every else 1.0

    def estimate(self, kind: str, model: str, factor: float = 1.0) -> float:
        return self.overhead + self._base(kind) * float(factor) * self.ratio(kind, model)

    def observe(self, kind: str, model: str, factor: float, seconds: float) -> None:
        """Learn from a finished task that took `seconds` (the part above the overhead; a task
        no longer than the overhead counts as a ratio of 0.05, not as free)."""
        expected = self._base(kind) * float(factor)
        if seconds > 0 and expected > 0:
            self.ratios.setdefault((kind, model), []).append(max(0.05, (seconds - self.overhead) / expected))


# ---- the learning curve's time axis ---------------------------------------------------------------
def train_seconds_at_step(history: Sequence[Mapping], global_step: int) -> float:
    """Training wall seconds up to `global_step` of a run, from its history.json epochs (each
    with `global_step` at the epoch's end and the epoch's training `seconds`, evaluation
    excluded): whole epochs summed, the current one linear in its steps. Raises ValueError for a
    step past the recorded epochs or a history whose steps do not increase."""
    if global_step < 0:
        raise ValueError(f"train_seconds_at_step: global_step must be >= 0, got {global_step}")
    total, prev_step = 0.0, 0
    for rec in history:
        end, secs = int(rec["global_step"]), float(rec["seconds"])
        if end <= prev_step:
            raise ValueError(f"train_seconds_at_step: history steps must increase ({prev_step} then {end})")
        if global_step <= end:
            return total + secs * (global_step - prev_step) / (end - prev_step)
        total += secs
        prev_step = end
    raise ValueError(f"train_seconds_at_step: step {global_step} is past the history's last epoch "
                     f"(step {prev_step}); the run's history.json is older than its checkpoint")


# ---- report ------------------------------------------------------------------------------------
def _f(v, fmt: str = ".3f") -> str:
    return "-" if not _finite(v) else format(v, fmt)


def _front_cell(p: Mapping, key: str = "pareto") -> str:
    on = [r for r in RANGE_NAMES if (p.get(key) or {}).get(r)]
    return "**" + ", ".join(on) + "**" if on else ""


def world_label(meta: Mapping) -> str:
    """What every point of a sweep was measured on, for titles: "quick preset, 1.8 m, simulator calibration v2,
    seed 0" (`detbench.eval.report.data_label` of the meta's "data_source")."""
    return (f"{meta.get('preset')} preset, {_f(meta.get('height'), 'g')} m, "
            f"{data_label([{'data_source': meta.get('data_source')}])}")


def tradeoff_markdown(result: Mapping) -> str:
    """tradeoff.md: the points with the Pareto front marked, the front per range, the region
    comparison, the learning curves, skipped and failed work. `result` is tradeoff.json's dict."""
    meta, points = result.get("meta", {}), result.get("points", [])
    lines = [f"# Speed / accuracy trade ({world_label(meta)})", "",
             f"Machine: {meta.get('processor')}, {meta.get('cpu_count')} cores, torch {meta.get('torch')}; "
             f"1-min load average {meta.get('load_average_start')} at the start, {meta.get('load_average_end')} "
             f"at the end. Data: `{meta.get('data')}` (simulator config sha256 {meta.get('sim_config_sha256')}). "
             f"Sweep wall time {_f(meta.get('elapsed_s', 0) / 60, '.1f')} min"
             + (f" of a {meta['budget_min']:g} min budget" if meta.get("budget_min") else " (no budget)") + ".", "",
             "Latency: per frame, batch of 1, after warm-up, median and 90th percentile over "
             f"{meta.get('frames')} test frames, split by stage (ms). Peak RSS: the measuring process's "
             "peak resident memory from just before the model is loaded through the timed passes (the evaluation "
             "runs after it; the process's libraries and data loaded before count too: see rss_before_model_mib in "
             "the JSON), MiB = 2^20 bytes. "
             "AP@R40 and recall at 3D IoU 0.7 of all LiDAR-detected vehicles per range on the test split. "
             "`trained`: *at this point* = a model trained with this point's settings; *preset model* = "
             "the preset's trained model, changed only at inference. Pareto: the ranges in which no other "
             "point (any model, same device) is both faster and more accurate; bold = on that front.", ""]
    stages: list[str] = []  # the models' own stages in order, input subsampling first, post-processing last
    for p in points:
        stages += [s for s in (p.get("latency_ms") or {}) if s not in ("total", "subsample", "post", *stages)]
    has = {s for p in points for s in (p.get("latency_ms") or {})}
    stages = (["subsample"] if "subsample" in has else []) + stages + (["post"] if "post" in has else [])
    head = ["model", "point", "trained", "device", "latency median (ms)", "p90 (ms)",
            *[f"{s} (ms)" for s in stages], "peak RSS (MiB)", "params (M)",
            *[f"AP@R40 {r}" for r in RANGE_NAMES], *[f"recall {r}" for r in RANGE_NAMES], "Pareto front"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in points:
        lat = p.get("latency_ms") or {}
        acc = p.get("accuracy") or {}
        row = [p["model"], p["point"], p.get("trained", ""), p.get("device", ""),
               _f(_latency(p), ".1f"), _f((lat.get("total") or {}).get("p90"), ".1f"),
               *[_f((lat.get(s) or {}).get("median"), ".1f") for s in stages],
               _f(p.get("peak_rss_mib"), ".0f"), _f((p.get("parameters") or 0) / 1e6, ".3f"),
               *[_f((acc.get(r) or {}).get("ap_r40")) if acc.get(r) is not None else "n/m" for r in RANGE_NAMES],
               *[_f((acc.get(r) or {}).get("recall")) if acc.get(r) is not None else "n/m" for r in RANGE_NAMES],
               _front_cell(p)]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "n/m: not modelled (the point's region does not cover that range).", ""]

    lines += ["## Pareto front per range", ""]
    for r in RANGE_NAMES:
        front = sorted((p for p in points if (p.get("pareto") or {}).get(r)), key=lambda p: _latency(p))
        lines.append(f"- {range_extent_label(r)}: " + (" -> ".join(
            f"{p['model']} / {p['point']} ({_f(_latency(p), '.1f')} ms, AP {_f(_ap(p, r))})" for p in front)
            or "no point with a figure"))
    lines.append("")

    regions = [p for p in points if p.get("knob") == "region"]
    if regions:
        lines += ["## Modelled region: a grid shrunk to the range against the full grid", "",
                  "Each region point is a model trained and run on a grid covering only that range (plus the "
                  "margins of the model's config); the full grid is the preset's model, evaluated on the same "
                  "range.", "",
                  "| model | range | grid x max / y half-width (m) | latency shrunk / full (ms) | "
                  "AP@R40 shrunk / full | recall shrunk / full |", "|---|---|---|---|---|---|"]
        full = {(p["model"], p.get("device")): p for p in points if p.get("knob") == "preset"}
        for p in regions:
            base = full.get((p["model"], p.get("device")))
            r = p.get("region_range")
            pcr = p.get("point_cloud_range") or [None] * 6
            lines.append(f"| {p['model']} | {r} | {_f(pcr[3], 'g')} / {_f(pcr[4], 'g')} | "
                         f"{_f(_latency(p), '.1f')} / {_f(_latency(base) if base else None, '.1f')} | "
                         f"{_f(_ap(p, r))} / {_f(_ap(base, r) if base else None)} | "
                         f"{_f(((p.get('accuracy') or {}).get(r) or {}).get('recall'))} / "
                         f"{_f((((base or {}).get('accuracy') or {}).get(r) or {}).get('recall'))} |")
        lines.append("")

    curves = result.get("curves") or {}
    if curves:
        lines += ["## Training budget: AP@R40 against training time", "",
                  "One training run per model, its checkpoints evaluated on the test split. Training time is "
                  "the epochs' wall time (evaluation and start-up excluded, linear within an epoch); CPU-minutes "
                  "are that time x the run's CPU time / wall time (its DataLoader workers included). The run "
                  "follows one one-cycle schedule over all its epochs, so a checkpoint before the end is "
                  "taken at a higher learning rate than a shorter run's end would be.", ""]
        for model, c in curves.items():
            lines += [f"### {model}: {c.get('epochs')} epochs ({c.get('run')})", "",
                      "| checkpoint | epochs done | train wall (min) | train CPU (min) | "
                      + " | ".join(f"AP@R40 {r}" for r in RANGE_NAMES) + " |", "|---|---|---|---|---|---|---|"]
            for e in c.get("points", []):
                lines.append(f"| {e['checkpoint']} | {_f(e.get('epochs_done'), '.2f')} | "
                             f"{_f(e.get('train_wall_s', 0) / 60, '.2f')} | "
                             f"{_f(e.get('train_cpu_s', 0) / 60, '.2f')} | "
                             + " | ".join(_f(((e.get('accuracy') or {}).get(r) or {}).get('ap_r40'))
                                          for r in RANGE_NAMES) + " |")
            lines.append("")

    skipped = result.get("skipped") or []
    if skipped:
        lines += ["## Not run within the budget", "", "| task | estimated (s) | why |", "|---|---|---|"]
        lines += [f"| {s['task']} | {_f(s.get('estimated_s'), '.0f')} | {s.get('reason', '')} |" for s in skipped]
        lines.append("")
    failed = result.get("failed") or []
    if failed:
        lines += ["## Failed", "", "| task | error |", "|---|---|"]
        lines += [f"| {s['task']} | {str(s.get('error', '')).splitlines()[-1] if s.get('error') else ''} |"
                  for s in failed]
        lines.append("")
    return "\n".join(lines) + "\n"


def _model_colors(names: Iterable[str]) -> dict[str, str]:
    palette = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink"]
    return {n: palette[i % len(palette)] for i, n in enumerate(sorted(set(names)))}


def _ap_limits(ax, values) -> None:
    """AP axis from 0 to a little above the largest value (at least 0.1), so a flat 0 reads as 0."""
    top = max([v for v in values if _finite(v)], default=0.0)
    ax.set_ylim(-0.02, max(0.1, min(1.0, top) * 1.1))


def plot_tradeoff(points: Sequence[Mapping], path: str | Path, world: str = "") -> Path:
    """Latency (median, ms per frame, log scale) against AP@R40, one panel per range; every point
    a marker (filled: trained at that point, hollow: the preset model changed at inference), one
    line per model through its own Pareto front, a star on the front of all models; `world` (`world_label`)
    heads the title. Returns path."""
    from matplotlib.figure import Figure


    colors = _model_colors(p["model"] for p in points)
    fig = Figure(figsize=(15, 4.8), layout="constrained")
    axes = fig.subplots(1, len(RANGE_NAMES))
    for ax, r in zip(axes, RANGE_NAMES):
        for model, color in colors.items():
            own = [p for p in points if p["model"] == model and _finite(_latency(p)) and _finite(_ap(p, r))]
            for p in own:
                trained = p.get("trained") == "at this point"
                ax.scatter([_latency(p)], [_ap(p, r)], s=28, color=color, alpha=0.8,
                           facecolors=color if trained else "none", edgecolors=color)
                if (p.get("pareto") or {}).get(r):
                    ax.scatter([_latency(p)], [_ap(p, r)], s=140, marker="*", color=color, zorder=3)
            front = sorted((p for p in own if (p.get("pareto_in_model") or {}).get(r)), key=_latency)
            if front:
                ax.plot([_latency(p) for p in front], [_ap(p, r) for p in front], "-", color=color, label=model)
        ax.set_xscale("log")
        _ap_limits(ax, [_ap(p, r) for p in points])
        ax.set_xlabel("latency per frame, median (ms, log scale)")
        ax.set_ylabel("AP@R40 (3D IoU 0.7)")
        ax.set_title(range_extent_label(r))
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8, title="model (line: its Pareto front)", title_fontsize=8)
    fig.suptitle((f"{world}: " if world else "") + "latency against accuracy; filled: trained at the point, "
                 "hollow: the preset's model, as is or changed at inference; star: on the front of all models")
    return save_figure(fig, path)


def plot_learning_curves(curves: Mapping[str, Mapping], path: str | Path, preset_points: Mapping[str, Mapping] = {},
                         world: str = "") -> Path:
    """AP@R40 against training CPU-minutes, one panel per range, one line per model (its run's
    checkpoints); `preset_points` {model: {"train_cpu_s", "accuracy"}} adds the preset's own
    final model as a cross; `world` (`world_label`) heads the title. Returns path."""
    from matplotlib.figure import Figure


    colors = _model_colors(list(curves) + list(preset_points))
    fig = Figure(figsize=(15, 4.6), layout="constrained")
    axes = fig.subplots(1, len(RANGE_NAMES))
    for ax, r in zip(axes, RANGE_NAMES):
        for model, c in curves.items():
            pts = [e for e in c.get("points", []) if _finite(((e.get("accuracy") or {}).get(r) or {}).get("ap_r40"))]
            pts.sort(key=lambda e: e["train_cpu_s"])
            ax.plot([e["train_cpu_s"] / 60 for e in pts], [e["accuracy"][r]["ap_r40"] for e in pts], "o-",
                    color=colors[model], label=f"{model} ({c.get('epochs')} epochs)")
        for model, p in preset_points.items():
            ap = ((p.get("accuracy") or {}).get(r) or {}).get("ap_r40")
            if _finite(ap) and _finite(p.get("train_cpu_s")):
                ax.scatter([p["train_cpu_s"] / 60], [ap], marker="x", s=60, color=colors[model],
                           label=f"{model} preset run's end" if r == RANGE_NAMES[0] else None)
        _ap_limits(ax, [((e.get("accuracy") or {}).get(r) or {}).get("ap_r40") for c in curves.values()
                        for e in c.get("points", [])])
        ax.set_xlabel("training time (CPU-minutes)")
        ax.set_ylabel("AP@R40 (3D IoU 0.7)")
        ax.set_title(range_extent_label(r))
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle((f"{world}: " if world else "") + "learning curves, checkpoints of one run per model, "
                 "evaluated on the test split")
    return save_figure(fig, path)
