"""The simulator's calibration check: seeds simulated at the paper's heights, judged against Tables IV-VI.

tools/check_calibration.py's computation. The statistics (criteria, decomposition, judging over
seeds, bootstrap intervals, precision and pass rates) are in detbench.studies.calibration; this
module runs the simulator, applies them and lays the report and its Markdown out.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from detbench.config import ConfigError
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies import calibration as cc
from detbench.utils.cli import UserError


@dataclass
class CalibrationOptions:
    """The check's settings (tools/check_calibration.py's arguments; tolerances are LDR fractions,
    total_tolerance a relative difference)."""

    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4, 5])
    frames: int = 8000
    block_frames: int = 0
    frames_per_scene: int | None = None
    tolerance: float = 0.05
    pooled_tolerance: float = 0.03
    allowed_misses: int = 1
    total_tolerance: float = 0.15
    second_tolerance: float = 0.07
    pair_tolerance: float = 0.03
    preset: str = "paper"
    overrides: list[str] = field(default_factory=list)
    no_progress: bool = False


LEVEL_TITLES = {"all": "All (Table IV)", "top3": "Top3 (Table V)", "top6": "Top6 (Table VI)"}


def simulated_scene_counts(seed: int, frames: int, frames_per_scene: int, cfg: dict, progress: bool) -> np.ndarray:
    """Scene counts (scenes, 3 ranges, 3 levels, 4) of `frames` simulated instants at the paper's heights
    (hit counts, no points)."""
    from detbench.sim import HighwaySimulator, lidar_preset

    lidars = [lidar_preset(float(h)) for h in cc.HEIGHTS]
    steps = HighwaySimulator(cfg, seed).run(frames, lidars, frames_per_scene=frames_per_scene, with_points=False)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, total=frames, desc=f"seed {seed}", unit="frame", leave=False)
    return cc.scene_counts(steps)


def _f(v, fmt="{:.3f}") -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt.format(v)


def _md_row(seed: str, name: str, frames: int, res: dict) -> str:
    flags = " / ".join("yes" if res[k] else "no" for k in cc.CRITERIA)
    return (f"| {seed} | {name} ({frames}) | {_f(res['worst_abs_deviation'])} | "
            f"{_f(100 * res['worst_total_ratio_error'], '{:.0f} %')} | {_f(res['worst_second_deviation'])} | "
            f"{flags} | {'yes' if res['ok'] else 'no'} |")


def _cell_tables(pooled: dict, judged: dict | None, intervals: dict, worst_seed: np.ndarray | None) -> list[str]:
    """The 27 cells, per level: pooled LDR [95 %] / paper, worst seed deviation, seeds within the tolerance."""
    paper, paper_pf = cc.paper_arrays()
    md = []
    for k, lv in enumerate(LEVELS):
        md += [f"### {LEVEL_TITLES[lv]}", "",
               "| range | " + " | ".join(f"{h} m pooled [95 %] / paper" for h in cc.HEIGHTS)
               + " | worst seed dev 0.5 / 1.0 / 1.8 | seeds within 0.5 / 1.0 / 1.8 | veh/frame here [95 %] / paper |",
               "| --- | --- | --- | --- | --- | --- | --- |"]
        for i, r in enumerate(RANGE_NAMES):
            cells = [_ldr_cell(pooled["ldr"][i, k, j], intervals["ldr"][i][k][j] if intervals.get("ldr") else None,
                               paper[i, k, j]) for j in range(3)]
            ws = "-" if worst_seed is None else " / ".join(f"{worst_seed[i, k, j]:.3f}" for j in range(3))
            sw = "-" if judged is None else " / ".join(str(int(judged["seeds_within"][i, k, j])) for j in range(3))
            ci = intervals["vehicles_per_frame"][i][k] if intervals.get("vehicles_per_frame") else None
            pf = (f"{pooled['vehicles_per_frame'][i, k]:.2f} {'' if ci is None else f'[{ci[0]:.2f}, {ci[1]:.2f}]'}"
                  f" / {paper_pf[i, k]:.2f}")
            md.append(f"| {r} | " + " | ".join(cells) + f" | {ws} | {sw} | {pf} |")
        md.append("")
    return md


def _ldr_cell(value, ci, paper_value) -> str:
    """'0.812 [0.790, 0.830] / 0.87': an LDR here, its 95 % interval (when given) and the paper's."""
    return f"{_f(value)} {'' if ci is None else f'[{ci[0]:.3f}, {ci[1]:.3f}]'} / {paper_value:.2f}"


