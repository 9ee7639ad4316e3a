"""The whole Height3 study: data, LiDAR detection ability, training and evaluation per model and height, report.

For a preset: (1) the dataset (the preset's simulated default, or a dataset on disk); (2) the
LiDAR detection-ability study at every height (tools/analyze.py); (3) each detector trained per
height on that height's training split (tools/train.py); (4) each evaluated on the same
height's test split, and with cross_height on the other heights' too (tools/eval.py); (5) the
combined report, and study.md opening with the summary of detbench.studies.study_summary.
The data and the splits' counts are made in this process; every other stage is a job of a graph
(detbench.studies.jobs: a tool in its own process, its log in OUT/logs/), run as soon as the
jobs it needs have finished, several at once on this machine or on a Ray cluster
(detbench.studies.ray_executor). With --seeds each model and height is trained once per seed.
A stage whose output exists and was computed from the same inputs (detbench.studies.stage_inputs:
the data's content, the stage's config and settings) is skipped, so the study resumes. A stage
whose inputs changed is recomputed (the ability study, an evaluation) or, for a training run,
refused with the reason before any stage runs. The run folders follow detbench.train.run_layout.
"""
from __future__ import annotations

import os
import sys
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from detbench.config import ConfigError
from detbench.data.errors import DatasetError
from detbench.data.layout import read_info
from detbench.studies.cross_height import cross_height_markdown, cross_height_matrix, plot_cross_height
from detbench.studies.jobs import (LOGS_DIR, Job, LocalExecutor, check_graph, cuda_devices, default_jobs, job_counts,
                                   run_graph)
from detbench.studies.registry import ModelRegistry
from detbench.studies.seeds import (
    detector_table, pairwise_leads, pairwise_markdown, seed_height_summary, seed_markdown, seed_summary,
)
from detbench.studies.split_check import compare_splits, split_check_markdown, split_check_warnings
from detbench.studies.stage_inputs import (
    RECORDS_DIR, FileHashes, changes, config_digest, dataset_fingerprint, training_config, write_record,
)
from detbench.studies.study_summary import (
    detector_summary, detector_summary_lines, height_summary, height_summary_lines, unlearned_lines,
)
from detbench.train.run_config import load_run_config
from detbench.train.checkpoint import CheckpointManager
from detbench.train.run_layout import (
    STUDY_FOLDER, default_study_dir, eval_report_path, study_run_dir, training_seconds,
)
from detbench.utils.cli import UserError
from detbench.utils.atomic import atomic_write_json, atomic_write_text, read_json
from detbench.utils.folder_locks import claim_folder
from detbench.utils.folder_ownership import FolderNotReplaceable, check_replaceable, clear_folder

# What each preset's detector figures can and cannot show (printed in the study's summary).
PRESET_CAVEATS = {
    "smoke": "*Preset `smoke` proves that the pipeline runs end to end: a few frames, narrow models, two epochs. "
             "Its detectors have not learned; their recall and AP (near 0) say nothing about the models or the "
             "heights. Run `--preset quick` for figures that do.*",
    "quick": "*Preset `quick` trains narrow models for a few minutes each on a small simulated dataset: the "
             "detectors that learn at this budget reach AP@R40 0.4-0.7 and their ranking per height is meaningful "
             "within the intervals shown, but absolute figures are far below the paper's (full models, 8000 frames, "
             "80 epochs). The ability figures are at the paper's scale.*",
    "cpu": "*Preset `cpu` trains each detector 7-16 minutes on one CPU core: absolute "
           "figures are below the "
           "paper's scale; differences between heights and models hold within the intervals shown.*",
    "paper": "*Preset `paper`: the paper's data size and schedule.*",
}


