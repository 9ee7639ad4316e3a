#!/usr/bin/env python3
"""LiDAR detection-ability study (the Height3 paper's Section IV) on a dataset or a simulator stream.

How many of the vehicles around the car does a LiDAR at each mounting height hit? A vehicle
counts as LiDAR-detected when at least one point lies inside its box with the box bottom
raised by 0.05 m; LDR = detected / total, by range (small/moderate/large) and importance
level (all/top3/top6).

Examples:
  python tools/analyze.py --simulate 8000 --heights 0.5 1.0 1.8 --seed 0 --out runs/ability
  python tools/analyze.py --data data/sim --split all --out runs/ability_disk
  python tools/analyze.py --simulate 2000 --rigs paper-1.8 forehead headlights --small-objects --out runs/rigs

Writes OUT/ability.json (or --json PATH), OUT/ability.md (tables like the paper's Tables
IV-VI) and PNG figures (Fig. 5-7 and LDR against distance) into OUT.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.data.regions import RANGES
from detbench.studies.ability import DEFAULT_THRESHOLDS
from detbench.studies.ability_tables import ability_markdown
from detbench.studies.ability_run import AbilityOptions, dataset_split_check, run_ability, summary_lines
from detbench.studies.split_check import split_check_markdown, split_check_warnings
from detbench.data.frame import data_key, height_or_rig_arg
from detbench.utils.cli import (
    add_sim_preset_argument, check_out_dir, claim_output, output_folder, require, require_distinct, run_main,
)
from detbench.utils.report_folders import ABILITY_FOLDER
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description="LiDAR detection-ability study: total and LiDAR-detected vehicles per mounting height, "
                    "range and importance level (Height3 paper, Section IV).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Ranges by box centre (m): "
               + "; ".join(f"{r} {x0:g}<=x<={x1:g} |y|<={ym:g}" for r, (x0, x1, ym) in RANGES.items())
               + ".\nTop3/Top6: the 1/2 nearest vehicles in each of the ego, left and right lanes.\n"
               "Writes OUT/ability.json (machine-readable), ability.md and the PNG figures. Units: LDR = detected / "
               "total, a fraction in [0, 1]; Number = vehicles summed over frames; heights, ranges and distances "
               "in metres.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", metavar="ROOT", help="a dataset on disk in the detbench layout (docs/data-format.md)")
    src.add_argument("--simulate", type=int, metavar="N",
                     help="stream N frames (instants; each at every height) from the built-in highway simulator, "
                          "nothing is written to disk but the results")
    ap.add_argument("--heights", type=height_or_rig_arg, nargs="+", default=None, metavar="H",
                    help="LiDAR mounting heights in metres (default: 0.5 1.0 1.8 for --simulate, every height of "
                         "the dataset for --data); with --data also the name of a rig the dataset holds "
                         "(tools/simulate.py --rigs), counted on its merged points")
    ap.add_argument("--rigs", nargs="+", default=None, metavar="NAME",
                    help="(--simulate) LiDAR rigs by name instead of heights (configs/rigs.yaml or --rig-file): "
                         "their LDR cells, ground blind zone, rays taken by the ego's body and near-field LDR by "
                         "distance and bearing, all rigs on the same instants; writes no figures")
    ap.add_argument("--rig-file", default=None, metavar="PATH",
                    help="(--rigs) a rig file with the keys of configs/rigs.yaml (default configs/rigs.yaml)")
    ap.add_argument("--small-objects", action="store_true",
                    help="(--rigs) place the small-object probe (cones, lost tyres, child-sized boxes) on the "
                         "carriageway and shoulder and report their LDR and points per object by distance")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (--simulate; default 0)")
    add_sim_preset_argument(ap)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator config override, repeatable (e.g. --set traffic.density_per_km_lane=25)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per simulated scene at 2 Hz (default: the --sim-preset's, 200 as in the paper)")
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
    ap.add_argument("--compare-splits", action="store_true",
                    help="(--data) also count the train and test splits apart and compare the test split's vehicles "
                         "per frame and LDR with the train split's (OUT/split_check.md, .json); a warning names each "
                         "cell whose difference exceeds both splits' sampling noise")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def check_arguments(args: argparse.Namespace) -> None:
    """UserError for a value the study cannot use, before any frame is read or simulated."""
    for h in args.heights or ():
        if isinstance(h, str):
            require(args.data is not None, f"--heights {h}: a rig's name goes with --data (a dataset simulated with "
                                           f"the rig); to simulate rigs give --simulate N --rigs {h}")
        else:
            require(math.isfinite(h) and h > 0, f"--heights {h:g}: a mounting height is a positive number of metres")
    require_distinct(args.heights, "--heights", key=data_key, what="height")
    require(args.rigs is None or args.simulate is not None, "--rigs needs --simulate N (rigs are simulated)")
    require(args.rigs is None or args.heights is None, "--rigs and --heights: give one of them")
    require(args.rig_file is None or args.rigs is not None, "--rig-file needs --rigs NAME [NAME ...]")
    require(not args.small_objects or args.rigs is not None, "--small-objects needs --rigs NAME [NAME ...]")
    require(args.rigs is None or not (args.points or args.example_frame),
            "--points and --example-frame: not with --rigs (rigs count with the simulator's hit counts, no figures)")
    require(args.lane_width is None or (math.isfinite(args.lane_width) and args.lane_width > 0),
            f"--lane-width {args.lane_width}: must be a positive number of metres (e.g. 3.5)")
    require(math.isfinite(args.distance_bin) and args.distance_bin > 0,
            f"--distance-bin {args.distance_bin:g}: must be a positive number of metres (e.g. 10)")
    require(args.bootstrap >= 0, f"--bootstrap {args.bootstrap}: must be an integer >= 0 (0 = no intervals)")
    require(args.example_window >= 1, f"--example-window {args.example_window}: must be an integer >= 1")
    require(args.frames_per_scene is None or args.frames_per_scene >= 1,
            f"--frames-per-scene {args.frames_per_scene}: must be an integer >= 1")
    out = output_folder(args.out, ABILITY_FOLDER)
    if args.json:
        check_out_dir(Path(args.json).parent, "--json")
        require(not Path(args.json).is_dir(), f"--json {args.json}: is a folder; give a file path, e.g. "
                                              f"{out / 'ability.json'}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    check_arguments(args)
    if args.rigs is not None:
        return main_rigs(args)
    opts = AbilityOptions(
        data=args.data, simulate=args.simulate, heights=args.heights, seed=args.seed, preset=args.sim_preset,
        overrides=args.overrides, frames_per_scene=args.frames_per_scene, split=args.split,
        lane_width=args.lane_width, thresholds=args.thresholds, distance_bin=args.distance_bin,
        no_figures=args.no_figures, example_frame=args.example_frame, points=args.points,
        example_window=args.example_window, skip_bad=args.skip_bad, bootstrap=args.bootstrap,
        no_progress=args.no_progress)
    report, example, seconds = run_ability(opts)
    with claim_output(args.out, ABILITY_FOLDER) as out:
        written = write_ability(args, opts, out, report, example)
    print("\n".join(summary_lines(report, seconds)))
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def main_rigs(args: argparse.Namespace) -> int:
    """--rigs: the ability study per rig (detbench.studies.rig_ability), OUT/ability.json and ability.md."""
    from detbench.studies.rig_ability import RigAbilityOptions, rig_markdown, run_rig_ability

    opts = RigAbilityOptions(
        simulate=args.simulate, rigs=args.rigs, rig_file=args.rig_file, seed=args.seed, preset=args.sim_preset,
        overrides=args.overrides, frames_per_scene=args.frames_per_scene, thresholds=args.thresholds,
        distance_bin=args.distance_bin, bootstrap=args.bootstrap, small_objects=args.small_objects,
        no_progress=args.no_progress)
    report, seconds = run_rig_ability(opts)
    with claim_output(args.out, ABILITY_FOLDER) as out:
        json_path = Path(args.json) if args.json else out / "ability.json"
        atomic_write_json(json_path, report)
        atomic_write_text(out / "ability.md", rig_markdown(report))
    print(f"{report['num_frames']} frames in {seconds:.1f} s; LDR of all vehicles and ground blind zone ahead:")
    for name, cell in report["rigs"].items():
        ahead = cell["blind_zone_m"]["ahead"]
        print(f"{name:<16}" + "".join(f"{r} {cell[r]['all']['ldr']:.2f}  " if cell[r]["all"]["total"] else f"{r} -  "
                                      for r in RANGES) + f"blind ahead {'-' if ahead is None else f'{ahead:.2f} m'}")
    print("wrote: " + ", ".join(str(p) for p in (json_path, out / "ability.md")))
    return 0


def write_ability(args: argparse.Namespace, opts: AbilityOptions, out: Path, report: dict, example) -> list[Path]:
    """Write the report, its figures and (--compare-splits) the split check into `out`; the paths written."""
    json_path = Path(args.json) if args.json else out / "ability.json"
    atomic_write_json(json_path, report)
    atomic_write_text(out / "ability.md", ability_markdown(report))
    written = [json_path, out / "ability.md"]
    if not args.no_figures:
        from detbench.studies.ability_plots import save_ability_figures

        written += list(save_ability_figures(report, out, example).values())
    if args.compare_splits:
        result, train_rep, test_rep = dataset_split_check(opts)
        atomic_write_json(out / "split_check.json", {"comparison": result, "train": train_rep, "test": test_rep})
        atomic_write_text(out / "split_check.md", "\n".join(
            ["# The test split against the train split", "",
             f"*Data: {args.data}; {train_rep['num_frames']} train and {test_rep['num_frames']} test frames.*", "",
             *split_check_markdown(result, "test split", "train split"), ""]))
        written += [out / "split_check.json", out / "split_check.md"]
        for line in split_check_warnings(result, "test split", "train split"):
            print(line, file=sys.stderr)
    return written


if __name__ == "__main__":
    sys.exit(run_main(main))
