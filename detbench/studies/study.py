"""The whole Height3 study: data, LiDAR detection ability, training and evaluation per model and height, report.

For a preset: (1) the dataset (the preset's simulated default, or a dataset on disk); (2) the
LiDAR detection-ability study at every height (tools/analyze.py); (3) each detector trained per
height on that height's training split (tools/train.py); (4) each evaluated on the same
height's test split, and with cross_height on the other heights' too (tools/eval.py); (5) the
combined report, and study.md opening with the summary of detbench.studies.study_summary.

`run_study` checks the arguments and claims OUT, then: the data and the splits' counts are made in
this process; the plan (detbench.studies.study_plan: names, heights, seeds, run folders, inputs) is
built once; every other stage is a job of the plan's graph (detbench.studies.study_jobs; each job a
tool in its own process, its log in OUT/logs/), run by detbench.studies.jobs as soon as the jobs it
needs have finished, several at once on this machine or on a Ray cluster
(detbench.studies.ray_executor); the finished outputs are read into study.json
(detbench.studies.study_results) and study.md is rendered from it (detbench.studies.study_report).
With --seeds each model and height is trained once per seed. A stage whose output exists and was
computed from the same inputs (detbench.studies.stage_inputs: the data's content, the stage's
config and settings) is skipped, so the study resumes. A stage whose inputs changed is recomputed
(the ability study, an evaluation) or, for a training run, refused with the reason before any
stage runs. The run folders follow detbench.train.run_layout.
"""
from __future__ import annotations

import json
import os
import sys
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from detbench.config import ConfigError
from detbench.data.errors import DatasetError
from detbench.data.frame import data_key, height_key, is_rig_key
from detbench.data.layout import read_info, same_scenes
from detbench.studies.cross_height import plot_cross_height
from detbench.studies.cpu_load import MachineLoad
from detbench.studies.executor import LocalExecutor
from detbench.studies.jobs import LOGS_DIR, check_graph, cuda_devices, default_jobs, job_counts, run_graph
from detbench.studies.registry import ModelRegistry
from detbench.studies.split_check import split_check_warnings
from detbench.studies.stage_inputs import RECORDS_DIR, FileHashes, changes, dataset_fingerprint, write_record
from detbench.studies.study_jobs import stale_trainings, study_jobs
from detbench.studies.study_plan import StudyPlan, build_plan
from detbench.studies.study_report import cross_height_file_markdown, study_markdown
from detbench.studies.study_results import cross_height_figure, study_results
from detbench.train.run_config import load_run_config
from detbench.train.run_layout import STUDY_FOLDER, default_study_dir
from detbench.utils.cli import UserError, require_distinct
from detbench.utils.atomic import atomic_write_json, atomic_write_text, read_json
from detbench.utils.folder_locks import check_members_free, claim_folder, clear_folder
from detbench.utils.folder_ownership import FolderNotReplaceable, check_replaceable


