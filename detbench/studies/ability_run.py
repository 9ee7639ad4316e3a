"""The LiDAR detection-ability study fed from the simulator or a dataset on disk (tools/analyze.py's computation).

`run_ability(AbilityOptions(...))` streams frames (simulated: the simulator's exact per-box hit
counts, or full clouds with points=True; on disk: every height of each instant together) into an
AbilityStudy (detbench.studies.ability) and returns its report and the frame for the bird's-eye
figure; `summary_lines` is the terminal summary.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

from detbench.data.frame import DEFAULT_LANE_WIDTH, data_key, height_key, is_rig_key, key_heading
from detbench.data.regions import RANGE_NAMES
from detbench.studies.ability import DEFAULT_THRESHOLDS, AbilityStudy, ExampleFrames
from detbench.utils.cli import UserError


@dataclass
class AbilityOptions:
    """The study's settings (tools/analyze.py's arguments): a source (data or simulate), heights in metres."""

    data: str | None = None  # a dataset root on disk
    simulate: int | None = None  # or this many simulated instants
    heights: list[float] | None = None  # None: 0.5 1.0 1.8 simulated, every height of the dataset on disk
    seed: int = 0
    preset: str = "paper"
    overrides: list[str] = field(default_factory=list)
    frames_per_scene: int | None = None
    split: str = "all"
    lane_width: float | None = None
    thresholds: list[int] = field(default_factory=lambda: list(DEFAULT_THRESHOLDS))
    distance_bin: float = 10.0
    no_figures: bool = False
    example_frame: str | None = None
    points: bool = False
    example_window: int = 10
    skip_bad: bool = False
    bootstrap: int = 1000
    no_progress: bool = False


def _progress(iterable, total, desc, disable):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", disable=disable, smoothing=0.05)


def simulated_lidars(args: AbilityOptions) -> list:
    """The LiDAR presets of --heights (default 0.5 1.0 1.8); a bad height is the user's error."""
    from detbench.sim import lidar_preset

    try:
        return [lidar_preset(float(h)) for h in (args.heights or [0.5, 1.0, 1.8])]
    except ValueError as e:
        raise UserError(f"--heights: {e}") from None


def stream_simulator(args: AbilityOptions, study: AbilityStudy) -> dict:
    """Feed `study` from the simulator; returns the provenance dict.

    By default the simulator runs without points (`with_points=False`) and hands over its
    exact per-box hit counts (same rule and result as points_in_boxes with the 0.05 m
    lift); `--points` simulates full clouds and counts with points_in_boxes instead.
    """
    from detbench.data.layout import sim_calibration
    from detbench.sim import HighwaySimulator, load_sim_config

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


def simulated_example(args: AbilityOptions, cfg_source: dict):
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


def stream_dataset(args: AbilityOptions, study: AbilityStudy) -> dict:
    """Feed `study` from a dataset on disk (all heights of each instant together)."""
    from detbench.data import DatasetError, Height3Dataset, read_info
    from detbench.data.validate import points_frame_problem

    info = read_info(args.data)
    keys = [data_key(h) for h in args.heights] if args.heights else list(info.heights)
    datasets = [Height3Dataset(args.data, k, args.split, lane_width=args.lane_width) for k in keys]
    for ds in datasets:  # points in another frame than declared would shift every count of points in a box
        problem = points_frame_problem(ds)
        if problem:
            raise UserError(f"{ds.info_file}: {problem}")
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
        study.add(frames, keys=keys if any(is_rig_key(k) for k in keys) else None)  # a rig: under its name
    src = {"kind": "dataset", "root": str(args.data), "split": args.split, "heights": keys,
           "dataset_source": info.source}
    if isinstance(info.source, dict) and info.source.get("kind") == "simulator":
        from detbench.data.layout import sim_calibration

        src["calibration"] = sim_calibration(info.source)  # "v1" for a dataset.json without the id
    if skipped:
        src["skipped"] = skipped
        print(f"warning: skipped {len(skipped)} frame(s) with malformed files (listed in the JSON)", file=sys.stderr)
    return src