def _decomposition_table(res: dict, intervals: dict) -> list[str]:
    paper, paper_pf = cc.paper_decomposition()
    md = ["| part | range | " + " | ".join(f"{h} m here [95 %] / paper" for h in cc.HEIGHTS)
          + " | veh/frame here / paper |", "| --- | --- | --- | --- | --- | --- |"]
    for p, part in enumerate(cc.PARTS):
        for i, r in enumerate(RANGE_NAMES):
            cells = [_ldr_cell(res["decomposition_ldr"][i, p, j],
                               intervals["decomposition_ldr"][i][p][j] if intervals.get("decomposition_ldr") else None,
                               paper[i, p, j]) for j in range(3)]
            md.append(f"| {cc.PART_NAMES[part]} | {r} | " + " | ".join(cells)
                      + f" | {res['decomposition_per_frame'][i, p]:.2f} / {paper_pf[i, p]:.2f} |")
    return md + [""]


def _load_config(args: CalibrationOptions) -> tuple[dict, int]:
    """The simulator config the options name and its frames per scene; UserError for a bad option."""
    from detbench.sim import load_sim_config

    if args.frames <= 0 or args.block_frames < 0:
        raise UserError("--frames must be > 0 and --block-frames >= 0")
    if args.allowed_misses < 0:
        raise UserError("--allowed-misses must be >= 0")
    try:
        cfg = load_sim_config(args.preset, overrides=tuple(args.overrides))
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    fps = int(args.frames_per_scene or cfg["scene"]["frames_per_scene"])
    if args.block_frames and args.block_frames % fps:
        raise UserError(f"--block-frames {args.block_frames} must be a multiple of the frames per scene ({fps}); "
                        f"set --frames-per-scene or change --block-frames")
    return cfg, fps


def _tolerances(args: CalibrationOptions) -> dict[str, float]:
    """The per-run criteria's tolerances, as `calibration.check_counts` takes them."""
    return {"tolerance": args.tolerance, "pair_tolerance": args.pair_tolerance,
            "total_tolerance": args.total_tolerance, "second_tolerance": args.second_tolerance}


def _report_head(args: CalibrationOptions, calibration: str, fps: int, tols: dict) -> dict:
    """calibration.json before any seed ran: the settings, units, layout and the paper's figures."""
    paper, paper_pf = cc.paper_arrays()
    paper_dec, paper_dec_pf = cc.paper_decomposition()
    return {"preset": args.preset, "overrides": list(args.overrides), "calibration": calibration,
            "frames": args.frames, "frames_per_scene": fps, "block_frames": args.block_frames, **tols,
            "pooled_tolerance": args.pooled_tolerance, "allowed_misses": args.allowed_misses,
            "units": {"ldr": "fraction detected / total", "vehicles_per_frame": "count per frame",
                      "total_ratio": "vehicles per frame here / paper", "seconds": "wall-clock s"},
            "layout": "cells are {level: {range: {height: value}}}; decomposition {part: {range: {height}}}; "
                      "parts: second = Top6 - Top3, beyond = All - Top6",
            "paper": {"ldr": cc.cell_grid(paper), "vehicles_per_frame": cc.level_grid(paper_pf),
                      "decomposition_ldr": cc.part_grid(paper_dec),
                      "decomposition_per_frame": cc.level_grid(paper_dec_pf, cc.PARTS)},
            "seeds": {}}


def _markdown_head(args: CalibrationOptions, calibration: str, fps: int) -> list[str]:
    """calibration.md's title, the criteria with their tolerances, and the head of the per-run table."""
    return [f"# Simulator calibration against Tables IV-VI ({args.preset} preset, calibration {calibration})", "",
            f"{args.frames} frames per seed, scenes of {fps} frames"
            + (f", blocks of {args.block_frames} frames" if args.block_frames else "") + ". Criteria per run: "
            f"(1) every |LDR - paper| <= {args.tolerance} (27 cells); (2) vehicles per frame within "
            f"+-{100 * args.total_tolerance:.0f} % (9 range x level); (3) |second-in-lane LDR - paper| <= "
            f"{args.second_tolerance}; (4) 1.8 m above both lower heights; (5) |LDR(0.5) - LDR(1.0)| <= "
            f"{args.pair_tolerance}. LDR is a fraction; vehicles per frame a count.", "",
            "| seed | run | worst abs dev | worst total error | worst second-in-lane dev | criteria 1 / 2 / 3 / 4 / 5 "
            "| ok |", "| --- | --- | --- | --- | --- | --- | --- |"]


