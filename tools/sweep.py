#!/usr/bin/env python3
"""Height sweep: which mounting height, for my LiDAR? LDR and training-free placement scores for many heights.

One sensor (a Table I / II preset, changed with --set sensor.KEY=VALUE) at every height of
--heights (default 0.3 to 2.2 m in 0.1 m steps) sees the same simulated traffic: each instant
is simulated once and ray-cast once per height. Reported per height: LDR by range and
importance level (the paper's Tables IV-VI, heights as rows) and against distance, with 95 %
intervals from a bootstrap over scenes; the placement scores of detbench.eval.placement
(evidence per LiDAR-detected vehicle, S-MIG of Hu et al. 2022); and, given report.json files
of detectors trained and tested at several heights, the rank correlation of every score with
their recall and AP@R40 (Spearman, Kendall, intervals, and where the score fails).

Examples:
  python tools/sweep.py --frames 8000 --out runs/sweep                      # 20 heights, h3-1.0 sensor
  python tools/sweep.py --frames 2000 --lidar xpeng-g9 --heights 0.4 0.6 0.8 1.0 1.4 1.8
  python tools/sweep.py --frames 2000 --set sensor.channels=64 --set traffic.density_per_km_lane=20
  python tools/sweep.py --from-json runs/sweep/sweep.json --out runs/sweep \\
      --detector-reports runs/study_cpu/second_h*/eval_*/report.json

Writes OUT/sweep.json (or --json PATH), OUT/sweep.md and the figures OUT/ldr_vs_height.png,
OUT/scores_vs_height.png, OUT/ldr_distance_map.png. Heights in metres; LDR, evidence and
correlations are fractions or coefficients in [-1, 1]; S-MIG in bits; times in seconds.
"""
from __future__ import annotations

import argparse
import dataclasses
import difflib
import os
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

from detbench import runtime  # noqa: E402,F401  (first detbench import: thread-runtime defaults before numba starts)
from detbench.data.frame import height_key  # noqa: E402
from detbench.data.regions import RANGE_NAMES  # noqa: E402
from detbench.utils.cli import UserError, run_main  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text, read_json  # noqa: E402

DEFAULT_HEIGHTS = [round(0.3 + 0.1 * i, 1) for i in range(20)]  # 0.3 ... 2.2 m
DEFAULT_LIDAR = "h3-1.0"
PAPER_SENSORS = "paper"  # --lidar paper: lidar_preset(height) per height, as the training datasets
_NOT_SETTABLE = {"height", "name"}