def empty_input_warnings(report: dict) -> list[str]:
    """What makes an LDR meaningless rather than low: a height with no labelled vehicle in any frame, or with
    vehicles but not one point inside any of them (empty or misread point files)."""
    out = []
    for h, ranges in report["heights"].items():
        cells = [ranges[r]["all"] for r in RANGE_NAMES]
        if not any(c["total"] for c in cells):
            out.append(f"{key_heading(h)}: no vehicle in any range of the {report['num_frames']} frame(s): every label "
                       f"file is empty or holds no vehicle box, so there is no LDR to report; check the labels")
        elif not any(c["detected"] for c in cells):
            out.append(f"{key_heading(h)}: not one point lies in any of the {max(c['total'] for c in cells)} vehicle "
                       f"box(es), so every LDR is 0.00; the point files are probably empty or misread (run "
                       f"tools/validate.py on the dataset)")
    return out


def run_ability(args: AbilityOptions) -> tuple[dict, ExampleFrames | None, float]:
    """Count every frame of the source at every height: (the report for ability.json, the frame for the
    bird's-eye figure or None, the seconds the counting took). UserError names the fix for a bad option."""
    if args.simulate is not None and args.simulate < 1:
        raise UserError("--simulate needs a positive number of frames")
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
    for w in empty_input_warnings(report):
        report.setdefault("warnings", []).append(w)
        print(f"warning: {w}", file=sys.stderr)
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
    return report, example, seconds


def dataset_split_check(args: AbilityOptions) -> tuple[dict, dict, dict]:
    """A dataset's test split against its train split (tools/analyze.py --compare-splits): (the comparison of
    detbench.studies.split_check, the train split's report, the test split's report). A test split that holds
    other traffic than the train split scores a detector on another world than it learned."""
    from dataclasses import replace

    from detbench.studies.split_check import compare_splits

    if args.data is None:
        raise UserError("--compare-splits needs --data ROOT (the splits of a dataset on disk)")
    reports = {}
    for split in ("train", "test"):
        reports[split], _, _ = run_ability(replace(args, split=split, no_figures=True))
    return compare_splits(reports["test"], reports["train"]), reports["train"], reports["test"]


def summary_lines(report: dict, seconds: float) -> list[str]:
    """A short summary for the terminal: LDR of all vehicles per range and height, and the sampling uncertainty."""
    lines = []
    heights = list(report["heights"])
    lines.append(f"{report['num_frames']} frames in {seconds:.1f} s; LDR of all vehicles (detected / total):")
    lines.append("range     " + "".join(f"{key_heading(h):>20}" for h in heights))
    for r in RANGE_NAMES:
        cells = [report["heights"][h][r]["all"] for h in heights]
        lines.append(f"{r:<10}" + "".join(f"{c['detected']:>9}/{c['total']:<6} {c['ldr']:.2f}" if c["total"] else
                                          f"{'-':>20}" for c in cells))
    unc = report["extras"]["uncertainty"]
    if unc["heights"] and unc["heights"][heights[0]]["large"]["all"]["ci95"] is not None:
        worst = max((unc["heights"][h][r]["all"]["ci95"][1] - unc["heights"][h][r]["all"]["ci95"][0]) / 2
                    for h in heights for r in RANGE_NAMES if unc["heights"][h][r]["all"]["ci95"] is not None)
        lines.append(f"sampling uncertainty ({unc['num_clusters']} {unc['clusters']}s, 95 % bootstrap): LDR within "
                     f"+-{worst:.3f} at worst (half-width of the interval; see ability.md)")
    else:
        lines.append("sampling uncertainty: not estimated (needs at least 2 scenes and --bootstrap > 0)")
    return lines


__all__ = ["AbilityOptions", "run_ability", "summary_lines"]
