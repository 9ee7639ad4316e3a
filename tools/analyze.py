#!/usr/bin/env python3
"""LiDAR detection-ability study (the Height3 paper's Section IV) on a dataset or a simulator stream.

How many of the vehicles around the car does a LiDAR at each mounting height hit? A vehicle
counts as LiDAR-detected when at least one point lies inside its box with the box bottom
raised by 0.05 m; LDR = detected / total, by range (small/moderate/large) and importance
level (all/top3/top6).

Examples:
  python tools/analyze.py --simulate 8000 --heights 0.5 1.0 1.8 --seed 0 --out runs/ability
  python tools/analyze.py --data data/sim --split all --out runs/ability_disk

Writes OUT/ability.json (or --json PATH), OUT/ability.md (tables like the paper's Tables
IV-VI) and PNG figures (Fig. 5-7 and LDR against distance) into OUT.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

from detbench.data.frame import DEFAULT_LANE_WIDTH, height_key  # noqa: E402
from detbench.data.regions import RANGE_NAMES  # noqa: E402
from detbench.eval.ability import DEFAULT_THRESHOLDS, AbilityStudy, ability_markdown  # noqa: E402
from detbench.utils.cli import UserError, run_main  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description="LiDAR detection-ability study: total and LiDAR-detected vehicles per mounting height, "
                    "range and importance level (Height3 paper, Section IV).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Ranges by box centre (m): small 0<=x<=50 |y|<=5; moderate 0<=x<=100 |y|<=10; large 0<=x<=150 "
               "|y|<=15.\nTop3/Top6: the 1/2 nearest vehicles in each of the ego, left and right lanes.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", metavar="ROOT", help="a dataset on disk in the detbench layout (docs/data-format.md)")
    src.add_argument("--simulate", type=int, metavar="N",
                     help="stream N frames (instants; each at every height) from the built-in highway simulator, "
                          "nothing is written to disk but the results")
    ap.add_argument("--heights", type=float, nargs="+", default=None, metavar="H",
                    help="LiDAR mounting heights in metres (default: 0.5 1.0 1.8 for --simulate, every height of "
                         "the dataset for --data)")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (--simulate; default 0)")
    ap.add_argument("--preset", default="paper", help="simulator preset from configs/sim.yaml (default: paper)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator config override, repeatable (e.g. --set traffic.density_per_km_lane=25)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per simulated scene at 2 Hz (default: the preset's, 200 as in the paper)")
    ap.add_argument("--split", choices=("train", "test", "all"), default="all",
                    help="dataset split to analyse (--data; default all, as the paper's Table IV)")
    ap.add_argument("--lane-width", type=float, default=None,
                    help="lane width in metres for datasets without lane ids (default: dataset.json's, 3.5)")
    ap.add_argument("--thresholds", type=int, nargs="+", default=list(DEFAULT_THRESHOLDS),
                    help="minimum points inside a box to count it detected; the first must be 1 (the paper's "
                         "rule), the others are extras (default: 1 5 10)")
    ap.add_argument("--distance-bin", type=float, default=10.0,
                    help="bin width in metres of LDR against distance (default 10)")
    ap.add_argument("--out", default="runs/ability", help="output folder for Markdown and PNG (default runs/ability)")
    ap.add_argument("--json", default=None, metavar="PATH", help="JSON results path (default OUT/ability.json)")
    ap.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    ap.add_argument("--example-frame", default=None, metavar="ID",
                    help="frame id for the bird's-eye figure (default: the instant where heights differ most)")
    ap.add_argument("--points", action="store_true",
                    help="(--simulate) simulate full point clouds and count with detbench.ops.points_in_boxes "
                         "(slower; by default the simulator skips the points and hands over its exact per-box "
                         "hit counts, which are the same numbers)")
    ap.add_argument("--example-window", type=int, default=10, metavar="K",
                    help="(--simulate without --points) the bird's-eye figure shows one of the first K instants, "
                         "re-simulated with points (default 10)")
    ap.add_argument("--skip-bad", action="store_true",
                    help="(--data) skip instants with a malformed file at any height and list them in the JSON, "
                         "instead of stopping at the first")
    ap.add_argument("--bootstrap", type=int, default=1000, metavar="B",
                    help="replicates of the scene bootstrap behind the 95 %% intervals in the report (default 1000; "
                         "0 = no intervals). Scenes, not frames, are resampled: frames of a scene are correlated")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def _progress(iterable, total, desc, disable):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", disable=disable, smoothing=0.05)


def simulated_lidars(args) -> list:
    """The LiDAR presets of --heights (default 0.5 1.0 1.8); a bad height is the user's error."""
    from detbench.sim import lidar_preset

    try:
        return [lidar_preset(float(h)) for h in (args.heights or [0.5, 1.0, 1.8])]
    except ValueError as e:
        raise UserError(f"--heights: {e}") from None


