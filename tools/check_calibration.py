#!/usr/bin/env python3
"""Check the simulator's calibration against the paper's Tables IV, V and VI, per seed, per block and pooled.

For each seed, streams `--frames` frames of the simulator (hit counts only, as
`tools/analyze.py --simulate` does) at the paper's three heights and checks, on each whole
run and each block of `--block-frames` consecutive frames, these criteria:
  1. each of the 27 (range x level x height) LDRs within +-`--tolerance` of the paper;
  2. vehicles per frame of every range and level within +-`--total-tolerance` (relative);
  3. the second-in-lane LDR (Top6 minus Top3: the second-nearest vehicle of the ego, left and
     right lanes) within +-`--second-tolerance` of the one the paper's counts imply;
  4. 1.8 m above both lower heights in every cell;
  5. 0.5 m and 1.0 m within `--pair-tolerance` of each other in every cell.
The beyond-Top6 LDRs (All minus Top6) are reported beside the paper's, not judged.
Over the seeds, the calibration bar (`verdict`): every cell within the tolerance for all seeds
but `--allowed-misses`, the pooled LDRs within +-`--pooled-tolerance`, and criteria 2-5 on
the pooled counts. The pooled LDRs, decomposition and per-frame totals carry 95 % intervals
from a bootstrap over scenes.

It also states the precision a study of a given length can have (`precision`: one scene's
scatter turned into the uncertainty of n scenes) and how often a fresh study meets every
criterion (`pass_rate`, from 2000 studies whose scenes are resampled from all seeds' scenes).
The statistics live in detbench/studies/calibration.py; this tool runs the simulator, parses
the arguments and writes the report.

Examples:
  python tools/check_calibration.py --seeds 0 1 2 3 4 5   # the full check: six seeds, 8000 frames each
  python tools/check_calibration.py --sim-preset v2        # calibration v2 (the default is v3)
  python tools/check_calibration.py --seeds 0 --frames 2000 --block-frames 0
  python tools/check_calibration.py --set traffic.density_per_km_lane=10 --strict

Writes OUT/calibration.json and OUT/calibration.md. LDR = detected / total (a fraction);
deviations are LDR differences; vehicles per frame are counts per frame (their criterion is a
relative difference); times are seconds. With --strict the exit code is 1 when the verdict
(several seeds) or the whole run (one seed) fails.
"""
from __future__ import annotations

import argparse
import sys

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.studies.calibration_check import CalibrationOptions, check_calibration
from detbench.utils.cli import UserError, add_sim_preset_argument, claim_output, output_folder, require_distinct
from detbench.utils.report_folders import CALIBRATION_FOLDER
from detbench.utils.atomic import atomic_write_json, atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description="Check the simulator's LiDAR detection rates against the paper's "
                                             "Tables IV-VI (27 cells), per-frame totals and the per-lane "
                                             "decomposition, per seed, per block of frames and pooled.",
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5],
                    help="simulator seeds (default 0 1 2 3 4 5: six seeds of 8000 frames judge a calibration)")
    ap.add_argument("--frames", type=int, default=8000, help="frames per seed (default 8000, the paper's)")
    ap.add_argument("--block-frames", type=int, default=0,
                    help="also check each block of this many consecutive frames (default 0 = no blocks); "
                         "a multiple of the frames per scene")
    ap.add_argument("--frames-per-scene", type=int, default=None,
                    help="frames per scene (default: the --sim-preset's, 200)")
    ap.add_argument("--tolerance", type=float, default=0.05, help="allowed |LDR - paper| per seed (default 0.05)")
    ap.add_argument("--pooled-tolerance", type=float, default=0.03,
                    help="allowed |LDR - paper| of the seeds pooled (default 0.03)")
    ap.add_argument("--allowed-misses", type=int, default=1,
                    help="seeds a cell may miss --tolerance in (default 1: 5 of 6 must meet it)")
    ap.add_argument("--total-tolerance", type=float, default=0.15,
                    help="allowed relative difference of vehicles per frame (default 0.15)")
    ap.add_argument("--second-tolerance", type=float, default=0.07,
                    help="allowed |second-in-lane LDR - paper| (default 0.07)")
    ap.add_argument("--pair-tolerance", type=float, default=0.03,
                    help="allowed |LDR(0.5 m) - LDR(1.0 m)| in each cell (default 0.03)")
    add_sim_preset_argument(ap, detail=", calibration v3; v2 and v1 are calibrations v2 and v1; the report "
                                       "names the preset's calibration")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator config override, repeatable")
    ap.add_argument("--out", default="runs/check_calibration", help="output folder for the JSON and Markdown")
    ap.add_argument("--strict", action="store_true", help="exit with 1 when the verdict (or one seed's run) fails")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    opts = CalibrationOptions(
        seeds=args.seeds, frames=args.frames, block_frames=args.block_frames, frames_per_scene=args.frames_per_scene,
        tolerance=args.tolerance, pooled_tolerance=args.pooled_tolerance, allowed_misses=args.allowed_misses,
        total_tolerance=args.total_tolerance, second_tolerance=args.second_tolerance,
        pair_tolerance=args.pair_tolerance, preset=args.sim_preset, overrides=args.overrides,
        no_progress=args.no_progress)
    try:
        require_distinct(args.seeds, "--seeds", what="seed")
        output_folder(args.out, CALIBRATION_FOLDER)
        report, md, failed = check_calibration(opts)
        with claim_output(args.out, CALIBRATION_FOLDER) as out:
            atomic_write_json(out / "calibration.json", report)
            atomic_write_text(out / "calibration.md", md)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out / 'calibration.json'}, {out / 'calibration.md'}")
    if args.strict:
        return 1 if failed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