def build_parser() -> argparse.ArgumentParser:
    doc = __doc__.split("\n\n")
    ap = argparse.ArgumentParser(description=doc[0], epilog="\n\n".join(doc[1:]),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8000, help="instants to simulate (each at every height; default 8000)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per scene at 2 Hz (default: the simulator preset's, 200 as in the paper); scenes are "
                         "the units of the bootstrap")
    ap.add_argument("--heights", type=float, nargs="+", default=None, metavar="H",
                    help="mounting heights in metres (default 0.3 0.4 ... 2.2)")
    ap.add_argument("--lidar", default=DEFAULT_LIDAR,
                    help="sensor preset, the same at every height: h3-0.5 / h3-1.0 / h3-1.8 (the paper's Table II; "
                         "h3-1.8 is pitched down 2.5 deg) or a Table I model (ideal-l8, aito-m5, xpeng-g9, neta-s, "
                         "arcfox-as-hi, avatr-3). Default h3-1.0 (128 x 480 rays, -12.5..12.5 deg, 180 deg, 150 m, "
                         "level). 'paper': the sensors the training datasets use at each height (Table II at 0.5, 1.0 "
                         "and 1.8 m, so 1.8 m is pitched; the 1.0 m one elsewhere): use it to correlate with "
                         "detectors trained on detbench's simulated datasets")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override, repeatable: sensor.FIELD=VALUE changes the sensor (e.g. sensor.channels=64, "
                         "sensor.pitch_deg=2.5, sensor.vfov_deg=[-15,10]); any other key is a simulator config key "
                         "(configs/sim.yaml, e.g. traffic.density_per_km_lane=20)")
    ap.add_argument("--preset", default="paper", help="simulator preset from configs/sim.yaml (default paper)")
    ap.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    ap.add_argument("--bootstrap", type=int, default=1000, metavar="B",
                    help="replicates of the scene bootstrap behind the 95 %% intervals (default 1000; 0 = none)")
    ap.add_argument("--distance-bin", type=float, default=10.0, help="metres per bin of LDR against distance (10)")
    ap.add_argument("--evidence-scale", type=float, default=None, metavar="N0",
                    help="points at which a vehicle holds 63 %% of full evidence, q(n) = 1 - exp(-n / N0) (default 10)")
    ap.add_argument("--voxel", type=float, default=0.5, help="S-MIG voxel size in metres (default 0.5)")
    ap.add_argument("--no-smig", action="store_true", help="skip S-MIG (the occupancy grid and the ray coverage)")
    ap.add_argument("--detector-reports", nargs="+", default=None, metavar="REPORT",
                    help="tools/eval.py report.json files of detectors trained and tested at heights of the sweep "
                         "(cross-height reports are skipped): every score is rank-correlated with their recall and "
                         "AP@R40 per range and level")
    ap.add_argument("--correlation-replicates", type=int, default=2000, metavar="B",
                    help="bootstrap replicates of the rank-correlation intervals (default 2000)")
    ap.add_argument("--from-json", default=None, metavar="SWEEP_JSON",
                    help="reuse a finished sweep (its sweep.json) instead of simulating: redo the report, the figures "
                         "and the correlation with --detector-reports")
    ap.add_argument("--out", default="runs/sweep", help="output folder (default runs/sweep)")
    ap.add_argument("--json", default=None, metavar="PATH", help="JSON path (default OUT/sweep.json)")
    ap.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def split_overrides(overrides: list[str]) -> tuple[dict, list[str]]:
    """(sensor field changes, simulator overrides) from --set; a bad sensor key or value is the user's error."""
    import yaml

    fields = {f.name for f in dataclasses.fields(_lidar_class())} - _NOT_SETTABLE
    sensor, sim = {}, []
    for item in overrides:
        if "=" not in item:
            raise UserError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        key = key.strip()
        if not key.startswith("sensor."):
            sim.append(item)
            continue
        name = key[len("sensor."):]
        if name in _NOT_SETTABLE:
            raise UserError(f"--set {key}: the {name} is what the sweep varies (use --heights)" if name == "height"
                            else f"--set {key}: the name is set by the sweep")
        if name not in fields:
            close = difflib.get_close_matches(name, sorted(fields), n=1)
            raise UserError(f"--set {key}: unknown sensor field {name!r}" + (f"; did you mean sensor.{close[0]}?"
                                                                             if close else "")
                            + f" (fields: {', '.join(sorted(fields))})")
        try:
            v = yaml.safe_load(value)
        except yaml.YAMLError as e:
            raise UserError(f"--set {key}: value {value!r} is not valid YAML ({e})") from None
        sensor[name] = tuple(v) if isinstance(v, list) else v
    return sensor, sim


def _lidar_class():
    from detbench.sim import LidarConfig

    return LidarConfig


def sweep_lidars(args, sensor_changes: dict) -> tuple[list, object]:
    """One LidarConfig per height: the preset with the --set sensor changes, at that height."""
    from detbench.sim import lidar_preset

    heights = args.heights or DEFAULT_HEIGHTS
    keys = [height_key(h) for h in heights]
    dup = sorted({k for k in keys if keys.count(k) > 1}, key=float)
    if dup:
        raise UserError(f"--heights: {', '.join(dup)} m given twice (heights are compared in millimetres)")
    try:
        if args.lidar == PAPER_SENSORS:
            # what the training datasets use (detbench.sim.dataset): lidar_preset(height) at each height
            lidars = [lidar_preset(float(h), **sensor_changes) for h in sorted(heights, key=float)]
            base = lidar_preset(1.0, **sensor_changes)
        else:
            base = lidar_preset(args.lidar)
            if sensor_changes:
                base = base.replace(**sensor_changes)
            lidars = [base.replace(height=float(h), name=f"{base.name}@{height_key(h)}") for h in
                      sorted(heights, key=float)]
    except (ValueError, TypeError) as e:
        raise UserError(f"--lidar / --heights / --set sensor.*: {e}") from None
    return lidars, base