def stream_simulator(args, study: AbilityStudy) -> dict:
    """Feed `study` from the simulator; returns the provenance dict.

    By default the simulator runs without points (`with_points=False`) and hands over its
    exact per-box hit counts (same rule and result as points_in_boxes with the 0.05 m
    lift); `--points` simulates full clouds and counts with points_in_boxes instead.
    """
    from detbench.sim import HighwaySimulator, load_sim_config
    from detbench.sim.dataset import sim_calibration

    heights = args.heights or [0.5, 1.0, 1.8]
    cfg = load_sim_config(args.preset, overrides=tuple(args.overrides))
    lift = float(cfg["output"]["count_bottom_lift_m"])
    if not args.points and abs(lift - study.bottom_lift) > 1e-12:
        raise UserError(f"the simulator counts with a {lift} m bottom lift but the study uses "
                        f"{study.bottom_lift} m; drop the output.count_bottom_lift_m override or pass --points")
    lidars = simulated_lidars(args)
    fps = args.frames_per_scene if args.frames_per_scene is not None else int(cfg["scene"]["frames_per_scene"])
    sim = HighwaySimulator(cfg, seed=args.seed)
    stream = sim.run(args.simulate, lidars, frames_per_scene=fps, with_points=args.points)
    for frames in _progress(stream, args.simulate, "simulate+count", args.no_progress):
        if args.points:
            study.add(frames)
        else:
            study.add(frames, counts=[f.hit_counts for f in frames])
    return {"kind": "simulator", "preset": args.preset, "calibration": sim_calibration(cfg), "seed": args.seed,
            "frames": args.simulate,
            "overrides": list(args.overrides), "frames_per_scene": fps,
            "counting": "points_in_boxes on full clouds" if args.points else "simulator hit counts (no points)",
            "heights": [height_key(h) for h in heights], "lidars": [lid.sensor.to_dict() for lid in lidars],
            "sim_timings_s": {k: round(v, 2) for k, v in sim.timings.items()}}


def simulated_example(args, cfg_source: dict):
    """Re-simulate the first instants with points and pick the one for the bird's-eye figure.

    Scenes are seeded independently of the run length, so the first `--example-window`
    instants of a short run with points are exactly the first instants of the main run.
    """
    from detbench.sim import HighwaySimulator, load_sim_config

    cfg = load_sim_config(args.preset, overrides=tuple(args.overrides))
    lidars = simulated_lidars(args)
    n = min(args.simulate, args.example_window)
    picker = AbilityStudy(keep_example=True, example_frame_id=args.example_frame,
                          bottom_lift=float(cfg["output"]["count_bottom_lift_m"]))
    sim = HighwaySimulator(cfg, seed=args.seed)
    for frames in sim.run(n, lidars, frames_per_scene=cfg_source["frames_per_scene"], with_points=True):
        picker.add(frames, counts=[f.hit_counts for f in frames])
        if args.example_frame and frames[0].frame_id == args.example_frame:
            break
    return picker.example_frames()


