"""A study's plan as a graph of jobs: the ability study, each training, its evaluations, the combined report.

`study_jobs(plan, hashes)` builds the graph (detbench.studies.jobs) from a `StudyPlan`. Each job's
stage is an object here that decides, when the job becomes ready, what it runs (`command`: the
tool's command from detbench.studies.commands, or None when its output is current) and records
what it was computed from once it succeeded (`record`, detbench.studies.stage_inputs):

- the ability study (no dependencies: the data exist) on the preset's own simulated stream, or on
  every frame of the dataset; recomputed when its inputs changed;
- per model, height and seed a training (no dependencies), resumed from its checkpoints when it
  was stopped; its stage record is written before it starts, so a killed run resumes with it;
- its evaluation at its own height (after the training), and with cross_height those of the
  primary seed at the other heights, on the test split of the dataset or of the plan's test data;
  recomputed when the checkpoint, the test data or the eval config changed;
- the combined report of the primary seed's evaluations (after every evaluation at its height).

`stale_trainings(plan)` lists the finished or started trainings computed from other inputs than the
plan's: the study refuses them before any job runs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from detbench.data.frame import key_label
from detbench.studies.commands import TrainSpec, ability_command, combine_command, eval_command, train_command
from detbench.studies.jobs import Job
from detbench.studies.stage_inputs import FileHashes, changes, config_digest, write_record
from detbench.studies.study_plan import StudyPlan
from detbench.train.checkpoint import CheckpointManager
from detbench.utils.atomic import read_json


def _note(text: str) -> None:
    print(f"note: {text}", flush=True)


@dataclass
class AbilityStage:
    """The LiDAR detection ability at every height of the plan."""

    plan: StudyPlan
    progress: bool = False

    def command(self) -> list[str] | None:
        plan = self.plan
        ability_json = plan.out / "ability" / "ability.json"
        diff = changes(plan.out, "ability", plan.ability_inputs) if ability_json.is_file() else None
        if ability_json.is_file() and not diff:
            return None
        if diff:
            _note(f"{ability_json} was computed from other inputs ({'; '.join(diff)}); computing it again")
        src = plan.ability
        return ability_command(plan.heights, plan.out / "ability", data=None if src.frames else plan.data_root,
                               simulate=src.frames, seed=src.seed, sim_preset=src.sim_preset,
                               sim_overrides=src.sim_overrides, progress=self.progress)

    def record(self) -> None:
        write_record(self.plan.out, "ability", self.plan.ability_inputs)


@dataclass
class TrainStage:
    """One training of (model, height, seed)."""

    plan: StudyPlan
    model: str
    height: float
    seed: int
    progress: bool = False

    @property
    def inputs(self):
        return self.plan.train_inputs[(self.model, self.height, self.seed)]

    def command(self) -> list[str] | None:
        plan = self.plan
        self.record()  # a killed run resumes with it
        return train_command(TrainSpec(
            model=self.model, height=self.height, preset=plan.preset, data=plan.data_root, device=plan.device,
            out=plan.run_dir(self.model, self.height, self.seed),
            overrides=(*plan.overrides, *plan.seed_overrides(self.seed)), progress=self.progress))

    def record(self) -> None:
        write_record(self.plan.out, self.plan.train_stage(self.model, self.height, self.seed), self.inputs)


@dataclass
class EvalStage:
    """The checkpoint trained at `height` evaluated on the test split at `test_height`."""

    plan: StudyPlan
    hashes: FileHashes
    model: str
    height: float
    test_height: float
    seed: int
    progress: bool = False
    recorded: dict = field(default_factory=dict)  # the inputs found when it became ready

    @property
    def device(self) -> str:
        return "cpu" if self.plan.device == "auto" else self.plan.device

    def command(self) -> list[str] | None:
        """Evaluate, unless the report holds this evaluation already (same checkpoint, data and eval config)."""
        plan = self.plan
        run_dir = plan.run_dir(self.model, self.height, self.seed)
        report = plan.report(self.model, self.height, self.seed, self.test_height)
        ckpt = read_json(run_dir / "train_summary.json")["checkpoint"]
        inputs = {"train": config_digest(plan.train_inputs[(self.model, self.height, self.seed)]),
                  "checkpoint": self.hashes.sha1(ckpt), "test_height": self.test_height,
                  "data_fingerprint": plan.eval_fingerprints[self.test_height],
                  "eval": plan.eval_digests[self.model]}
        self.hashes.save()
        self.recorded.update(inputs)
        stage = plan.eval_stage(self.model, self.height, self.test_height, self.seed)
        diff = changes(plan.out, stage, inputs) if report.is_file() else None
        if report.is_file() and not diff:
            return None
        if diff:
            _note(f"{report} was computed from other inputs ({'; '.join(diff)}); evaluating again")
        return eval_command(ckpt, self.height, self.test_height, report.parent, self.device, data=plan.test_root,
                            progress=self.progress)

    def record(self) -> None:
        write_record(self.plan.out, self.plan.eval_stage(self.model, self.height, self.test_height, self.seed),
                     self.recorded)


@dataclass
class CombineStage:
    """The primary seed's evaluations at their own heights in one table (always rewritten)."""

    plan: StudyPlan

    def command(self) -> list[str]:
        plan = self.plan
        reports = [plan.report(m, h, plan.primary) for m in plan.models for h in plan.heights]
        return combine_command(reports, plan.out / "combined")