def simulate(args, sweep, lidars, cfg) -> dict:
    """Feed `sweep` from the simulator (hit counts, no points); returns the provenance."""
    from tqdm import tqdm

    from detbench.sim import HighwaySimulator

    fps = args.frames_per_scene if args.frames_per_scene is not None else int(cfg["scene"]["frames_per_scene"])
    sim = HighwaySimulator(cfg, seed=args.seed)
    stream = sim.run(args.frames, lidars, frames_per_scene=fps, with_points=False)
    for step in tqdm(stream, total=args.frames, desc=f"simulate x {len(lidars)} heights", unit="frame",
                     disable=args.no_progress, smoothing=0.05):
        sweep.add(step, counts=[f.hit_counts for f in step])
    return {"fps": fps, "sim_timings_s": {k: round(v, 2) for k, v in sim.timings.items()}}


def run_sweep(args) -> dict:
    from detbench.config import ConfigError
    from detbench.eval.placement import EVIDENCE_SCALE_POINTS, VoxelGrid, ray_coverage
    from detbench.eval.sweep import HeightSweep
    from detbench.sim import load_sim_config

    sensor_changes, sim_overrides = split_overrides(args.overrides)
    lidars, base = sweep_lidars(args, sensor_changes)
    try:
        cfg = load_sim_config(args.preset, overrides=tuple(sim_overrides))
    except ConfigError as e:
        raise UserError(str(e)) from None
    from detbench.data.regions import DETECTED_BOTTOM_LIFT

    lift = float(cfg["output"]["count_bottom_lift_m"])
    if abs(lift - DETECTED_BOTTOM_LIFT) > 1e-12:
        raise UserError(f"--set output.count_bottom_lift_m={lift}: the sweep counts LiDAR-detected vehicles with the "
                        f"paper's {DETECTED_BOTTOM_LIFT} m lift; drop that override")
    try:
        grid = VoxelGrid(voxel=args.voxel)
        sweep = HeightSweep(distance_bin=args.distance_bin, bootstrap=args.bootstrap,
                            evidence_scale=args.evidence_scale if args.evidence_scale is not None
                            else EVIDENCE_SCALE_POINTS, grid=grid)
    except ValueError as e:
        raise UserError(str(e)) from None
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    prov = simulate(args, sweep, lidars, cfg)
    t_sim = time.perf_counter() - t0
    coverage = None
    t1 = time.perf_counter()
    if not args.no_smig:
        coverage = {height_key(l.height): ray_coverage(l.ray_directions().reshape(-1, 3), l.height, l.max_range, grid)
                    for l in lidars}
    t_cov = time.perf_counter() - t1
    t2 = time.perf_counter()
    described = base.to_dict()
    described.pop("height")
    source = {"kind": "simulator", "preset": args.preset, "seed": args.seed, "frames": args.frames,
              "frames_per_scene": prov["fps"], "overrides": list(sim_overrides),
              "sensor": {"preset": args.lidar, "changes": {k: list(v) if isinstance(v, tuple) else v
                                                           for k, v in sensor_changes.items()},
                         "fields": described,
                         "description": f"{base.channels} x {base.h_samples} rays, vfov {base.vfov_deg[0]:g}.."
                                        f"{base.vfov_deg[1]:g} deg, pitch {base.pitch_deg:g} deg down, hfov "
                                        f"{base.hfov_deg:g} deg, {base.max_range:g} m"
                                        + ("; Table II's pitched sensor at 1.8 m" if args.lidar == PAPER_SENSORS
                                           else ""),
                         "per_height": {height_key(l.height): l.name for l in lidars}},
              "counting": "simulator hit counts (no points), the 0.05 m lift rule"}
    report = sweep.report(coverage=coverage, source=source)
    t_rep = time.perf_counter() - t2
    load_after = os.getloadavg()
    report["run"] = {"seconds": round(t_sim + t_cov + t_rep, 2), "simulate_and_count_s": round(t_sim, 2),
                     "smig_coverage_s": round(t_cov, 2), "report_s": round(t_rep, 2), "heights": len(lidars),
                     "frames_per_second": round(args.frames / t_sim, 1) if t_sim > 0 else None,
                     "lidar_frames_per_second": round(args.frames * len(lidars) / t_sim, 1) if t_sim > 0 else None,
                     "cpu_count": os.cpu_count(),
                     "load_average_before": [round(v, 2) for v in load_before],
                     "load_average_after": [round(v, 2) for v in load_after],
                     "threads": runtime.describe() if hasattr(runtime, "describe") else None,
                     "sim_timings_s": prov["sim_timings_s"]}
    return report


