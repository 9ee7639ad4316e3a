"""The height sweep fed from the simulator: one sensor per height, the frames simulated and counted, the report.

tools/sweep.py's computation: `run_sweep(SweepOptions(...))` builds the sensor at every height
(a preset with --set sensor.* changes, or the training datasets' sensors with lidar="paper"),
simulates the frames (hit counts, no points), feeds detbench.studies.sweep.HeightSweep and adds
the S-MIG ray coverage; `correlate_with_detectors` adds the rank correlation with trained
detectors (detbench.studies.rankcorr); `summary_lines` is the terminal summary.
"""
from __future__ import annotations

import dataclasses
import difflib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from detbench import runtime
from detbench.data.frame import height_key
from detbench.data.regions import RANGE_NAMES
from detbench.studies.rankcorr import correlate_sweep, load_detector_reports
from detbench.utils.cli import UserError
from detbench.utils.atomic import read_json

DEFAULT_HEIGHTS = [round(0.3 + 0.1 * i, 1) for i in range(20)]  # 0.3 ... 2.2 m
DEFAULT_LIDAR = "h3-1.0"
PAPER_SENSORS = "paper"  # --lidar paper: lidar_preset(height) per height, as the training datasets
_NOT_SETTABLE = {"height", "name"}

@dataclass
class SweepOptions:
    """The sweep's settings (tools/sweep.py's arguments): instants, heights in metres, the sensor and simulator."""

    frames: int = 8000
    frames_per_scene: int | None = None  # None: the simulator preset's
    heights: list[float] | None = None  # None: DEFAULT_HEIGHTS
    lidar: str = DEFAULT_LIDAR
    overrides: list[str] = field(default_factory=list)  # sensor.FIELD=VALUE or simulator KEY=VALUE
    preset: str = "paper"
    seed: int = 0
    bootstrap: int = 1000
    distance_bin: float = 10.0
    evidence_scale: float | None = None
    voxel: float = 0.5
    no_smig: bool = False
    no_progress: bool = False


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


def sweep_lidars(args: SweepOptions, sensor_changes: dict) -> tuple[list, object]:
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


def simulate(args: SweepOptions, sweep, lidars, cfg) -> dict:
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


def run_sweep(args: SweepOptions) -> dict:
    """Simulate the sweep's frames at every height and return its report (sweep.json). Raises UserError
    naming the fix for a bad option."""
    if args.frames < 1:
        raise UserError("--frames needs a positive number of instants")
    if args.frames_per_scene is not None and args.frames_per_scene < 1:
        raise UserError("--frames-per-scene needs a positive number")
    if args.bootstrap < 0:
        raise UserError("--bootstrap needs 0 or more replicates")
    from detbench.config import ConfigError
    from detbench.studies.placement import EVIDENCE_SCALE_POINTS, VoxelGrid, ray_coverage
    from detbench.studies.sweep import HeightSweep
    from detbench.sim import load_sim_config
    from detbench.data.layout import sim_calibration

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
        coverage = {height_key(lidar.height): ray_coverage(lidar.ray_directions().reshape(-1, 3), lidar.height,
                                                        lidar.max_range, grid)
                    for lidar in lidars}
    t_cov = time.perf_counter() - t1
    t2 = time.perf_counter()
    described = base.to_dict()
    described.pop("height")
    source = {"kind": "simulator", "preset": args.preset, "calibration": sim_calibration(cfg), "seed": args.seed,
              "frames": args.frames,
              "frames_per_scene": prov["fps"], "overrides": list(sim_overrides),
              "sensor": {"preset": args.lidar, "changes": {k: list(v) if isinstance(v, tuple) else v
                                                           for k, v in sensor_changes.items()},
                         "fields": described,
                         "description": f"{base.channels} x {base.h_samples} rays, vfov {base.vfov_deg[0]:g}.."
                                        f"{base.vfov_deg[1]:g} deg, pitch {base.pitch_deg:g} deg down, hfov "
                                        f"{base.hfov_deg:g} deg, {base.max_range:g} m"
                                        + ("; Table II's pitched sensor at 1.8 m" if args.lidar == PAPER_SENSORS
                                           else ""),
                         "per_height": {height_key(lidar.height): lidar.name for lidar in lidars}},
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
    """A finished sweep's report from its sweep.json; UserError when the file is not one."""
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


def correlate_with_detectors(report: dict, report_paths: list[str], replicates: int) -> list[str]:
    """Rank-correlate the sweep's scores with the detectors' figures of `report_paths` (tools/eval.py
    report.json files) into report["correlation"]; returns the notes for the terminal."""
    try:
        figures, skipped = load_detector_reports(report_paths)
    except ValueError as e:
        raise UserError(str(e)) from None
    corr = correlate_sweep(report, figures, replicates=replicates)
    corr["skipped_reports"] = skipped
    report["correlation"] = corr
    return corr["notes"] + [f"skipped {s['source']}: {s['reason']}" for s in skipped]


def summary_lines(report: dict) -> list[str]:
    """A few lines for the terminal: LDR of all vehicles and the primary score per height."""
    lines = []
    ab = report["ability"]
    prim = report["scores"]["primary"]
    lines.append(f"{report['num_frames']} frames, {report['num_scenes']} scenes, {len(report['heights'])} heights"
          + (f", {report['run']['seconds']:.1f} s" if report.get("run") else ""))
    lines.append("height  " + "".join(f"{'LDR ' + r:>14}" for r in RANGE_NAMES) + f"{prim + ' large':>16}")
    for h in report["heights"]:
        ldrs = [ab["heights"][h][r]["all"]["ldr"] for r in RANGE_NAMES]
        s = report["scores"]["heights"][h]["large"][prim]["value"]
        lines.append(f"{h:>6}  " + "".join(f"{'-' if v is None else f'{v:.3f}':>14}" for v in ldrs)
              + f"{'-' if s is None else f'{s:.3f}':>16}")
    best = report["best_height"]
    lines.append("best height by LDR (all vehicles): " + ", ".join(
        f"{r} {best[r]['all']['height']} m" for r in RANGE_NAMES if best[r]["all"]))
    corr = report.get("correlation")
    if corr:
        for s, v in corr["summary"].items():
            lines.append(f"{s}: {v['predicts']} of {v['rows']} cells predicted, median rho {v['median_spearman']}")
    return lines


__all__ = ["DEFAULT_HEIGHTS", "DEFAULT_LIDAR", "PAPER_SENSORS", "SweepOptions", "correlate_with_detectors",
           "load_sweep", "run_sweep", "split_overrides", "summary_lines", "sweep_lidars"]