@dataclass
class StudyOptions:
    """The study's settings (tools/study.py's arguments)."""

    preset: str = "quick"
    models: list[str] | None = None  # None: the preset's study.models, else every registered model
    heights: list[float] | None = None  # None: the preset's data.heights
    data: str | None = None  # a dataset on disk instead of the simulated default
    device: str = "auto"
    out: str | None = None  # None: run_layout.default_study_dir(preset)
    overrides: list[str] = field(default_factory=list)  # --set KEY=VALUE for every training run
    cross_height: bool = False
    fresh: bool = False  # empty OUT (a study's folder) first instead of resuming
    no_progress: bool = False
    jobs: int | None = None  # jobs at once; None: one per free CPU core (or per GPU), or the Ray cluster's
    executor: str = "local"  # local or ray
    address: str | None = None  # the Ray cluster (None: a local Ray instance)
    seeds: list[int] | None = None  # training seeds; None: the config's train.seed


def study_models(preset: str, requested: list[str] | None, overrides: list[str], *,
                 registry: ModelRegistry) -> tuple[list[str], list[str]]:
    """(the models to study, the registered ones the preset leaves out): --models when given, else the
    preset's `study.models`, else every registered model. Unknown names raise ValueError."""
    cfg = load_run_config(sorted(registry.REGISTRY)[0], preset, overrides=overrides)
    names = list(requested or [str(m) for m in (cfg["study"].get("models") or [])] or sorted(registry.REGISTRY))
    for n in names:
        registry.get_model_class(n)
    return names, ([] if requested else sorted(set(registry.REGISTRY) - set(names)))


def split_ability_reports(root: Path, heights: list[float], out: Path, fingerprint: str, *,
                          no_progress: bool = True) -> dict:
    """{"train": report, "test": report}: the ability study counted on each split of the dataset at `root`
    (hit counts of its points, as tools/analyze.py --data), kept in `out`/splits/<split>.json. A kept report
    is reused while its stage record (detbench.studies.stage_inputs: the heights and the data's content
    `fingerprint`) still holds."""
    from detbench.studies.ability_run import AbilityOptions, run_ability

    inputs = {"heights": list(heights), "data_fingerprint": fingerprint}
    reports = {}
    for split in ("train", "test"):
        path = out / "splits" / f"{split}.json"
        if path.is_file() and not changes(out, f"split_{split}", inputs):
            reports[split] = read_json(path)
            continue
        reports[split], _, _ = run_ability(AbilityOptions(data=str(root), split=split, heights=list(heights),
                                                          no_figures=True, no_progress=no_progress))
        atomic_write_json(path, reports[split])
        write_record(out, f"split_{split}", inputs)
    return reports


def run_study(args: StudyOptions, *, registry: ModelRegistry, repo: str | os.PathLike) -> tuple[Path, float]:
    """Run the study (each stage a tool of `repo` in its own process, resumed where OUT has its
    output) and write OUT/study.md and study.json: (the study.md path, the seconds it took).
    Raises UserError naming the fix before anything is deleted or created. OUT must be new, empty or a
    study's (`detbench.train.run_layout.STUDY_FOLDER`); it is locked while the study runs, so a second
    study on it is refused; `fresh` empties it first, only when it holds nothing but a study's files."""
    out = Path(args.out or default_study_dir(args.preset)).resolve()
    try:
        names, left_out = study_models(args.preset, args.models, args.overrides, registry=registry)
        base_cfg = load_run_config(names[0], args.preset, overrides=args.overrides)
    except (ConfigError, ValueError, KeyError) as e:
        raise UserError(str(e).strip("'\"")) from None
    if args.data and not Path(args.data).is_dir():
        raise UserError(f"--data {args.data}: no such folder; give a dataset written by tools/simulate.py or "
                        f"python -m detbench.data.convert, or leave --data out for the simulated default")
    if args.data:  # a folder without a readable dataset.json is refused here, not by a stage after others ran
        try:
            read_info(args.data)
        except DatasetError as e:
            raise UserError(f"--data {args.data}: {e}") from None
    bad_heights = [h for h in (args.heights or []) if not (h > 0 and h < 10)]
    if bad_heights:
        raise UserError(f"--heights {' '.join(f'{h:g}' for h in bad_heights)}: a mounting height is a positive "
                        f"number of metres below 10, e.g. --heights 0.5 1.0 1.8")
    _check_executor_options(args)
    # only now, with the arguments known to be good, is anything deleted or created
    with ExitStack() as held:
        try:
            if args.fresh:  # before the claim: a refused --fresh creates nothing
                check_replaceable(out, True, STUDY_FOLDER, flag="--fresh", out="--out")
            held.enter_context(claim_folder(out, STUDY_FOLDER, "a study", notes=_note))
            if args.fresh:
                clear_folder(out, STUDY_FOLDER, flag="--fresh")
        except FolderNotReplaceable as e:
            raise UserError(f"--out {e}") from None
        return _run_stages(args, out, names, left_out, base_cfg, repo=repo)