def study_jobs(plan: StudyPlan, hashes: FileHashes, *, gpu: bool = False, progress: bool = False) -> list[Job]:
    """The study's job graph, in the order a single worker runs it (each evaluation right after its
    training). `gpu`: trainings (and evaluations on a CUDA device) ask for a GPU; `progress`: progress bars."""
    def seed_words(seed: int) -> str:
        return "" if len(plan.seeds) == 1 else f" seed {seed}"

    ability = AbilityStage(plan, progress)
    what = (f"ability study ({plan.ability.frames} simulated frames)" if plan.ability.frames
            else "ability study (every frame)")
    jobs = [Job("ability", "ability", what, ability.command, outputs=(plan.out / "ability",), finish=ability.record)]
    evals = []
    for m, h, s in plan.runs():
        train = TrainStage(plan, m, h, s, progress)
        jobs.append(Job(plan.train_stage(m, h, s), "train", f"train {m} {key_label(h)}{seed_words(s)}", train.command,
                        model=m, outputs=(plan.run_dir(m, h, s),), gpu=gpu, finish=train.record))
        evals.append(_eval_job(plan, hashes, m, h, h, s, f"evaluate {m} {key_label(h)}{seed_words(s)}", gpu, progress))
        jobs.append(evals[-1])
    if plan.cross_height:
        for m in plan.models:
            for h in plan.heights:
                jobs += [_eval_job(plan, hashes, m, h, t, plan.primary,
                                   f"evaluate {m} trained at {key_label(h)} on {key_label(t)}", gpu, progress)
                         for t in plan.heights if t != h]
    combine = CombineStage(plan)
    jobs.append(Job("combine", "combine", "combine reports", combine.command, deps=tuple(j.id for j in evals),
                    outputs=(plan.out / "combined",)))
    return jobs


def _eval_job(plan: StudyPlan, hashes: FileHashes, model: str, height: float, test_height: float, seed: int,
              what: str, gpu: bool, progress: bool) -> Job:
    stage = EvalStage(plan, hashes, model, height, test_height, seed, progress)
    return Job(plan.eval_stage(model, height, test_height, seed), "eval" if test_height == height else "cross_eval",
               what, stage.command, deps=(plan.train_stage(model, height, seed),), model=model,
               outputs=(plan.report(model, height, seed, test_height).parent,),
               gpu=gpu and stage.device.startswith("cuda"), finish=stage.record)


def stale_trainings(plan: StudyPlan) -> list[str]:
    """"<run folder> (<what changed>)" for every training of the plan that finished or started from other
    inputs than the plan's (its figures would be reported under this study's data and settings)."""
    stale = []
    for (m, h, s), inputs in plan.train_inputs.items():
        run_dir = plan.run_dir(m, h, s)
        started = (run_dir / "train_summary.json").is_file() or CheckpointManager(run_dir / "checkpoints").latest()
        diff = changes(plan.out, plan.train_stage(m, h, s), inputs) if started else []
        if diff:
            stale.append(f"{run_dir} ({'; '.join(diff)})")
    return stale


__all__ = ["AbilityStage", "CombineStage", "EvalStage", "TrainStage", "stale_trainings", "study_jobs"]