def stream_dataset(args, study: AbilityStudy) -> dict:
    """Feed `study` from a dataset on disk (all heights of each instant together)."""
    from detbench.data import DatasetError, Height3Dataset, read_info

    info = read_info(args.data)
    keys = [height_key(h) for h in args.heights] if args.heights else list(info.heights)
    datasets = [Height3Dataset(args.data, k, args.split, lane_width=args.lane_width) for k in keys]
    ids = datasets[0].frame_ids
    if not ids:
        raise UserError(f"{args.data}: the {args.split!r} split lists no frames; try --split all")
    skipped = []
    for fid in _progress(ids, len(ids), "read+count", args.no_progress):
        try:
            frames = [ds.load(fid) for ds in datasets]
        except (DatasetError, FileNotFoundError) as e:
            if not args.skip_bad:
                raise UserError(f"{e} (fix the file, or pass --skip-bad to skip such frames)") from None
            skipped.append(str(e))
            continue
        study.add(frames)
    src = {"kind": "dataset", "root": str(args.data), "split": args.split, "heights": keys,
           "dataset_source": info.source}
    if isinstance(info.source, dict) and info.source.get("kind") == "simulator":
        from detbench.sim.dataset import sim_calibration

        src["calibration"] = sim_calibration(info.source)  # "v1" for datasets written before the id existed
    if skipped:
        src["skipped"] = skipped
        print(f"warning: skipped {len(skipped)} frame(s) with malformed files (listed in the JSON)", file=sys.stderr)
    return src


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.simulate is not None and args.simulate < 1:
        raise UserError("--simulate needs a positive number of frames")
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "ability.json"
    lane_width = args.lane_width if args.lane_width is not None else DEFAULT_LANE_WIDTH
    sim_counts = args.simulate is not None and not args.points
    try:
        study = AbilityStudy(thresholds=args.thresholds, distance_bin=args.distance_bin, lane_width=lane_width,
                             keep_example=not args.no_figures and not sim_counts,
                             example_frame_id=args.example_frame, bootstrap=args.bootstrap)
    except ValueError as e:
        raise UserError(str(e)) from None
    t0 = time.perf_counter()
    from detbench.config import ConfigError
    from detbench.data import DatasetError

    try:
        source = stream_simulator(args, study) if args.simulate is not None else stream_dataset(args, study)
    except (ConfigError, DatasetError, FileNotFoundError) as e:
        raise UserError(str(e)) from None
    seconds = time.perf_counter() - t0
    report = study.report(source=source)
    report["extras"]["run"] = {"seconds": round(seconds, 2),
                               "frames_per_second": round(study.num_frames / seconds, 1) if seconds > 0 else None}
    example = None
    if not args.no_figures:
        example = simulated_example(args, source) if sim_counts else study.example_frames()
        if args.example_frame and example is None:
            print(f"warning: --example-frame {args.example_frame} was not among the frames"
                  f"{' searched (the first --example-window instants)' if sim_counts else ''}; "
                  f"no bird's-eye figure", file=sys.stderr)
    report["extras"]["example_frame"] = None if example is None else example.frame_id
    atomic_write_json(json_path, report)
    atomic_write_text(out / "ability.md", ability_markdown(report))
    written = [json_path, out / "ability.md"]
    if not args.no_figures:
        from detbench.eval.ability_plots import save_ability_figures

        written += list(save_ability_figures(report, out, example).values())
    # a short summary on the terminal: LDR of all vehicles per range and height
    heights = list(report["heights"])
    print(f"{report['num_frames']} frames in {seconds:.1f} s; LDR of all vehicles (detected / total):")
    print("range     " + "".join(f"{h + ' m':>20}" for h in heights))
    for r in RANGE_NAMES:
        cells = [report["heights"][h][r]["all"] for h in heights]
        print(f"{r:<10}" + "".join(f"{c['detected']:>9}/{c['total']:<6} {c['ldr']:.2f}" if c["total"] else
                                   f"{'-':>20}" for c in cells))
    unc = report["extras"]["uncertainty"]
    if unc["heights"] and unc["heights"][heights[0]]["large"]["all"]["ci95"] is not None:
        worst = max((unc["heights"][h][r]["all"]["ci95"][1] - unc["heights"][h][r]["all"]["ci95"][0]) / 2
                    for h in heights for r in RANGE_NAMES if unc["heights"][h][r]["all"]["ci95"] is not None)
        print(f"sampling uncertainty ({unc['num_clusters']} {unc['clusters']}s, 95 % bootstrap): LDR within "
              f"+-{worst:.3f} at worst (half-width of the interval; see ability.md)")
    else:
        print("sampling uncertainty: not estimated (needs at least 2 scenes and --bootstrap > 0)")
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