def _note(text: str) -> None:
    print(f"note: {text}", file=sys.stderr, flush=True)


def _run_stages(args: StudyOptions, out: Path, names: list[str], left_out: list[str], base_cfg: dict, *,
                repo: str | os.PathLike) -> tuple[Path, float]:
    """The study's stages in OUT (claimed and locked by `run_study`), then study.md and study.json."""
    heights = args.heights or [float(h) for h in base_cfg["data"]["heights"]]
    t_start = time.perf_counter()
    study_cfg = dict(base_cfg.get("study") or {})
    ability_frames = 0 if args.data else int(study_cfg.get("ability_frames", 0) or 0)
    ability_json = out / "ability" / "ability.json"

    add_left_out = f"--models {' '.join(sorted(set(names) | set(left_out)))}"  # the study with them
    if left_out:
        print(f"note: the {args.preset} preset's study leaves out {', '.join(left_out)} (study.models in "
              f"configs/presets/{args.preset}.yaml); add it with {add_left_out}", flush=True)

    # 1. data (in this process, before the graph: every job reads it)
    from detbench.sim.dataset import default_dataset

    data_cfg = dict(base_cfg["data"])
    if args.data:
        data_cfg["root"] = str(Path(args.data).resolve())
    else:
        data_cfg["heights"] = sorted(set(map(float, data_cfg["heights"])) | set(heights))
    print(f"\n=== dataset ({args.preset} preset)", flush=True)
    root = default_dataset(data_cfg, progress=not args.no_progress)
    print(f"dataset: {root}")
    info = read_json(root / "dataset.json") if (root / "dataset.json").is_file() else {}

    # The training seeds: the config's own train.seed keeps the run folder `model_hH`; each other seed
    # trains into `model_hH_sS` (run_layout.model_run_name) with --set train.seed=S.
    default_seed = int(base_cfg["train"]["seed"])
    seeds = list(dict.fromkeys(int(x) for x in args.seeds)) if args.seeds else [default_seed]
    primary = seeds[0]  # its reports make the combined report and the detector summary

    def tag(seed: int) -> int | None:
        return None if seed == default_seed else seed

    def seed_sets(seed: int) -> list[str]:
        return [] if tag(seed) is None else [f"train.seed={seed}"]

    def run_dir_of(name: str, h: float, seed: int) -> Path:
        return study_run_dir(out, name, h, tag(seed))

    # What each stage is computed from; a finished training run computed from other inputs is refused
    # here, before any stage runs (its figures would be reported under this study's data and settings).
    hashes = FileHashes(out / RECORDS_DIR / "file_hashes.json")
    try:
        data_fp = {h: dataset_fingerprint(root, [h], hashes) for h in heights}
    except (DatasetError, FileNotFoundError, ValueError) as e:
        raise UserError(str(e)) from None
    train_inputs = {(name, h, seed): {"model": name, "height": h, "preset": args.preset,
                                      "config": training_config(load_run_config(
                                          name, args.preset, overrides=[*args.overrides, *seed_sets(seed)])),
                                      "data_fingerprint": data_fp[h]}
                    for name in names for h in heights for seed in seeds}
    stale = []
    for (name, h, seed), inputs in train_inputs.items():
        run_dir = run_dir_of(name, h, seed)
        started = (run_dir / "train_summary.json").is_file() or CheckpointManager(run_dir / "checkpoints").latest()
        diff = changes(out, _train_stage(name, h, tag(seed)), inputs) if started else []
        if diff:
            stale.append(f"{run_dir} ({'; '.join(diff)})")
    if stale:
        more = f" (and {len(stale) - 1} more run(s))" if len(stale) > 1 else ""
        raise UserError(f"--out {out}: the training run {stale[0]}{more} was computed from other inputs than this "
                        f"study's (data_fingerprint: the content of the dataset's files at that height), so its "
                        f"figures would be reported as this study's; run this study with another --out, or delete "
                        f"that run folder to train it again")
    hashes.save()

    # The splits counted like the ability study (in this process; compared with it after the graph).
    print("\n=== the train and test splits counted like the ability study", flush=True)
    split_reports = split_ability_reports(root, heights, out, dataset_fingerprint(root, heights, hashes),
                                          no_progress=args.no_progress)
    hashes.save()

    # 2-5. the job graph: the ability study, each training, its evaluations, the combined report
    gpu = args.device.startswith("cuda") or (args.device == "auto" and _cuda_available())
    executor = _executor(args, gpu, repo)
    try:  # until run_graph owns it (it closes it whatever happens): a Ray connection is not left open
        # several jobs at once (or on Ray) write to their logs only: progress bars there are one endless line of
        # carriage returns, so the jobs print their per-epoch and summary lines instead
        logs_only = args.executor == "ray" or executor.slots > 1
        jobs, reports, cross_reports, seed_reports = _study_jobs(
            args, out, names, heights, seeds, root, data_cfg, ability_frames, hashes, train_inputs, data_fp,
            tag=tag, seed_sets=seed_sets, run_dir_of=run_dir_of, primary=primary, gpu=gpu, quiet=logs_only)
        check_graph(jobs)
    except BaseException:
        executor.close()
        raise
    counts = job_counts(jobs)
    where = ("Ray" if args.executor == "ray" else "this machine") + (" (GPUs)" if gpu else "")
    print(f"\n=== {len(jobs)} jobs ({', '.join(f'{n} {k}' for k, n in counts.items())}), up to {executor.slots} at "
          f"once on {where}; each job's output in {out / LOGS_DIR}/<job>.log", flush=True)
    try:
        run_graph(jobs, executor, out / LOGS_DIR)
    finally:
        hashes.save()

    # the splits against the ability study: does the test split hold the traffic the ability tables describe?
    split_checks = {name: compare_splits(rep, read_json(ability_json)) for name, rep in split_reports.items()}
    for name, result in split_checks.items():
        for line in split_check_warnings(result, f"{name} split", "ability study"):
            print(line, file=sys.stderr)

    ability = read_json(ability_json)
    combined = read_json(out / "combined" / "combined.json")
    report_dicts = [read_json(r) for r in reports]
    seconds = time.perf_counter() - t_start
    test_frames = report_dicts[0]["num_frames"] if report_dicts else 0
    test_scenes = ((report_dicts[0].get("uncertainty") or {}).get("num_clusters") if report_dicts else None)
    data_words = (f"`{root}`" + (f" ({info.get('num_frames', '?')} frames" if info else "")
                  + (f", {info.get('frames_per_scene')} per scene)" if info.get("frames_per_scene") else
                     (")" if info else "")))
    src = (ability.get("extras") or {}).get("source") or {}
    if src.get("kind") == "simulator":
        ability_words = (f"{src.get('frames')} frames simulated by the `{src.get('preset')}` simulator preset, seed "
                         f"{src.get('seed')}, {src.get('frames_per_scene')} per scene (hit counts, no points)")
    else:
        ability_words = f"every frame of {data_words}"
    source_ability = f"*Preset `{args.preset}`; data: {ability_words}.*"
    def detect_source(tested: str = "tested on the test split") -> str:
        return (f"*Preset `{args.preset}`; trained on the train split and {tested} of {data_words}: "
                f"{test_frames} test frames" + (f" from {test_scenes} scenes" if test_scenes else "") + ".*")

    source_detect = detect_source()
    # training time per model: the epochs' own seconds from each run's history.json, so a training that was
    # stopped and resumed counts every invocation's epochs
    train_min = {(name, h): [training_seconds(run_dir_of(name, h, seed)) / 60.0 for seed in seeds]
                 for name in names for h in heights}  # per model and height: minutes of each seed's training
    train_s = {name: 60.0 * sum(sum(train_min[(name, h)]) for h in heights) for name in names}
    train_words = (f"Training time (the runs' epochs, summed over heights{' and seeds' if len(seeds) > 1 else ''}; "
                   "a resumed training counts every invocation; evaluation excluded): "
                   + ", ".join(f"{m} {t / 60:.1f} min" for m, t in train_s.items())
                   + f"; {sum(train_s.values()) / 60:.1f} min in all.")
    study = {"preset": args.preset, "data": str(root), "heights": heights, "models": names, "left_out": left_out,
             "data_fingerprints": {str(h): fp for h, fp in data_fp.items()},
             "ability_frames": ability_frames or None, "test_frames": test_frames, "test_scenes": test_scenes,
             "seconds_this_invocation": round(seconds, 1),
             "train_seconds": {m: round(t, 1) for m, t in train_s.items()},
             "summary": {"heights": height_summary(ability),
                         "detectors": {str(h): c for h, c in detector_summary(report_dicts).items()}},
             "ability": ability, "detection": combined,
             "split_check": split_checks}
    cross_lines: list[str] = []
    if cross_reports:
        cross_dicts = [read_json(r) for r in cross_reports]
        mats = [cross_height_matrix(cross_dicts, "ap_r40", "small", "all"),
                cross_height_matrix(cross_dicts, "recall", "large", "all")]
        (out / "cross_height").mkdir(exist_ok=True)
        atomic_write_json(out / "cross_height" / "cross_height.json", {"matrices": mats})
        for mat in mats:
            plot_cross_height(mat, out / "cross_height" / f"cross_height_{mat['metric']}_{mat['range']}.png")
        cross_lines = ["## 3. Cross-height matrix", "", detect_source("tested on the test split at each height"),
                       "", *[ln for mat in mats for ln in cross_height_markdown(mat)]]
        atomic_write_text(out / "cross_height" / "cross_height.md", "\n".join(["# Cross-height matrix", "",
                                                                             *cross_lines[2:]]))
        study["cross_height"] = mats
    seed_lines = _seed_section(study, seeds, seed_reports,
                               {k: sum(v) / len(v) for k, v in train_min.items()})
    atomic_write_json(out / "study.json", study)

    def embed(md_path: Path, source: str) -> str:
        """A tool's Markdown one level below the study's sections, its source under every heading."""
        lines = []
        for ln in md_path.read_text(encoding="utf-8").splitlines():
            if ln.startswith("#"):
                lines += ["##" + ln, "", source]
            else:
                lines.append(ln)
        return "\n".join(lines)

    lines = [f"# Height3 study ({args.preset} preset)", "",
             f"Heights: {', '.join(f'{h:g} m' for h in heights)}. Models: {', '.join(names)}. "
             f"Detection data: {data_words}. Ran {seconds / 60:.1f} min in this invocation. {train_words}", "",
             "## Summary", "",
             "**Which height sees the most vehicles?** LiDAR detection rate (LDR: vehicles with >= 1 point / all "
             "vehicles), best height per importance level and range, and its paired lead over the next height "
             "(95 % scene-bootstrap interval).", "", source_ability, "",
             *height_summary_lines(ability), "",
             "**Which detector finds the most LiDAR-detected vehicles?** Per height, the model with the highest "
             "recall of the LiDAR-detected vehicles in the large range (every vehicle within 150 m ahead, "
             "|y| <= 15 m), at 3D IoU >= 0.7 and score >= 0.1; intervals from a bootstrap over test scenes, the "
             "lead paired over the same scenes.", "", source_detect, "",
             *detector_summary_lines(report_dicts), "",
             *([f"**Over the training seeds** {', '.join(map(str, seeds))} (the lines above are seed {primary}'s "
                f"alone): each model and height's mean over seeds, its interval holding both the test-scene "
                f"bootstrap and the seed-to-seed spread.", "", *seed_lines] if seed_lines else []),
             *unlearned_lines(report_dicts),
             *([f"*Not in this study: {', '.join(left_out)} (the preset's `study.models`, "
                f"configs/presets/{args.preset}.yaml, says why); add it with `{add_left_out}`.*", ""]
               if left_out else []),
             PRESET_CAVEATS.get(args.preset, ""), "",
             "Paper-scale figures (8000 frames, full models, 80 epochs; a GPU): "
             "`python tools/study.py --preset paper --device cuda`.", "",
             "## 1. LiDAR detection ability", "",
             embed(out / "ability" / "ability.md", source_ability), "",
             "### The splits against the ability study", "",
             "The detection dataset's splits counted like the ability study (all vehicles; 95 % scene-bootstrap "
             "intervals): a test split that holds other traffic than the ability study scores the detectors on "
             "another world.", "",
             f"*Preset `{args.preset}`; the train and test splits of {data_words}, against the ability study "
             f"({ability_words}).*", "",
             *[ln for name, result in split_checks.items()
               for ln in [f"**{name.capitalize()} split** ({split_reports[name]['num_frames']} frames, "
                          f"{(split_reports[name]['extras'].get('uncertainty') or {}).get('num_clusters')} scenes)",
                          "", *split_check_markdown(result, f"{name} split", "ability study"), ""]],
             "## 2. Detectors on the LiDAR-detected vehicles (test split)", "",
             embed(out / "combined" / "combined.md", source_detect), "",
             *cross_lines,
             "Per-run reports with 95 % intervals: " + ", ".join(
                 f"`{r.parent.relative_to(out)}/report.md`" for r in reports), "",
             "Figures: " + ", ".join(f"`{p.relative_to(out)}`" for p in sorted(out.glob("*/*.png"))), ""]
    atomic_write_text(out / "study.md", "\n".join(lines))
    return out / "study.md", seconds