def load_sweep(path: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"--from-json {p}: no such file; give the sweep.json of a finished tools/sweep.py run")
    try:
        rep = read_json(p)
    except (ValueError, UnicodeDecodeError) as e:
        raise UserError(f"--from-json {p}: not JSON ({e}); give the sweep.json of a tools/sweep.py run") from None
    if not isinstance(rep, dict) or rep.get("kind") != "height_sweep" or "scores" not in rep:
        raise UserError(f"--from-json {p}: not a height-sweep report (no kind 'height_sweep'); give the sweep.json "
                        f"written by tools/sweep.py")
    return rep


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "sweep.json"
    if args.from_json:
        report = load_sweep(args.from_json)
        report.pop("correlation", None)
    else:
        if args.frames < 1:
            raise UserError("--frames needs a positive number of instants")
        if args.frames_per_scene is not None and args.frames_per_scene < 1:
            raise UserError("--frames-per-scene needs a positive number")
        if args.bootstrap < 0:
            raise UserError("--bootstrap needs 0 or more replicates")
        report = run_sweep(args)
    if args.detector_reports:
        from detbench.eval.rankcorr import correlate_sweep, load_detector_reports

        try:
            figures, skipped = load_detector_reports(args.detector_reports)
        except ValueError as e:
            raise UserError(str(e)) from None
        corr = correlate_sweep(report, figures, replicates=args.correlation_replicates)
        corr["skipped_reports"] = skipped
        report["correlation"] = corr
        for note in corr["notes"] + [f"skipped {s['source']}: {s['reason']}" for s in skipped]:
            print(f"note: {note}", file=sys.stderr)
    from detbench.eval.sweep import sweep_markdown

    atomic_write_json(json_path, report)
    atomic_write_text(out / "sweep.md", sweep_markdown(report))
    written = [json_path, out / "sweep.md"]
    if not args.no_figures:
        from detbench.eval.sweep_plots import save_sweep_figures

        written += list(save_sweep_figures(report, out).values())
    _summary(report)
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _summary(report: dict) -> None:
    """A few lines on the terminal: LDR of all vehicles and the primary score per height."""
    ab = report["ability"]
    prim = report["scores"]["primary"]
    print(f"{report['num_frames']} frames, {report['num_scenes']} scenes, {len(report['heights'])} heights"
          + (f", {report['run']['seconds']:.1f} s" if report.get("run") else ""))
    print("height  " + "".join(f"{'LDR ' + r:>14}" for r in RANGE_NAMES) + f"{prim + ' large':>16}")
    for h in report["heights"]:
        ldrs = [ab["heights"][h][r]["all"]["ldr"] for r in RANGE_NAMES]
        s = report["scores"]["heights"][h]["large"][prim]["value"]
        print(f"{h:>6}  " + "".join(f"{'-' if v is None else f'{v:.3f}':>14}" for v in ldrs)
              + f"{'-' if s is None else f'{s:.3f}':>16}")
    best = report["best_height"]
    print("best height by LDR (all vehicles): " + ", ".join(
        f"{r} {best[r]['all']['height']} m" for r in RANGE_NAMES if best[r]["all"]))
    corr = report.get("correlation")
    if corr:
        for s, v in corr["summary"].items():
            print(f"{s}: {v['predicts']} of {v['rows']} cells predicted, median rho {v['median_spearman']}")


if __name__ == "__main__":
    sys.exit(run_main(main))
