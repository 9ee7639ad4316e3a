#!/usr/bin/env python3
"""The whole Height3 study in one command: data, LiDAR detection ability, train, evaluate, report.

For the chosen preset: (1) the dataset (the simulated default of the preset, or --data);
(2) the LiDAR detection-ability study over all its frames at every height (paper Tables
IV-VI, Fig. 5-7); (3) each registered detector trained per height on that height's training
split; (4) each evaluated on the same height's test split (Table VII); (5) one combined
report with the paper's Fig. 8-10.

Examples:
  python tools/study.py --preset smoke                 # the quick start: minutes on a CPU
  python tools/study.py --preset cpu --out runs/study_cpu
  python tools/study.py --preset paper --device cuda   # the paper's scale
  python tools/study.py --preset cpu --models second --heights 0.5 1.8

The study resumes: a stage whose output exists is skipped, an interrupted training run is
resumed from its last checkpoint. Delete OUT (or pass --fresh) to start over.
Writes OUT/study.md and OUT/study.json, OUT/ability/, OUT/<model>_h<height>/ (training run
and eval_*/ report) and OUT/combined/ (table and figures).
"""
from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Not installed (run from a checkout): the repository root holds detbench and models.
if importlib.util.find_spec("detbench") is None or importlib.util.find_spec("models") is None:
    sys.path.insert(0, str(ROOT))

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)
import models  # noqa: E402
from detbench.config import ConfigError  # noqa: E402
from detbench.data.frame import height_key  # noqa: E402
from detbench.train.run_config import load_run_config, preset_names  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text, read_json  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="smoke", choices=preset_names(),
                    help="smoke (minutes, CPU; proves the pipeline), cpu (learns for real; ~10 min per model and "
                         "height on 2 cores), paper (the paper's scale; a GPU). Default smoke")
    ap.add_argument("--models", nargs="+", default=None, help=f"detectors (default all: "
                                                               f"{', '.join(sorted(models.REGISTRY))})")
    ap.add_argument("--heights", type=float, nargs="+", default=None,
                    help="mounting heights in metres (default: the preset's data.heights, 0.5 1.0 1.8)")
    ap.add_argument("--data", default=None, metavar="ROOT", help="a dataset on disk instead of the simulated default")
    ap.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    ap.add_argument("--out", default=None, help="output folder (default runs/study_<preset>)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override passed to every training run, e.g. --set train.epochs=4")
    ap.add_argument("--fresh", action="store_true", help="delete OUT first instead of resuming")
    ap.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return ap


def run(cmd: list[str], what: str) -> None:
    """Run one stage as its own process (its output streams through); stop the study if it fails."""
    print(f"\n=== {what}\n$ {' '.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"study: {what} failed (exit {proc.returncode}); fix the error above and run the same "
                         f"command again: finished stages are kept and skipped")
    print(f"=== {what}: done in {time.perf_counter() - t0:.0f} s", flush=True)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    py = sys.executable
    out = Path(args.out or f"runs/study_{args.preset}").resolve()
    if args.fresh and out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    names = args.models or sorted(models.REGISTRY)
    try:
        for n in names:
            models.get_model_class(n)
        base_cfg = load_run_config(names[0], args.preset, overrides=args.overrides)
    except (ConfigError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None
    heights = args.heights or [float(h) for h in base_cfg["data"]["heights"]]
    quiet = ["--no-progress"] if args.no_progress else []
    t_start = time.perf_counter()

    # 1. data
    from detbench.sim.dataset import default_dataset

    data_cfg = dict(base_cfg["data"])
    if args.data:
        data_cfg["root"] = str(Path(args.data).resolve())
    else:
        data_cfg["heights"] = sorted(set(map(float, data_cfg["heights"])) | set(heights))
    print(f"=== dataset ({args.preset} preset)", flush=True)
    root = default_dataset(data_cfg, progress=not args.no_progress)
    print(f"dataset: {root}")

    # 2. LiDAR detection ability, all frames, every height
    ability_json = out / "ability" / "ability.json"
    if not ability_json.is_file():
        run([py, "tools/analyze.py", "--data", str(root), "--split", "all", "--heights", *map(str, heights),
             "--out", str(out / "ability"), *quiet], "LiDAR detection ability")

    # 3-4. train and evaluate each model at each height
    reports = []
    for name in names:
        for h in heights:
            run_dir = out / f"{name}_h{height_key(h)}"
            report = run_dir / f"eval_h{height_key(h)}_test" / "report.json"
            reports.append(report)
            if report.is_file():
                continue
            summary = run_dir / "train_summary.json"
            done = summary.is_file() and not read_json(summary).get("interrupted", False)
            if not done:
                resume = ["--resume"] if (run_dir / "checkpoints").is_dir() else []
                sets = [x for o in args.overrides for x in ("--set", o)]
                run([py, "tools/train.py", "--model", name, "--height", str(h), "--preset", args.preset,
                     "--data", str(root), "--device", args.device, "--out", str(run_dir), *resume, *sets,
                     "--no-eval", *quiet], f"train {name} at {h:g} m")
            ckpt = read_json(summary)["checkpoint"]
            run([py, "tools/eval.py", "--ckpt", ckpt, "--split", "test", "--out", str(report.parent),
                 "--device", "cpu" if args.device == "auto" else args.device, *quiet],
                f"evaluate {name} at {h:g} m")

    # 5. combined report and figures
    run([py, "tools/eval.py", "--combine", *map(str, reports), "--out", str(out / "combined")], "combine reports")
    ability = read_json(ability_json)
    combined = read_json(out / "combined" / "combined.json")
    seconds = time.perf_counter() - t_start
    study = {"preset": args.preset, "data": str(root), "heights": heights, "models": names,
             "seconds_this_invocation": round(seconds, 1), "ability": ability, "detection": combined}
    atomic_write_json(out / "study.json", study)
    def embed(md_path: Path) -> str:  # a tool's Markdown one level below the study's sections
        return "\n".join("##" + ln if ln.startswith("#") else ln
                         for ln in md_path.read_text(encoding="utf-8").splitlines())

    lines = [f"# Height3 study ({args.preset} preset)", "",
             f"Data: `{root}`. Heights: {', '.join(f'{h:g} m' for h in heights)}. Models: {', '.join(names)}.", "",
             "## 1. LiDAR detection ability (all frames)", "",
             embed(out / "ability" / "ability.md"), "",
             "## 2. Detectors on the LiDAR-detected vehicles (test split)", "",
             embed(out / "combined" / "combined.md"), "",
             "Figures: " + ", ".join(f"`{p.relative_to(out)}`" for p in sorted(out.glob("*/*.png"))), ""]
    atomic_write_text(out / "study.md", "\n".join(lines))
    print(f"\nstudy done in {seconds / 60:.1f} min: {out / 'study.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