@dataclass
class SeedRun:
    """One seed simulated and checked: its scene counts, the wall-clock seconds the simulation took, and the
    check (`calibration.summarize`) of its whole run ("all") and of each block."""

    seed: int
    scenes: np.ndarray  # (scenes, 3 ranges, 3 levels, 1 + 3 heights)
    seconds: float
    runs: list[tuple[str, int, dict]]  # (run name, frames, check result), "all" first

    @property
    def whole(self) -> dict:
        """The check of the seed's whole run."""
        return next(res for name, _, res in self.runs if name == "all")

    def report(self) -> dict:
        """The seed's entry in calibration.json."""
        return {"seconds": round(self.seconds, 1), "runs": {name: cc.jsonable(res) for name, _, res in self.runs},
                "scene_ldr_std": cc.cell_grid(cc.scene_ldr_std(self.scenes))}

    def line(self, frames: int) -> str:
        """The line printed when the seed is done."""
        w = self.whole
        return (f"seed {self.seed}: {frames} frames in {self.seconds:.0f} s, worst |dLDR| "
                f"{_f(w['worst_abs_deviation'])}, worst second-in-lane {_f(w['worst_second_deviation'])}, worst total "
                f"{100 * w['worst_total_ratio_error']:.0f} %, ok={w['ok']}")


def run_seed(seed: int, args: CalibrationOptions, cfg: dict, fps: int, tols: dict) -> SeedRun:
    """Simulate one seed's frames and check its whole run and each block of `args.block_frames`."""
    t0 = time.perf_counter()
    scenes = simulated_scene_counts(seed, args.frames, fps, cfg, not args.no_progress)
    seconds = time.perf_counter() - t0
    runs = [(name, nf, cc.summarize(block, nf, **tols))
            for name, block, nf in cc.study_runs(scenes, args.frames, fps, args.block_frames)]
    return SeedRun(seed, scenes, seconds, runs)


@dataclass
class PooledRun:
    """Every seed's scenes together: their check, bootstrap intervals and, with several seeds, the verdict."""

    seeds: list[int]
    scenes: np.ndarray  # every seed's scene counts, concatenated
    frames: int
    result: dict  # calibration.summarize of the pooled scenes
    intervals: dict  # calibration.bootstrap_intervals
    judged: dict | None  # calibration.judge_seeds; None with one seed

    def report(self) -> dict:
        """calibration.json's "pooled" entry."""
        return {"seeds": list(self.seeds), "frames": self.frames, **cc.jsonable(self.result),
                "intervals_95": self.intervals}

    def row(self) -> str:
        """The pooled row of the per-run table."""
        p = self.result
        return (f"| pooled | all seeds ({self.frames}) | {_f(p['worst_abs_deviation'])} | "
                f"{100 * p['worst_total_ratio_error']:.0f} % | {_f(p['worst_second_deviation'])} | "
                + " / ".join("yes" if p[k] else "no" for k in cc.CRITERIA) + f" | {'yes' if p['ok'] else 'no'} |")


def pool_seeds(runs: list[SeedRun], args: CalibrationOptions, fps: int, tols: dict) -> PooledRun:
    """Check the seeds' scenes pooled and, with more than one seed, judge the seeds (`calibration.judge_seeds`)."""
    scenes = np.concatenate([r.scenes for r in runs])
    frames = args.frames * len(runs)
    pooled = cc.summarize(scenes, frames, **tols)
    judged = None
    if len(runs) > 1:
        judged = cc.judge_seeds({str(r.seed): r.whole for r in runs}, pooled, args.tolerance, args.pooled_tolerance,
                                args.allowed_misses)
    return PooledRun([r.seed for r in runs], scenes, frames, pooled, cc.bootstrap_intervals(scenes, fps), judged)


def _verdict_report(judged: dict) -> dict:
    """calibration.json's "verdict"."""
    return {**judged["verdict"], "seeds_within": cc.cell_grid(judged["seeds_within"], 0),
            "seeds_needed": judged["seeds_needed"],
            "worst_seed_deviation": cc.cell_grid(judged["worst_seed_deviation"])}


def _verdict_lines(judged: dict, args: CalibrationOptions) -> list[str]:
    """The verdict section of calibration.md."""
    v = judged["verdict"]
    n = len(args.seeds)
    return ["", f"## Verdict over {n} seeds: {'met' if v['ok'] else 'NOT met'}", "",
            f"- every cell within +-{args.tolerance} for at least {judged['seeds_needed']} of {n} "
            f"seeds: {'yes' if v['cells_per_seed'] else 'no'}",
            f"- every pooled cell within +-{args.pooled_tolerance}: {'yes' if v['cells_pooled'] else 'no'}",
            f"- pooled vehicles per frame within +-{100 * args.total_tolerance:.0f} %: "
            f"{'yes' if v['totals_pooled'] else 'no'}",
            f"- pooled second-in-lane LDR within +-{args.second_tolerance}: {'yes' if v['second_pooled'] else 'no'}",
            f"- 1.8 m above both lower heights (pooled / every seed): "
            f"{'yes' if v['high_above_low_pooled'] else 'no'}"
            f" / {'yes' if v['high_above_low_every_seed'] else 'no'}",
            f"- 0.5 m and 1.0 m within {args.pair_tolerance} (pooled / every seed): "
            f"{'yes' if v['low_pair_close_pooled'] else 'no'} / {'yes' if v['low_pair_close_every_seed'] else 'no'}"]


