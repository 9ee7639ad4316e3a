#!/usr/bin/env python3
"""Check the simulator's calibration against the paper's Table IV, per seed and per block.

For each seed, streams `--frames` frames of the simulator (hit counts only, as
`tools/analyze.py --simulate` does) at the paper's three heights and checks the issue's
criteria for all vehicles:
  1. every (range, height) LDR within +-`--tolerance` of Table IV;
  2. 1.8 m above both lower heights in every range;
  3. 0.5 m and 1.0 m within `--pair-tolerance` of each other in every range.
It checks the whole run and each block of `--block-frames` consecutive frames (a shorter
study, e.g. 2000 frames = 10 scenes), then the counts of all seeds pooled, and reports the scatter of one scene's LDR (standard
deviation across scenes) and the vehicles per frame against the paper's.

It also states the precision a study of a given length can have (`precision` in the JSON):
from the scene scatter s over all seeds, a block of n scenes is uncertain by about
+-1.96 s / sqrt(n) (95 %, normal approximation), and a cell whose pooled LDR is off the
paper by d needs about (1.96 s / (tolerance - d))^2 scenes for its block LDR to stay within
the tolerance 95 % of the time (per cell; all nine cells at once need more). And it estimates
directly how often a fresh study meets every criterion at once (`pass_rate`, per study
length: the block and the whole run), from 2000 studies whose scenes are resampled with
replacement from all seeds' scenes.

The statistics live in detbench/eval/calibration.py; this tool runs the simulator, parses
the arguments and writes the report.

Examples:
  python tools/check_calibration.py                       # seeds 0 1 2, 8000 frames, blocks of 2000
  python tools/check_calibration.py --seeds 0 --frames 2000 --block-frames 2000
  python tools/check_calibration.py --set traffic.density_per_km_lane=10 --strict

Writes OUT/calibration.json and OUT/calibration.md. LDR = detected / total (a fraction);
deviations are LDR differences; vehicles per frame are counts per frame; times are seconds.
With --strict the exit code is 1 when any whole run fails a criterion.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

# Not installed (run from a checkout): the repository root holds detbench and models.
if importlib.util.find_spec("detbench") is None or importlib.util.find_spec("models") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from detbench.config import ConfigError  # noqa: E402
from detbench.data.regions import RANGE_NAMES  # noqa: E402
from detbench.eval.calibration import (HEIGHTS, jsonable, ldr_grid, paper_arrays, pass_rates, precision,  # noqa: E402
                                       scene_counts, scene_ldr_std, study_runs, summarize)
from detbench.utils.io import atomic_write_json, atomic_write_text  # noqa: E402


def simulated_scene_counts(seed: int, frames: int, frames_per_scene: int, cfg: dict, progress: bool) -> np.ndarray:
    """Scene counts (scenes, 3, 4) of `frames` simulated instants at the paper's heights (hit counts, no points)."""
    from detbench.sim import HighwaySimulator, lidar_preset

    lidars = [lidar_preset(float(h)) for h in HEIGHTS]
    steps = HighwaySimulator(cfg, seed).run(frames, lidars, frames_per_scene=frames_per_scene, with_points=False)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, total=frames, desc=f"seed {seed}", unit="frame", leave=False)
    return scene_counts(steps)