def _study_jobs(args: StudyOptions, out: Path, names: list[str], heights: list[float], seeds: list[int], root: Path,
                data_cfg: dict, ability_frames: int, hashes: FileHashes, train_inputs: dict, data_fp: dict, *,
                tag, seed_sets, run_dir_of, primary: int, gpu: bool, quiet: bool = False):
    """The study's job graph: (jobs, the primary seed's report paths at the trained height, the cross-height
    report paths (primary seed), {(model, height): [report path per seed]}). `quiet` (or --no-progress)
    runs every job without progress bars.

    Jobs: the ability study (no dependencies: the data exist); per model, height and seed a training (no
    dependencies) and its evaluation at its height (after the training); with cross_height the evaluations
    at the other heights (after the training); the combined report (after every evaluation at the trained
    height). Each decides when it becomes ready whether its output is current (stage records)."""
    py = sys.executable
    quiet_args = ["--no-progress"] if args.no_progress or quiet else []
    eval_device = "cpu" if args.device == "auto" else args.device
    jobs: list[Job] = []

    # the LiDAR detection ability at every height: on the preset's own simulated stream of
    # study.ability_frames frames (counts only, no points: the paper's 8000 frames in about a
    # minute), else on every frame of the dataset.
    ability_json = out / "ability" / "ability.json"
    sim_sets = [x for o in data_cfg.get("sim_overrides") or [] for x in ("--set", o)]
    if ability_frames:
        ability_inputs = {"heights": heights, "simulate": ability_frames, "seed": data_cfg.get("seed", 0),
                          "sim_preset": str(data_cfg.get("sim_preset", "paper")), "sim_overrides": sim_sets}
        ability_cmd = [py, "tools/analyze.py", "--simulate", str(ability_frames), "--seed",
                       str(data_cfg.get("seed", 0)), "--sim-preset", str(data_cfg.get("sim_preset", "paper")),
                       *sim_sets,
                       "--heights", *map(str, heights), "--out", str(out / "ability"), *quiet_args]
        ability_what = f"ability study ({ability_frames} simulated frames)"
    else:
        ability_inputs = {"heights": heights, "data_fingerprint": dataset_fingerprint(root, heights, hashes)}
        hashes.save()
        ability_cmd = [py, "tools/analyze.py", "--data", str(root), "--split", "all", "--heights",
                       *map(str, heights), "--out", str(out / "ability"), *quiet_args]
        ability_what = "ability study (every frame)"

    def ability_prepare() -> list[str] | None:
        diff = changes(out, "ability", ability_inputs) if ability_json.is_file() else None
        if ability_json.is_file() and not diff:
            return None
        if diff:
            print(f"note: {ability_json} was computed from other inputs ({'; '.join(diff)}); computing it again",
                  flush=True)
        return ability_cmd

    jobs.append(Job("ability", "ability", ability_what, ability_prepare, outputs=(out / "ability",),
                    finish=lambda: write_record(out, "ability", ability_inputs)))

    def seed_words(seed: int) -> str:
        return "" if len(seeds) == 1 else f" seed {seed}"

    def train_job(name: str, h: float, seed: int) -> Job:
        run_dir = run_dir_of(name, h, seed)
        stage = _train_stage(name, h, tag(seed))
        sets = [x for o in [*args.overrides, *seed_sets(seed)] for x in ("--set", o)]

        def prepare() -> list[str] | None:
            summary = run_dir / "train_summary.json"
            write_record(out, stage, train_inputs[(name, h, seed)])  # a killed run resumes with it
            if summary.is_file() and not read_json(summary).get("interrupted", False):
                return None
            resume = ["--resume"] if (run_dir / "checkpoints").is_dir() else []
            return [py, "tools/train.py", "--model", name, "--height", str(h), "--preset", args.preset,
                    "--data", str(root), "--device", args.device, "--out", str(run_dir), *resume, *sets,
                    "--no-eval", *quiet_args]

        return Job(stage, "train", f"train {name} {h:g} m{seed_words(seed)}", prepare, model=name,
                   outputs=(run_dir,), gpu=gpu, finish=lambda: write_record(out, stage, train_inputs[(name, h, seed)]))

    def eval_job(name: str, h: float, seed: int, t: float, what: str) -> tuple[Job, Path]:
        run_dir = run_dir_of(name, h, seed)
        report = eval_report_path(run_dir, t)
        stage = _eval_stage(name, h, t, tag(seed))
        recorded: dict = {}

        def prepare() -> list[str] | None:
            """Evaluate the checkpoint trained at `h` on the test split at `t`, unless `report` holds that already."""
            ckpt = read_json(run_dir / "train_summary.json")["checkpoint"]
            inputs = {"train": config_digest(train_inputs[(name, h, seed)]), "checkpoint": hashes.sha1(ckpt),
                      "test_height": t, "data_fingerprint": data_fp[t],
                      "eval": config_digest(load_run_config(name, args.preset, overrides=args.overrides)["eval"])}
            hashes.save()
            recorded.update(inputs)
            diff = changes(out, stage, inputs) if report.is_file() else None
            if report.is_file() and not diff:
                return None
            if diff:
                print(f"note: {report} was computed from other inputs ({'; '.join(diff)}); evaluating again",
                      flush=True)
            return [py, "tools/eval.py", "--ckpt", ckpt, *(["--test-height", str(t)] if t != h else []),
                    "--split", "test", "--out", str(report.parent), "--device", eval_device, *quiet_args]

        job = Job(stage, "eval" if t == h else "cross_eval", what, prepare, deps=(_train_stage(name, h, tag(seed)),),
                  model=name, outputs=(report.parent,), gpu=gpu and eval_device.startswith("cuda"),
                  finish=lambda: write_record(out, stage, recorded))
        return job, report

    reports: list[Path] = []
    seed_reports: dict[tuple[str, float], list[Path]] = {}
    evals: list[Job] = []
    for name in names:
        for h in heights:
            for seed in seeds:
                jobs.append(train_job(name, h, seed))
                job, report = eval_job(name, h, seed, h, f"evaluate {name} {h:g} m{seed_words(seed)}")
                jobs.append(job)  # right after its training: with one job at a time, train then evaluate
                evals.append(job)
                seed_reports.setdefault((name, h), []).append(report)
                if seed == primary:
                    reports.append(report)
    cross_reports: list[Path] = []
    if args.cross_height:
        for name in names:
            for h in heights:
                for t in heights:
                    if t == h:
                        cross_reports.append(eval_report_path(run_dir_of(name, h, primary), t))
                        continue
                    job, report = eval_job(name, h, primary, t, f"evaluate {name} trained at {h:g} m on {t:g} m")
                    jobs.append(job)
                    evals.append(job)
                    cross_reports.append(report)
    combine_cmd = [py, "tools/eval.py", "--combine", *map(str, reports), "--out", str(out / "combined")]
    jobs.append(Job("combine", "combine", "combine reports", lambda: combine_cmd,
                    deps=tuple(j.id for j in evals if j.kind == "eval"), outputs=(out / "combined",)))
    return jobs, reports, cross_reports, seed_reports


