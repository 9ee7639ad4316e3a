#!/usr/bin/env python3
"""The whole Height3 study in one command: data, LiDAR detection ability, train, evaluate, report.

For the chosen preset: (1) the dataset (the simulated default of the preset, or --data);
(2) the LiDAR detection-ability study over all its frames at every height (paper Tables
IV-VI, Fig. 5-7); (3) each registered detector trained per height on that height's training
split; (4) each evaluated on the same height's test split (Table VII); (5) one combined
report with the paper's Fig. 8-10.

Examples:
  python tools/study.py --preset quick                 # the quick start: every detector learns
  python tools/study.py --preset smoke                 # the pipeline end to end (tests, CI)
  python tools/study.py --preset cpu --out runs/study_cpu
  python tools/study.py --preset paper --device cuda   # the paper's scale
  python tools/study.py --preset cpu --models second --heights 0.5 1.8
  python tools/study.py --preset cpu --rigs headlights forehead --cross-height   # rigs as cars carry them
  python tools/study.py --preset quick --cross-height  # + each model tested at the other heights
  python tools/study.py --preset cpu --heights 0.5 1.8 --test-data data/test200   # tested on more scenes
  python tools/study.py --preset quick --jobs 2        # two jobs at once (default: one per usable core)
  python tools/study.py --preset quick --models second pillarnet --seeds 0 1   # each run once per seed
  python tools/study.py --preset smoke --executor ray  # the jobs as tasks of a local Ray instance
  python tools/study.py --preset paper --device cuda --executor ray --address auto --out /shared/nfs/study

Jobs: every training, evaluation, the ability study and the combined report is a job that runs
as soon as the jobs it needs have finished (a training needs the data, its evaluation the
training, the report all of them), each in its own process with one torch thread, so a study's
figures do not depend on how many run at once. Each job's output goes to OUT/logs/<job>.log (and
to the terminal too with --jobs 1); a failed job prints its log's last lines and stops the study
(the running trainings write a checkpoint first), as does Ctrl-C. Measured times per preset:
docs/results.md.

The study resumes: a stage whose output exists and was computed from the same inputs (the
data's content, the config, the heights) is skipped, an interrupted training run is resumed
from its last checkpoint. A rerun with other inputs computes the ability study and the
evaluations again and refuses a finished training run computed from other inputs, naming it
and what changed. Delete OUT (or pass --fresh) to start over.
Writes OUT/study.md and OUT/study.json, OUT/ability/, OUT/<model>_h<height>/ (training run
and eval_*/ report; OUT/<model>_h<height>_s<seed>/ for each --seeds seed other than the
config's train.seed), OUT/combined/ (table and figures) and OUT/logs/ (one log per job).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
import models
from detbench.studies.study import StudyOptions, run_study
from detbench.studies.study_plan import preset_description
from detbench.train.run_config import preset_names
from detbench.utils.cli import doc_parser, run_main


def build_parser() -> argparse.ArgumentParser:
    ap = doc_parser(__doc__)
    preset = ap.add_argument("--preset", default="quick", choices=preset_names(),
                             help="training budget, configs/presets/NAME.yaml (data, epochs, model widths). Default "
                                  "quick")
    _describe_presets_in_help(ap, preset)
    ap.add_argument("--models", nargs="+", default=None,
                    help=f"detectors, any of {', '.join(sorted(models.REGISTRY))} (default: the preset's "
                         f"study.models, configs/presets/NAME.yaml; every one when that list is empty)")
    ap.add_argument("--heights", type=float, nargs="+", default=None,
                    help="mounting heights in metres (default: with --data every height the dataset holds, else the "
                         "preset's data.heights)")
    ap.add_argument("--rigs", nargs="+", default=None, metavar="NAME",
                    help="LiDAR rigs by name instead of heights (configs/rigs.yaml; docs/rigs.md): the data simulated "
                         "with those rigs (or --data holding them), the ability study, training and evaluation per "
                         "rig, the report keyed by rig; --cross-height gives the cross-rig matrix. E.g. --rigs "
                         "headlights forehead")
    ap.add_argument("--data", default=None, metavar="ROOT", help="a dataset on disk instead of the simulated default")
    ap.add_argument("--test-data", default=None, metavar="ROOT",
                    help="evaluate on the test split of this dataset instead of the training data's (the training "
                         "still reads the train split of --data or the simulated default): more test scenes for "
                         "narrower intervals without training again, or another world. It must hold every height "
                         "(or rig) of the study. E.g. a held-out set of 200 scenes of the cpu preset's world: "
                         "tools/simulate.py --out data/test200 --frames 2000 --frames-per-scene 10 --frame-stride 20 "
                         "--heights 0.5 1.8 --seed 1 --test-fraction 0.99")
    ap.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    ap.add_argument("--out", default=None, help="output folder (default runs/study_<preset>)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override passed to every training run, e.g. --set train.epochs=4")
    ap.add_argument("--cross-height", action="store_true",
                    help="also test each model at every other height (the cross-height matrix: rows trained at, "
                         "columns tested at; evaluations only, no extra training)")
    ap.add_argument("--fresh", action="store_true",
                    help="empty OUT first instead of resuming (only a study's folder: any other is refused)")
    ap.add_argument("--no-progress", action="store_true", help="hide progress bars")
    ap.add_argument("--jobs", type=int, default=None, metavar="N",
                    help="jobs at once, whatever else runs (default: one per CPU core this process may use, its "
                         "affinity and any cgroup CPU quota, fewer while other processes keep some of them busy, "
                         "measured again as slots free up, and the progress line says so; one per GPU with "
                         "--device cuda; with --executor ray the cluster's CPUs or GPUs). Each job has one torch "
                         "thread whatever N, so results do not depend on it. E.g. --jobs 2")
    ap.add_argument("--executor", choices=("local", "ray"), default="local",
                    help="local (default): the jobs as processes of this machine; ray: each job a Ray task asking "
                         "for 1 CPU (or 1 GPU with --device cuda) on whichever worker Ray picks (pip install -e "
                         "'.[cluster]'). With ray, OUT and --data must be folders every worker shares (NFS), and "
                         "every worker has this checkout at the same path. E.g. --executor ray --address auto")
    ap.add_argument("--address", default=None, metavar="ADDR",
                    help="with --executor ray: the cluster, 'auto' (the one `ray start` started here) or host:port "
                         "of its head; left out: a local Ray instance on this machine. E.g. --address 10.0.0.1:6379")
    ap.add_argument("--seeds", type=int, nargs="+", default=None, metavar="S",
                    help="train each model and height once per seed (--set train.seed=S; default: the config's "
                         "train.seed only). The config's own seed keeps the run folder <model>_h<height>, the "
                         "others get <model>_h<height>_s<S>; study.md gives each figure as the mean over seeds "
                         "with an interval holding seed spread and scene bootstrap. E.g. --seeds 0 1 2")
    return ap


def _describe_presets_in_help(ap: argparse.ArgumentParser, preset: argparse.Action) -> None:
    """--help states what each preset is, read from configs/presets/ when the help is shown."""
    format_help = ap.format_help

    def with_presets() -> str:
        described = "; ".join(f"{p}: {preset_description(p, sorted(models.REGISTRY))}" for p in preset_names())
        preset.help = (f"training budget, configs/presets/NAME.yaml ({described}; measured times: "
                       f"docs/results.md). Default quick")
        return format_help()

    ap.format_help = with_presets


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    opts = StudyOptions(preset=args.preset, models=args.models, heights=args.heights, rigs=args.rigs, data=args.data,
                        device=args.device, out=args.out, overrides=args.overrides, cross_height=args.cross_height,
                        fresh=args.fresh, no_progress=args.no_progress, jobs=args.jobs, executor=args.executor,
                        address=args.address, seeds=args.seeds, test_data=args.test_data)
    md, seconds = run_study(opts, registry=models, repo=ROOT)
    print(f"\nstudy done in {seconds / 60:.1f} min: {md}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
