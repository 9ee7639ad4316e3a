"""A study's plan, built once before anything runs: what is trained, evaluated and reported, and where.

`StudyPlan` holds the names (preset, models, the registered models the preset leaves out), the
mounting heights, the training seeds (the first one's reports make the combined report and the
summary), the run folders, the dataset with its content fingerprint per height, each stage's inputs
(`detbench.studies.stage_inputs`) and the config values the report states. Everything after it
reads the plan: the job graph (`detbench.studies.study_jobs`), the finished outputs read into
study.json (`detbench.studies.study_results`) and study.md rendered from study.json
(`detbench.studies.study_report`).

Run folders (detbench.train.run_layout): the config's own train.seed keeps `model_hH`; every other
seed trains into `model_hH_sS` with --set train.seed=S.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from detbench.data.errors import DatasetError
from detbench.data.frame import key_text
from detbench.studies.stage_inputs import FileHashes, config_digest, dataset_fingerprint, training_config
from detbench.train.run_config import load_run_config
from detbench.train.run_layout import eval_report_path, study_run_dir
from detbench.utils.cli import UserError

PAPER_PRESET = "paper"  # the preset at the paper's scale, which the report names for paper-scale figures


@dataclass(frozen=True)
class AbilitySource:
    """Where the ability study counts: `frames` simulated frames (counts only) of the simulator preset
    `sim_preset` with `seed` and `sim_overrides` (--set KEY=VALUE), or, with frames 0, every frame of the data."""

    frames: int = 0
    seed: int = 0
    sim_preset: str = "paper"
    sim_overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class PresetFacts:
    """What the report states of the preset: each model's training epochs (with the study's --set), and the
    paper preset's frames and each model's epochs there."""

    epochs: Mapping[str, int]
    paper_frames: int
    paper_epochs: Mapping[str, int]


@dataclass(frozen=True)
class StudyPlan:
    """The study's plan (see the module's docstring). Heights in metres; mappings are read-only by convention."""

    preset: str
    models: tuple[str, ...]
    left_out: tuple[str, ...]  # registered models the preset's study.models leaves out (none with --models)
    heights: tuple[float, ...]
    seeds: tuple[int, ...]  # training seeds; the first is the primary one
    config_seed: int  # the config's train.seed: its runs keep the folder model_hH
    out: Path
    data_root: Path
    data_info: Mapping  # dataset.json ({} where there is none)
    data_fingerprints: Mapping[float, str]  # per height: the content of the dataset's files at that height
    ability: AbilitySource
    ability_inputs: Mapping  # the ability study's stage inputs
    train_inputs: Mapping[tuple[str, float, int], Mapping]  # (model, height, seed): its training's stage inputs
    eval_digests: Mapping[str, str]  # model: the digest of its eval config (an evaluation's stage input)
    overrides: tuple[str, ...] = ()  # --set KEY=VALUE for every training
    device: str = "auto"
    cross_height: bool = False
    facts: PresetFacts | None = None
    test_root: Path | None = None  # the dataset whose test split the evaluations read (None: data_root's)
    test_info: Mapping | None = None  # its dataset.json
    test_fingerprints: Mapping[float, str] | None = None  # per height: the content of its files at that height

    @property
    def eval_fingerprints(self) -> Mapping[float, str]:
        """Per height: the content of the files the evaluations read (the test data's, else the dataset's)."""
        return self.data_fingerprints if self.test_fingerprints is None else self.test_fingerprints

    @property
    def primary(self) -> int:
        return self.seeds[0]

    def tag(self, seed: int) -> int | None:
        """The seed in a run folder's name: None for the config's own seed."""
        return None if seed == self.config_seed else seed

    def seed_overrides(self, seed: int) -> tuple[str, ...]:
        return _seed_overrides(seed, self.config_seed)

    def run_dir(self, model: str, height: float, seed: int) -> Path:
        return study_run_dir(self.out, model, height, self.tag(seed))

    def report(self, model: str, height: float, seed: int, test_height: float | None = None) -> Path:
        """The report.json of the run of (model, height, seed) on the test split at `test_height` (its own)."""
        return eval_report_path(self.run_dir(model, height, seed), height if test_height is None else test_height)

    def train_stage(self, model: str, height: float, seed: int) -> str:
        tag = self.tag(seed)
        return f"train_{model}_h{key_text(height)}" + ("" if tag is None else f"_s{tag}")

    def eval_stage(self, model: str, height: float, test_height: float, seed: int) -> str:
        tag = self.tag(seed)
        return f"eval_{model}_h{key_text(height)}_on_h{key_text(test_height)}" + ("" if tag is None else f"_s{tag}")

    def runs(self):
        """(model, height, seed) of every training, in the graph's order."""
        return [(m, h, s) for m in self.models for h in self.heights for s in self.seeds]