@dataclass
class StudyOptions:
    """The study's settings (tools/study.py's arguments)."""

    preset: str = "quick"
    models: list[str] | None = None  # None: the preset's study.models, else every registered model
    heights: list[float] | None = None  # None: with `data` the heights it holds, else the preset's data.heights
    rigs: list[str] | None = None  # rigs by name instead of heights (configs/rigs.yaml; with `data`: the ones it holds)
    data: str | None = None  # a dataset on disk instead of the simulated default
    device: str = "auto"
    out: str | None = None  # None: run_layout.default_study_dir(preset)
    overrides: list[str] = field(default_factory=list)  # --set KEY=VALUE for every training run
    cross_height: bool = False
    fresh: bool = False  # empty OUT (a study's folder) first instead of resuming
    no_progress: bool = False
    jobs: int | None = None  # jobs at once; None: one per usable core (fewer under other load), GPU or Ray CPU
    executor: str = "local"  # local or ray
    address: str | None = None  # the Ray cluster (None: a local Ray instance)
    seeds: list[int] | None = None  # training seeds; None: the config's train.seed
    test_data: str | None = None  # a dataset whose test split the evaluations read (None: the training data's)


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
                          no_progress: bool = True, test_root: Path | None = None,
                          test_fingerprint: str | None = None) -> dict:
    """{"train": report, "test": report}: the ability study counted on each split of the dataset at `root`
    (hit counts of its points, as tools/analyze.py --data), the test split on `test_root`'s when given, kept in
    `out`/splits/<split>.json. A kept report is reused while its stage record (detbench.studies.stage_inputs:
    the heights and the data's content `fingerprint`, or `test_fingerprint` for the test split) still holds."""
    from detbench.studies.ability_run import AbilityOptions, run_ability

    reports = {}
    for split in ("train", "test"):
        other = split == "test" and test_root is not None
        inputs = {"heights": list(heights), "data_fingerprint": test_fingerprint if other else fingerprint}
        data = test_root if other else root
        path = out / "splits" / f"{split}.json"
        if path.is_file() and not changes(out, f"split_{split}", inputs):
            reports[split] = read_json(path)
            continue
        reports[split], _, _ = run_ability(AbilityOptions(data=str(data), split=split, heights=list(heights),
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
    require_distinct(args.models, "--models", what="model")
    try:
        names, left_out = study_models(args.preset, args.models, args.overrides, registry=registry)
        base_cfg = load_run_config(names[0], args.preset, overrides=args.overrides)
    except (ConfigError, ValueError, KeyError) as e:
        raise UserError(str(e).strip("'\"")) from None
    if args.data and not Path(args.data).is_dir():
        raise UserError(f"--data {args.data}: no such folder; give a dataset written by tools/simulate.py or "
                        f"python -m detbench.data.convert, or leave --data out for the simulated default")
    bad_heights = [h for h in (args.heights or []) if not (h > 0 and h < 10)]
    if bad_heights:
        raise UserError(f"--heights {' '.join(f'{h:g}' for h in bad_heights)}: a mounting height is a positive "
                        f"number of metres below 10, e.g. --heights 0.5 1.0 1.8")
    require_distinct(args.heights, "--heights", key=height_key, what="height")
    if args.rigs:
        heights = study_rigs(args.data, args.rigs, args.heights)
    else:
        heights = study_heights(args.data, args.heights, base_cfg["data"]["heights"])
    _check_test_data(args.test_data, heights)
    _check_executor_options(args)
    # only now, with the arguments known to be good, is anything deleted or created
    with ExitStack() as held:
        try:
            if args.fresh:  # before the claim: a refused --fresh creates nothing
                check_replaceable(out, True, STUDY_FOLDER, flag="--fresh", out="--out")
            held.enter_context(claim_folder(out, STUDY_FOLDER, "a study", notes=_note))
            if args.fresh:
                clear_folder(out, STUDY_FOLDER, flag="--fresh")
            else:  # a job of an earlier driver that still runs (the driver was killed): not a second writer
                check_members_free(out, "a job of an earlier run of this study that has not ended yet; wait for "
                                        "it to end (or stop it), then run the same command again")
        except FolderNotReplaceable as e:
            raise UserError(f"--out {e}") from None
        return _run_stages(args, out, names, left_out, heights, base_cfg, repo=repo)


def study_heights(data: str | None, heights: list[float] | None, preset_heights: list) -> list[float]:
    """The study's mounting heights (metres): `heights` (--heights) when given, else with `data` (--data) every
    height that dataset holds (its rigs go with --rigs), else the preset's data.heights. UserError for a dataset
    whose dataset.json cannot be read, that holds rigs only, or that lacks a height of `heights` (before anything
    is created)."""
    if not data:
        return list(heights) if heights else [float(h) for h in preset_heights]
    try:
        keys = list(read_info(data).heights)
    except DatasetError as e:
        raise UserError(f"--data {data}: {e}") from None
    held = {height_key(k): float(k) for k in keys if not is_rig_key(k)}  # a rig is studied with --rigs
    if not held and not heights:
        raise UserError(f"--data {data}: holds the rigs {', '.join(keys)} and no height; study them with --rigs "
                        f"{' '.join(keys)}")
    if not heights:
        return sorted(held.values())
    missing = [h for h in heights if height_key(h) not in held]
    if missing:
        have = ", ".join(f"{h:g} m" for h in sorted(held.values())) or "no height"
        raise UserError(f"--heights {' '.join(f'{h:g}' for h in missing)}: the dataset {data} holds {have}; give "
                        f"heights among them, or leave --heights out to study every height it holds")
    return list(heights)


def study_rigs(data: str | None, rigs: list[str], heights: list[float] | None) -> list[str]:
    """The study's rigs (--rigs), each studied where a height would be: with `data` (--data) rigs it holds, else
    rigs of configs/rigs.yaml (the study simulates them). UserError before anything is created for --heights
    beside them, a rig named twice, an unknown rig or one the dataset lacks."""
    from detbench.data.frame import RIG_NAME, is_rig_key

    if heights:
        raise UserError("--heights and --rigs: give one of them (a study compares heights or rigs)")
    require_distinct(rigs, "--rigs", what="rig")
    bad = [r for r in rigs if not (RIG_NAME.fullmatch(r) and is_rig_key(r))]
    if bad:
        raise UserError(f"--rigs {' '.join(bad)}: a rig's name starts with a letter (configs/rigs.yaml, docs/rigs.md)")
    if data:
        try:
            held = [k for k in read_info(data).heights if is_rig_key(k)]
        except DatasetError as e:
            raise UserError(f"--data {data}: {e}") from None
        where, fix = f"the dataset {data}", "simulate them into it (tools/simulate.py --rigs)"
    else:
        from detbench.sim.rigs import RIGS_CONFIG, load_rigs

        try:
            held = list(load_rigs())
        except ConfigError as e:
            raise UserError(str(e)) from None
        where, fix = RIGS_CONFIG.name, "add them there"
    missing = [r for r in rigs if r not in held]
    if missing:
        raise UserError(f"--rigs {' '.join(missing)}: not in {where}, which holds {', '.join(held) or 'no rig'}; "
                        f"give rigs among them, or {fix}")
    return list(rigs)


def _check_test_data(test_data: str | None, heights: list) -> None:
    """UserError before anything is created for --test-data that is no dataset or lacks a height (or rig) of
    the study."""
    if not test_data:
        return
    if not (Path(test_data) / "dataset.json").is_file():
        raise UserError(f"--test-data {test_data}: no dataset.json there; give a dataset written by "
                        f"tools/simulate.py (e.g. tools/simulate.py --out {test_data} --seed 1 ...) or python -m "
                        f"detbench.data.convert, or leave --test-data out to test on the training data's test split")
    try:
        held = list(read_info(test_data).heights)
    except DatasetError as e:
        raise UserError(f"--test-data {test_data}: {e}") from None
    missing = [h for h in heights if data_key(h) not in held]
    if missing:
        lacks = ", ".join(h if isinstance(h, str) else f"{h:g} m" for h in missing)
        raise UserError(f"--test-data {test_data}: lacks {lacks} (it holds {', '.join(map(str, held))}); simulate "
                        f"the test data at every height (or rig) of the study")


def _check_held_out(root: Path, info: dict, test_root: Path, test_info: dict) -> None:
    """UserError when the test data repeat the training data's scenes: two simulations with the same simulator
    preset, seed and overrides draw the same scenes (detbench.sim.simulator seeds each scene by (seed, scene)), so
    the training data's train scenes would be tested on."""
    if test_root == root:
        return
    src = info.get("source") or {}
    if same_scenes(src, test_info.get("source")):
        raise UserError(f"--test-data {test_root}: simulated with the training data's simulator preset, seed "
                        f"{src.get('seed')} and overrides, so its scenes repeat the training scenes of {root}; "
                        f"simulate the test data with another --seed (e.g. --seed {int(src.get('seed') or 0) + 1})")


def _note(text: str) -> None:
    print(f"note: {text}", file=sys.stderr, flush=True)


def _run_stages(args: StudyOptions, out: Path, names: list[str], left_out: list[str], heights: list[float],
                base_cfg: dict, *, repo: str | os.PathLike) -> tuple[Path, float]:
    """The study's stages in OUT (claimed and locked by `run_study`), then study.json and study.md."""
    t_start = time.perf_counter()
    if left_out:
        add = f"--models {' '.join(sorted(set(names) | set(left_out)))}"  # the study with them
        print(f"note: the {args.preset} preset's study leaves out {', '.join(left_out)} (study.models in "
              f"configs/presets/{args.preset}.yaml); add it with {add}", flush=True)
    # 1. data (in this process, before the graph: every job reads it)
    root, info = _dataset(args, base_cfg, heights)
    test_root = Path(args.test_data).resolve() if args.test_data else None
    test_info = read_json(test_root / "dataset.json") if test_root is not None else None
    if test_root is not None:
        _check_held_out(root, info, test_root, test_info)
        print(f"test data: {test_root} (the evaluations read its test split)", flush=True)
    hashes = FileHashes(out / RECORDS_DIR / "file_hashes.json")
    plan = build_plan(preset=args.preset, models=names, left_out=left_out, heights=heights, seeds=args.seeds,
                      base_cfg=base_cfg, out=out, data_root=root, data_info=info, hashes=hashes,
                      simulated=not args.data, overrides=args.overrides, device=args.device,
                      cross_height=args.cross_height, test_root=test_root,
                      test_info=test_info)
    # a finished training run computed from other inputs is refused here, before any stage runs
    stale = stale_trainings(plan)
    if stale:
        more = f" (and {len(stale) - 1} more run(s))" if len(stale) > 1 else ""
        raise UserError(f"--out {out}: the training run {stale[0]}{more} was computed from other inputs than this "
                        f"study's (data_fingerprint: the content of the dataset's files at that height), so its "
                        f"figures would be reported as this study's; run this study with another --out, or delete "
                        f"that run folder to train it again")
    hashes.save()
    # the splits counted like the ability study (in this process; compared with it after the graph)
    print("\n=== the train and test splits counted like the ability study", flush=True)
    split_ability_reports(root, heights, out, dataset_fingerprint(root, heights, hashes), no_progress=args.no_progress,
                          test_root=test_root,
                          test_fingerprint=None if test_root is None else dataset_fingerprint(test_root, heights,
                                                                                              hashes))
    hashes.save()
    # 2-5. the job graph: the ability study, each training, its evaluations, the combined report
    _run_jobs(args, plan, hashes, repo)
    seconds = time.perf_counter() - t_start
    study = json.loads(json.dumps(study_results(plan, seconds)))  # as study.json reads back
    for name, result in study["split_check"].items():
        for line in split_check_warnings(result, f"{name} split", "ability study"):
            print(line, file=sys.stderr)
    _write_report(out, study)
    return out / "study.md", seconds


def _dataset(args: StudyOptions, base_cfg: dict, heights: list[float]) -> tuple[Path, dict]:
    """(the dataset's root, its dataset.json or {}): --data, or the preset's simulated default at its heights
    and `heights`, simulated once into the cache."""
    from detbench.sim.dataset import default_dataset

    data_cfg = dict(base_cfg["data"])
    if args.data:
        data_cfg["root"] = str(Path(args.data).resolve())
    elif any(isinstance(h, str) for h in heights):  # rigs: a dataset of those rigs alone
        data_cfg["heights"] = list(heights)
    else:
        data_cfg["heights"] = sorted(set(map(float, data_cfg["heights"])) | set(heights))
    print(f"\n=== dataset ({args.preset} preset)", flush=True)
    root = default_dataset(data_cfg, progress=not args.no_progress)
    print(f"dataset: {root}")
    return root, (read_json(root / "dataset.json") if (root / "dataset.json").is_file() else {})


def _run_jobs(args: StudyOptions, plan: StudyPlan, hashes: FileHashes, repo: str | os.PathLike) -> None:
    """Run the plan's job graph on this machine or on Ray; each job's log in OUT/logs/."""
    gpu = args.device.startswith("cuda") or (args.device == "auto" and _cuda_available())
    executor = _executor(args, gpu, repo)
    try:  # until run_graph owns it (it closes it whatever happens): a Ray connection is not left open
        # several jobs at once (or on Ray) write to their logs only: progress bars there are one endless line of
        # carriage returns, so the jobs print their per-epoch and summary lines instead
        logs_only = args.executor == "ray" or executor.slots > 1
        jobs = study_jobs(plan, hashes, gpu=gpu, progress=not (args.no_progress or logs_only))
        check_graph(jobs)
    except BaseException:
        executor.close()
        raise
    counts = job_counts(jobs)
    where = ("Ray" if args.executor == "ray" else "this machine") + (" (GPUs)" if gpu else "")
    print(f"\n=== {len(jobs)} jobs ({', '.join(f'{n} {k}' for k, n in counts.items())}), up to {executor.slots} at "
          f"once on {where}; each job's output in {plan.out / LOGS_DIR}/<job>.log", flush=True)
    try:
        run_graph(jobs, executor, plan.out / LOGS_DIR)
    finally:
        hashes.save()


def _write_report(out: Path, study: dict) -> None:
    """study.json, study.md and, with cross-height evaluations, OUT/cross_height/ (matrices, figures, Markdown)."""
    if study.get("cross_height"):
        mats = study["cross_height"]
        (out / "cross_height").mkdir(exist_ok=True)
        atomic_write_json(out / "cross_height" / "cross_height.json", {"matrices": mats})
        for mat in mats:
            plot_cross_height(mat, cross_height_figure(out, mat["metric"], mat["range"]))
        atomic_write_text(out / "cross_height" / "cross_height.md", cross_height_file_markdown(study))
    atomic_write_json(out / "study.json", study)
    atomic_write_text(out / "study.md", study_markdown(study))


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def _check_executor_options(args: StudyOptions) -> None:
    """UserError for --jobs, --executor, --address or --seeds that cannot work (before anything is created)."""
    if args.jobs is not None and args.jobs < 1:
        raise UserError(f"--jobs {args.jobs}: the number of jobs at once is at least 1 (leave it out for one per "
                        f"CPU core this process may use, or one per GPU with --device cuda)")
    if args.executor not in ("local", "ray"):
        raise UserError(f"--executor {args.executor}: one of local, ray")
    if args.address and args.executor != "ray":
        raise UserError(f"--address {args.address} names a Ray cluster: add --executor ray")
    if args.executor == "ray":
        from detbench.studies.ray_executor import import_ray

        import_ray()  # not installed: the install command
    require_distinct(args.seeds, "--seeds", what="seed")
    bad = [s for s in (args.seeds or []) if s < 0]
    if bad:
        raise UserError(f"--seeds {' '.join(map(str, bad))}: a training seed is a whole number >= 0, "
                        f"e.g. --seeds 0 1 2")


def _executor(args: StudyOptions, gpu: bool, repo: str | os.PathLike):
    """The executor of the study's jobs: local (--jobs N at once; default one per GPU, or one per CPU core this
    process may use, fewer while the machine's other load keeps cores busy) or Ray (--executor ray --address
    ADDR; --jobs caps the jobs at once)."""
    if args.executor == "ray":
        from detbench.studies.ray_executor import RayExecutor

        return RayExecutor(address=args.address, cwd=repo, gpu=gpu, slots=args.jobs)
    if gpu:
        return LocalExecutor(args.jobs or default_jobs("cuda"), cwd=repo, devices=cuda_devices())
    if args.jobs:  # a fixed number, whatever else runs
        return LocalExecutor(args.jobs, cwd=repo)
    return LocalExecutor(default_jobs("cpu"), cwd=repo, load=MachineLoad())


__all__ = ["StudyOptions", "run_study", "study_heights", "study_models", "study_rigs"]
