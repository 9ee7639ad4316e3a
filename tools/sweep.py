#!/usr/bin/env python3
"""Height sweep: which mounting height, for my LiDAR? LDR and training-free placement scores for many heights.

One sensor (a Table I / II preset, changed with --set sensor.KEY=VALUE) at every height of
--heights (default 0.3 to 2.2 m in 0.1 m steps) sees the same simulated traffic: each instant
is simulated once and ray-cast once per height. Reported per height: LDR by range and
importance level (the paper's Tables IV-VI, heights as rows) and against distance, with 95 %
intervals from a bootstrap over scenes; the placement scores of detbench.studies.placement
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
import math
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench import runtime  # noqa: F401  (first detbench import: thread-runtime defaults before numba starts)
from detbench.studies.sweep_sim import (
    DEFAULT_LIDAR, SweepOptions, correlate_with_detectors, load_sweep, run_sweep, summary_lines,
)
from detbench.utils.cli import (
    UserError, add_sim_preset_argument, check_out_dir, claim_output, output_folder, require, require_distinct, run_main,
)
from detbench.utils.report_folders import SWEEP_FOLDER
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    doc = __doc__.split("\n\n")
    ap = argparse.ArgumentParser(description=doc[0], epilog="\n\n".join(doc[1:]),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8000,
                    help="instants to simulate (each at every height; default 8000)")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per scene at 2 Hz (default: the --sim-preset's, 200 as in the paper); scenes are "
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
    add_sim_preset_argument(ap)
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


def check_arguments(args: argparse.Namespace) -> None:
    """UserError for a value the sweep cannot use, before anything is simulated."""
    from detbench.data.frame import height_key

    for h in args.heights or ():
        try:
            height_key(h)
        except ValueError as e:
            raise UserError(f"--heights {h:g}: {e}") from None
    require_distinct(args.heights, "--heights", key=height_key, what="height")
    for flag, v in (("--distance-bin", args.distance_bin), ("--voxel", args.voxel),
                    ("--evidence-scale", args.evidence_scale)):
        require(v is None or (math.isfinite(v) and v > 0), f"{flag} {v}: must be a positive number")
    require(args.correlation_replicates >= 1,
            f"--correlation-replicates {args.correlation_replicates}: must be an integer >= 1")
    output_folder(args.out, SWEEP_FOLDER)
    if args.json:
        check_out_dir(Path(args.json).parent, "--json")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    check_arguments(args)
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "sweep.json"
    if args.from_json:
        report = load_sweep(args.from_json)
        report.pop("correlation", None)
    else:
        report = run_sweep(SweepOptions(
            frames=args.frames, frames_per_scene=args.frames_per_scene, heights=args.heights, lidar=args.lidar,
            overrides=args.overrides, preset=args.sim_preset, seed=args.seed, bootstrap=args.bootstrap,
            distance_bin=args.distance_bin, evidence_scale=args.evidence_scale, voxel=args.voxel,
            no_smig=args.no_smig, no_progress=args.no_progress))
    if args.detector_reports:
        for note in correlate_with_detectors(report, args.detector_reports, args.correlation_replicates):
            print(f"note: {note}", file=sys.stderr)
    from detbench.studies.sweep import sweep_markdown

    with claim_output(out, SWEEP_FOLDER):
        atomic_write_json(json_path, report)
        atomic_write_text(out / "sweep.md", sweep_markdown(report))
        written = [json_path, out / "sweep.md"]
        if not args.no_figures:
            from detbench.studies.sweep_plots import save_sweep_figures

            written += list(save_sweep_figures(report, out).values())
    print("\n".join(summary_lines(report)))
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