def _cells_lines(pooled: PooledRun) -> list[str]:
    """The 27 cells and the decomposition, pooled, with their intervals."""
    n = len(pooled.seeds)
    judged = pooled.judged
    md = ["", f"## The 27 cells ({'pooled over ' + str(n) + ' seeds' if n > 1 else 'one seed'}"
              f", 95 % bootstrap intervals over scenes)", ""]
    md += _cell_tables(pooled.result, judged, pooled.intervals,
                       None if judged is None else judged["worst_seed_deviation"])
    md += ["## Decomposition (second-in-lane = Top6 - Top3, judged; beyond-Top6 = All - Top6, reported)", ""]
    return md + _decomposition_table(pooled.result, pooled.intervals)


def precision_report(scenes: np.ndarray, args: CalibrationOptions, fps: int, tols: dict) -> dict:
    """calibration.json's "precision": the scene scatter and how often a study of the run's size (and of a block)
    meets the criteria, estimated from the scenes."""
    prec = cc.precision(scenes, args.tolerance, args.block_frames // fps if args.block_frames else None)
    study_frames = [args.frames] + ([args.block_frames] if args.block_frames else [])
    prec["pass_rate"] = cc.pass_rates(scenes, study_frames, fps, **tols)
    return prec


def _pass_rate_phrases(prec: dict) -> list[str]:
    return [f"a study of {r['scenes_per_block']} scenes ({f} frames) meets every criterion {100 * r['ok']:.0f} % "
            f"of the time (the 27 cells alone: {100 * r['within']:.0f} %)"
            for f, r in prec["pass_rate"].items() if r["ok"] is not None]


def _precision_lines(prec: dict) -> list[str]:
    rates = _pass_rate_phrases(prec)
    lo, hi = prec["scene_std_range"]
    return ["## Precision", "",
            f"One scene's LDR scatters by {_f(lo)}-{_f(hi)} (std across scenes, all seeds' {prec['scenes']} scenes); "
            f"a study of n scenes is uncertain by about +-1.96 std / sqrt(n) (95 %)."
            + (f" Estimated from the scenes directly: {'; '.join(rates)}." if rates else ""), ""]


def check_calibration(args: CalibrationOptions) -> tuple[dict, str, bool]:
    """Simulate each seed's frames at the paper's heights and judge them against Tables IV-VI: (the
    report for calibration.json, the Markdown of calibration.md, whether the verdict or, with one
    seed, its run failed). Prints a line per seed and the verdict as it goes; UserError names the
    fix for a bad option."""
    cfg, fps = _load_config(args)
    tols = _tolerances(args)
    calibration = str(cfg.get("calibration", "v1"))
    report = _report_head(args, calibration, fps, tols)
    md = _markdown_head(args, calibration, fps)
    runs = []
    for seed in args.seeds:
        run = run_seed(seed, args, cfg, fps, tols)
        runs.append(run)
        md += [_md_row(str(seed), name, nf, res) for name, nf, res in run.runs]
        report["seeds"][str(seed)] = run.report()
        print(run.line(args.frames), flush=True)
    pooled = pool_seeds(runs, args, fps, tols)
    report["pooled"] = pooled.report()
    if pooled.judged is not None:
        report["verdict"] = _verdict_report(pooled.judged)
        md.append(pooled.row())
        v = pooled.judged["verdict"]
        print("verdict: " + ", ".join(f"{k}={v[k]}" for k in v), flush=True)
        md += _verdict_lines(pooled.judged, args)
    md += _cells_lines(pooled)
    report["precision"] = precision_report(pooled.scenes, args, fps, tols)
    md += _precision_lines(report["precision"])
    rates = _pass_rate_phrases(report["precision"])
    if rates:
        print("pass rate: " + "; ".join(rates), flush=True)
    if pooled.judged is not None:
        failed = not pooled.judged["verdict"]["ok"]
    else:
        failed = any(not r.whole["ok"] for r in runs)
    return report, "\n".join(md) + "\n", failed


__all__ = ["CalibrationOptions", "PooledRun", "SeedRun", "check_calibration", "pool_seeds", "precision_report",
           "run_seed", "simulated_scene_counts"]