def build_plan(*, preset: str, models: list[str], left_out: list[str], heights: list[float], seeds: list[int] | None,
               base_cfg: Mapping, out: Path, data_root: Path, data_info: Mapping, hashes: FileHashes,
               simulated: bool, overrides: list[str] = (), device: str = "auto",
               cross_height: bool = False, test_root: Path | None = None,
               test_info: Mapping | None = None) -> StudyPlan:
    """The plan of a study on the dataset at `data_root` (made or found already), whose figures go to `out`.
    `simulated`: the data are the preset's simulated default, so the ability study may run on its own
    simulated stream (the config's study.ability_frames). `test_root`: a second dataset whose test split the
    evaluations read instead of `data_root`'s (the training still reads `data_root`'s train split). Raises
    UserError when the data cannot be read."""
    config_seed = int(base_cfg["train"]["seed"])
    seeds = list(dict.fromkeys(int(x) for x in seeds)) if seeds else [config_seed]
    try:
        fingerprints = {h: dataset_fingerprint(data_root, [h], hashes) for h in heights}
        test_fingerprints = (None if test_root is None
                             else {h: dataset_fingerprint(test_root, [h], hashes) for h in heights})
    except (DatasetError, FileNotFoundError, ValueError) as e:
        raise UserError(str(e)) from None
    data_cfg = base_cfg["data"]
    rigs = any(isinstance(h, str) for h in heights)  # rigs are counted on the dataset's merged points
    frames = int((base_cfg.get("study") or {}).get("ability_frames", 0) or 0) if simulated and not rigs else 0
    sim_overrides = tuple(str(o) for o in data_cfg.get("sim_overrides") or [])
    ability = AbilitySource(frames=frames, seed=data_cfg.get("seed", 0),
                            sim_preset=str(data_cfg.get("sim_preset", "paper")), sim_overrides=sim_overrides)
    if frames:
        ability_inputs = {"heights": list(heights), "simulate": frames, "seed": ability.seed,
                          "sim_preset": ability.sim_preset, "sim_overrides": [x for o in sim_overrides
                                                                             for x in ("--set", o)]}
    else:
        ability_inputs = {"heights": list(heights), "data_fingerprint": dataset_fingerprint(data_root, heights, hashes)}
    train_inputs = {(m, h, s): {"model": m, "height": h, "preset": preset,
                                "config": training_config(load_run_config(
                                    m, preset, overrides=[*overrides, *_seed_overrides(s, config_seed)])),
                                "data_fingerprint": fingerprints[h]}
                    for m in models for h in heights for s in seeds}
    eval_digests = {m: config_digest(load_run_config(m, preset, overrides=list(overrides))["eval"]) for m in models}
    return StudyPlan(preset=preset, models=tuple(models), left_out=tuple(left_out), heights=tuple(heights),
                     seeds=tuple(seeds), config_seed=config_seed, out=out, data_root=data_root, data_info=data_info,
                     data_fingerprints=fingerprints, ability=ability, ability_inputs=ability_inputs,
                     train_inputs=train_inputs, eval_digests=eval_digests, overrides=tuple(overrides), device=device,
                     cross_height=cross_height, facts=preset_facts(models, preset, overrides), test_root=test_root,
                     test_info=test_info, test_fingerprints=test_fingerprints)


def _seed_overrides(seed: int, config_seed: int) -> tuple[str, ...]:
    """--set train.seed=S for a seed other than the config's own."""
    return () if seed == config_seed else (f"train.seed={seed}",)


def preset_facts(models, preset: str, overrides=()) -> PresetFacts:
    """Each model's training epochs at `preset` (with `overrides`), the paper preset's frames and each model's
    epochs there, for the report."""
    cfgs = {m: load_run_config(m, preset, overrides=list(overrides)) for m in models}
    paper = {m: load_run_config(m, PAPER_PRESET) for m in models}
    return PresetFacts(epochs={m: int(c["train"]["epochs"]) for m, c in cfgs.items()},
                       paper_frames=int(paper[models[0]]["data"]["frames"]),
                       paper_epochs={m: int(c["train"]["epochs"]) for m, c in paper.items()})




def preset_description(preset: str, models: list[str]) -> str:
    """What a preset is, from its config: "48 frames, 2 epochs, every detector" (the detection data's frames,
    the training epochs of `models`, its study.models)."""
    cfgs = {m: load_run_config(m, preset) for m in models}
    first = cfgs[models[0]]
    epochs = sorted({int(c["train"]["epochs"]) for c in cfgs.values()})
    studied = [str(m) for m in (first.get("study") or {}).get("models") or []]
    return (f"{first['data']['frames']} frames, {epochs[0]}{'' if len(epochs) == 1 else f'-{epochs[-1]}'} epochs, "
            + (" ".join(studied) if studied else "every detector"))


__all__ = ["AbilitySource", "PAPER_PRESET", "PresetFacts", "StudyPlan", "build_plan", "preset_description",
           "preset_facts"]