def _seed_section(study: dict, seeds: list[int], seed_reports: dict[tuple[str, float], list[Path]],
                  train_minutes: dict[tuple[str, float], float]) -> list[str]:
    """With several seeds: study["seeds"] and study.md's section: the detector table (seed means with the
    interval of scenes and seeds, the paper's Table VII recall, training minutes), every resolved pair of
    models, then per model and height the mean over seeds next to the single-seed scene bootstrap interval."""
    if len(seeds) < 2:
        return []
    groups = {}
    for key, paths in seed_reports.items():
        groups[key] = []
        for seed, path in zip(seeds, paths):
            rep = read_json(path)
            rep.setdefault("train_seed", seed)  # how the seed statistics name each run
            groups[key].append(rep)
    # detbench.studies.seeds: the seed mean per model and height with the interval of scenes and seeds, next to
    # the scene-only interval; a model or height called ahead only where that interval of its lead excludes 0
    leads = pairwise_leads(groups)
    study["seeds"] = {"seeds": seeds, "by_height": {f"{h:g}": cell for h, cell in seed_summary(groups).items()},
                      "by_model": seed_height_summary(groups),
                      "pairs": {f"{h:g}": cell for h, cell in leads.items()},
                      "train_minutes": {f"{m} {h:g}": round(t, 2) for (m, h), t in train_minutes.items()}}
    return ["**Which detector** (seed means; small range 0-50 m, moderate 0-100 m, large 0-150 m; training "
            "minutes: the mean over seeds of each run's training epochs):", "",
            *detector_table(groups, train_minutes), "", *pairwise_markdown(leads), "", *seed_markdown(groups), ""]


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def _check_executor_options(args: StudyOptions) -> None:
    """UserError for --jobs, --executor, --address or --seeds that cannot work (before anything is created)."""
    if args.jobs is not None and args.jobs < 1:
        raise UserError(f"--jobs {args.jobs}: the number of jobs at once is at least 1 (leave it out for one per "
                        f"free CPU core, or one per GPU with --device cuda)")
    if args.executor not in ("local", "ray"):
        raise UserError(f"--executor {args.executor}: one of local, ray")
    if args.address and args.executor != "ray":
        raise UserError(f"--address {args.address} names a Ray cluster: add --executor ray")
    if args.executor == "ray":
        from detbench.studies.ray_executor import import_ray

        import_ray()  # not installed: the install command
    bad = [s for s in (args.seeds or []) if s < 0]
    if bad:
        raise UserError(f"--seeds {' '.join(map(str, bad))}: a training seed is a whole number >= 0, "
                        f"e.g. --seeds 0 1 2")


def _executor(args: StudyOptions, gpu: bool, repo: str | os.PathLike):
    """The executor of the study's jobs: local (--jobs N at once, default one per free CPU core or per GPU)
    or Ray (--executor ray --address ADDR; --jobs caps the jobs at once)."""
    if args.executor == "ray":
        from detbench.studies.ray_executor import RayExecutor

        return RayExecutor(address=args.address, cwd=repo, gpu=gpu, slots=args.jobs)
    devices = cuda_devices() if gpu else None
    return LocalExecutor(args.jobs or default_jobs("cuda" if gpu else "cpu"), cwd=repo, devices=devices)


def _train_stage(name: str, h: float, seed: int | None = None) -> str:
    return f"train_{name}_h{h:g}" + ("" if seed is None else f"_s{seed}")


def _eval_stage(name: str, h: float, t: float, seed: int | None = None) -> str:
    return f"eval_{name}_h{h:g}_on_h{t:g}" + ("" if seed is None else f"_s{seed}")


__all__ = ["PRESET_CAVEATS", "StudyOptions", "run_study", "study_models"]