def _md_row(seed: str, name: str, frames: int, res: dict) -> str:
    worst = res["worst_abs_deviation"]
    return (f"| {seed} | {name} ({frames}) | "
            + " | ".join(" / ".join(f"{v:.3f}" for v in res["ldr"][i]) for i in range(3))
            + f" | {'-' if worst is None else f'{worst:.3f}'} | "
            + " / ".join(f"{v:.2f}" for v in res["vehicles_per_frame"].values())
            + f" | {'yes' if res['ok'] else 'no'} |")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description="Check the simulator's LiDAR detection rates against the paper's "
                                             "Table IV, per seed and per block of frames.",
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="simulator seeds (default 0 1 2)")
    ap.add_argument("--frames", type=int, default=8000, help="frames per seed (default 8000, the paper's)")
    ap.add_argument("--block-frames", type=int, default=2000,
                    help="also check each block of this many consecutive frames (default 2000; 0 = no blocks); "
                         "a multiple of the frames per scene")
    ap.add_argument("--frames-per-scene", type=int, default=None, help="frames per scene (default: the preset's, 200)")
    ap.add_argument("--tolerance", type=float, default=0.05, help="allowed |LDR - Table IV| (default 0.05)")
    ap.add_argument("--pair-tolerance", type=float, default=0.03,
                    help="allowed |LDR(0.5 m) - LDR(1.0 m)| in each range (default 0.03)")
    ap.add_argument("--preset", default="paper", help="simulator preset from configs/sim.yaml (default paper)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator config override, repeatable")
    ap.add_argument("--out", default="runs/check_calibration", help="output folder for the JSON and Markdown")
    ap.add_argument("--strict", action="store_true", help="exit with 1 when any whole run fails a criterion")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from detbench.sim import load_sim_config

    if args.frames <= 0 or args.block_frames < 0:
        print("error: --frames must be > 0 and --block-frames >= 0", file=sys.stderr)
        return 2
    try:
        cfg = load_sim_config(args.preset, overrides=tuple(args.overrides))
    except (ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    fps = int(args.frames_per_scene or cfg["scene"]["frames_per_scene"])
    if args.block_frames and args.block_frames % fps:
        print(f"error: --block-frames {args.block_frames} must be a multiple of the frames per scene ({fps}); "
              f"set --frames-per-scene or change --block-frames", file=sys.stderr)
        return 2
    paper_ldr, paper_pf = paper_arrays()
    report = {"preset": args.preset, "overrides": list(args.overrides), "frames": args.frames,
              "frames_per_scene": fps, "block_frames": args.block_frames, "tolerance": args.tolerance,
              "pair_tolerance": args.pair_tolerance, "units": {"ldr": "fraction detected / total",
                                                               "vehicles_per_frame": "count per frame",
                                                               "seconds": "wall-clock s"},
              "paper": {"ldr": ldr_grid(paper_ldr),
                        "vehicles_per_frame": {r: round(float(v), 3) for r, v in zip(RANGE_NAMES, paper_pf)}},
              "seeds": {}}
    md = [f"# Simulator calibration against Table IV ({args.preset} preset)", "",
          f"{args.frames} frames per seed, scenes of {fps} frames, blocks of {args.block_frames} frames; "
          f"criteria: every |LDR - paper| <= {args.tolerance}, 1.8 m above both lower heights, "
          f"|LDR(0.5) - LDR(1.0)| <= {args.pair_tolerance}. LDR is a fraction; vehicles per frame a count.", "",
          "| seed | run | LDR small 0.5/1.0/1.8 | moderate | large | worst abs dev | veh/frame s/m/l | ok |",
          "| --- | --- | --- | --- | --- | --- | --- | --- |",
          "| paper | 8000 | " + " | ".join(" / ".join(f"{v:.2f}" for v in paper_ldr[i]) for i in range(3))
          + " | - | " + " / ".join(f"{v:.2f}" for v in paper_pf) + " | - |"]
    any_fail = False
    all_scenes = []
    for seed in args.seeds:
        t0 = time.perf_counter()
        S = simulated_scene_counts(seed, args.frames, fps, cfg, not args.no_progress)
        all_scenes.append(S)
        secs = time.perf_counter() - t0
        runs = study_runs(S, args.frames, fps, args.block_frames)
        seed_rep = {"seconds": round(secs, 1), "runs": {}, "scene_ldr_std": scene_ldr_std(S)}
        for name, block, nf in runs:
            res = summarize(block, nf, args.tolerance, args.pair_tolerance)
            seed_rep["runs"][name] = jsonable(res)
            if name == "all" and not res["ok"]:
                any_fail = True
            md.append(_md_row(str(seed), name, nf, res))
        report["seeds"][str(seed)] = seed_rep
        summary = seed_rep["runs"]["all"]
        worst = summary["worst_abs_deviation"]
        shown = None if worst is None else round(worst, 3)
        print(f"seed {seed}: {args.frames} frames in {secs:.0f} s, worst |dLDR| {shown}, "
              f"ok={summary['ok']}; blocks ok: "
              f"{sum(r['ok'] for k, r in seed_rep['runs'].items() if k != 'all')}/{len(runs) - 1}", flush=True)
    if len(args.seeds) > 1:
        pooled_frames = args.frames * len(args.seeds)
        res = summarize(np.concatenate(all_scenes), pooled_frames, args.tolerance, args.pair_tolerance)
        report["pooled"] = {"seeds": list(args.seeds), "frames": pooled_frames, **jsonable(res)}
        md.append(_md_row("pooled", "all seeds", pooled_frames, res))
        print(f"pooled over seeds {' '.join(map(str, args.seeds))}: worst |dLDR| "
              f"{None if res['worst_abs_deviation'] is None else round(res['worst_abs_deviation'], 3)}, "
              f"ok={res['ok']}", flush=True)
    scenes = np.concatenate(all_scenes)
    prec = precision(scenes, paper_ldr, args.tolerance, args.block_frames // fps if args.block_frames else None)
    # how often a fresh study meets the criteria, at the block length and at the run length (resampled scenes)
    study_frames = [args.frames] + ([args.block_frames] if args.block_frames else [])
    prec["pass_rate"] = pass_rates(scenes, study_frames, fps, args.tolerance, args.pair_tolerance)
    report["precision"] = prec
    hw = prec["half_width_95_at_block"]
    need = [v for r in RANGE_NAMES for v in prec["scenes_needed"][r].values()]
    need_txt = "more than any finite study (a pooled LDR is off by the tolerance or more)" if None in need \
        else f"{min(need)}-{max(need)} scenes per cell"
    if hw is not None:
        vals = [v for r in RANGE_NAMES for v in hw[r].values() if v is not None]
        print(f"precision: one scene's LDR scatters by {prec['scene_std_range'][0]:.3f}-{prec['scene_std_range'][1]:.3f}; "
              f"a block of {prec['scenes_per_block']} scenes is uncertain by +-{min(vals):.3f} to +-{max(vals):.3f} "
              f"(95 %); staying within +-{args.tolerance} 95 % of the time needs {need_txt}", flush=True)
    rates = [f"a study of {r['scenes_per_block']} scenes ({f} frames) meets every criterion {100 * r['ok']:.0f} % "
             f"of the time (+-{args.tolerance} alone: {100 * r['within']:.0f} %)"
             for f, r in prec["pass_rate"].items() if r["ok"] is not None]
    rate_txt = None
    if rates:
        reps = max(r["replicates"] for r in prec["pass_rate"].values())
        rate_txt = "; ".join(rates) + f" ({reps} studies resampled from {prec['scenes']} scenes)"
        print(f"pass rate: {rate_txt}", flush=True)
    md += ["", f"Precision (all seeds' scenes): one scene's LDR scatters by {prec['scene_std_range'][0]:.3f}-"
               f"{prec['scene_std_range'][1]:.3f} (std across scenes)"
               + (f"; a block of {prec['scenes_per_block']} scenes is uncertain by about +-1.96 std / "
                  f"sqrt({prec['scenes_per_block']}) (95 %)" if hw is not None else "")
               + f"; to keep a cell within +-{args.tolerance} of the paper 95 % of the time, given its pooled "
                 f"offset from the paper, needs {need_txt}."
               + (f" Estimated from the scenes directly: {rate_txt}." if rate_txt else ""), "",
           "| range | scenes needed 0.5 / 1.0 / 1.8 m | 95 % half-width of a block 0.5 / 1.0 / 1.8 m |",
           "| --- | --- | --- |"]
    for r in RANGE_NAMES:
        nd = " / ".join("-" if prec["scenes_needed"][r][h] is None else str(prec["scenes_needed"][r][h])
                        for h in HEIGHTS)
        hh = "-" if hw is None else " / ".join("-" if hw[r][h] is None else f"{hw[r][h]:.3f}" for h in HEIGHTS)
        md.append(f"| {r} | {nd} | {hh} |")
    md += ["", "Scatter of one scene's LDR (standard deviation across scenes, small / moderate / large at "
               "0.5 / 1.0 / 1.8 m):", ""]
    for seed, rep in report["seeds"].items():
        std = rep["scene_ldr_std"]
        cells = ["{} {}".format(r, " / ".join("-" if std[r][h] is None else f"{std[r][h]:.3f}" for h in HEIGHTS))
                 for r in RANGE_NAMES]
        md.append(f"- seed {seed}: " + "; ".join(cells))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "calibration.json", report)
    atomic_write_text(out / "calibration.md", "\n".join(md) + "\n")
    print(f"wrote {out / 'calibration.json'}, {out / 'calibration.md'}")
    return 1 if (args.strict and any_fail) else 0


if __name__ == "__main__":
    sys.exit(main())
