"""The training loop: `train(model, train_set, cfg, out_dir, ...)`, readable top to bottom.

One call trains (or resumes) a detector that follows the contract `Detector` (detbench/train/detector.py):
AdamW + one-cycle LR stepped per batch, gradient clipping, mixed precision on CUDA only
(float32 master weights, dynamic loss scaling), seeded data order and augmentation, skipping
of steps whose loss or gradient is not finite (`max_nonfinite_steps` in a row stop the run), a
checkpoint at every epoch end (and on Ctrl-C), TensorBoard + history.json + a console line per
epoch, an optional evaluation callback, and DistributedDataParallel when launched by torchrun.

The file reads in the order a run goes: `train`; its set-up `_setup` (seed, model on its
device, loader, optimizer, schedule, `_resume`); per epoch `_train_epoch` (each batch one
`_step`: forward, loss, backward, the finiteness check, clip, optimizer and schedule; then
logging, the non-finite streak, mid-epoch checkpoints, the stop check); and `_end_epoch`
(averaged losses, checkpoint, evaluation, logs). `_Run` carries the run's objects and its
advancing `TrainState` between them. What it is given lives beside it: the `train` config
section (`TrainConfig`, detbench/train/train_config.py), the (epoch, index) batch sampler
(`EpochBatches`, detbench/train/dataset.py), the Ctrl-C / SIGTERM handling
(`StopRequest`, detbench/train/stop_request.py) and the seeds (detbench/train/rng.py).

Outputs in `out_dir`: config.yaml (the run config, written once the run is accepted: a
refused start or resume changes no file), checkpoints/epoch_EEE.pt (last `keep_checkpoints`
kept), tensorboard/ (event files), history.json (one record per epoch, written before the
epoch's checkpoint, so a kill at any point loses no completed epoch's line).

Non-finite steps. A step whose loss or gradient holds NaN or inf changes nothing: no optimizer
update, and the BatchNorm statistics its forward pass touched are put back (the learning-rate
schedule still advances, so it stays tied to the step count). It is reported on the console with
its frame ids, counted in TensorBoard (train/nonfinite_steps) and listed in the epoch's
history.json record (`nonfinite_steps`). `max_nonfinite_steps` such steps in a row stop the run
with `NonFiniteTrainingError` naming the frames and the newest checkpoint, which holds the
weights of the last good step (skipped steps never change the weights). Under mixed precision
(CUDA) an overflow of the *scaled* gradients is the GradScaler's business: the step changes nothing
(no update, BatchNorm statistics put back) and the scale is halved, as designed. Such a step is no
update either: it is left out of the epoch's averaged losses, counted in history.json
(`scaler_skipped_steps`) beside the scale at the epoch's end (`loss_scale`, also TensorBoard's
train/loss_scale), so a scale that keeps falling shows; it counts as non-finite only once the scale
is <= 1, i.e. when the unscaled gradient itself overflows. A non-finite step that is the model's
(a NaN loss, or under mixed precision a NaN / inf in the forward pass's outputs, cause "output",
which a loss that zeroes non-finite differences would hide) keeps the scale: halving it cannot
help, and occasional NaN steps would otherwise drive it down unseen.
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure
from torch import nn
from torch.utils.data import DataLoader
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from detbench.config import dump
from detbench.data.batch import Batch, Sample, collate
from detbench.train.checkpoint import CheckpointError, CheckpointManager, TrainState, load_checkpoint, restore_training
from detbench.train.dataset import EpochBatches
from detbench.train.detector import channels_last_2d
from detbench.train.distributed import DistInfo, any_rank, barrier, reduce_mean, sync_buffers, wrap_model
from detbench.train.logger import TrainLogger, bev_figure, format_epoch_summary
from detbench.train.optim import build_optimizer, build_scheduler
from detbench.train.precise_bn import recompute_bn_statistics
from detbench.train.rng import capture_rng_state, rank_seed, restore_rng_state, seed_everything, worker_init_fn
from detbench.train.stop_request import StopRequest
from detbench.train.train_config import RESUME_IGNORE_KEYS, TrainConfig
from detbench.utils.atomic import atomic_write_text, read_json, remove_stale_temporaries

__all__ = ["NonFiniteTrainingError", "TrainResult", "train"]

NONFINITE_RECORDS_PER_EPOCH = 20  # skipped steps listed in an epoch's history.json record (all are counted)


class NonFiniteTrainingError(FloatingPointError):
    """`max_nonfinite_steps` steps in a row had a NaN or inf loss or gradient; the run stopped."""


@dataclass
class TrainResult:
    """What `train` did."""

    out_dir: Path
    epochs_completed: int
    global_step: int
    last_checkpoint: Path | None  # newest checkpoint written or resumed from (None on ranks > 0)
    interrupted: bool  # stopped by Ctrl-C / SIGTERM; resume with resume=True
    history: list[dict] = field(default_factory=list)  # one record per completed epoch (rank 0)


def train(model: nn.Module, train_set, cfg: TrainConfig, out_dir: str | Path, *, model_name: str,
          run_config: Mapping, data_info: Mapping, dist_info: DistInfo | None = None, resume: bool = False,
          eval_fn: Callable[[nn.Module, int], Mapping[str, float]] | None = None, preview: Sample | None = None,
          resume_ignore_keys: Iterable[str] = RESUME_IGNORE_KEYS,
          stored_config: Callable[[Mapping], Mapping] | None = None,
          resume_hint: str = "run the same command again with --resume", progress: bool = True) -> TrainResult:
    """Train `model` on `train_set`, or resume the run in `out_dir`.

    Args:
        model: a `Detector` (detbench/train/detector.py): forward(Batch), loss(outputs, Batch),
            predict(outputs, Batch). Built by the caller after `seed_everything(cfg.seed)`;
            moved to the device here.
        train_set: a torch Dataset of `Sample`s indexed by (epoch, index) pairs (a `TrainingSet`)
            and, for the preview image, `point_cloud_range` and `get(i, epoch, augment)`.
        cfg: the parsed `train` section.
        out_dir: the run folder (checkpoints/, tensorboard/, history.json).
        model_name / run_config / data_info: stored in every checkpoint and checked on resume
            (data_info e.g. {"source": "/data/h3 or a simulator description", "height": 1.8}).
        dist_info: from `init_distributed` (default: one CPU process).
        resume: continue from the newest checkpoint in out_dir/checkpoints (a fresh start when
            there is none).
        eval_fn: `eval_fn(model, epoch) -> {metric: value}` run on rank 0, in eval mode under
            no_grad, every `cfg.eval_every` epochs and after the last one; the figures go to
            TensorBoard (eval/*), history.json and the console.
        preview: the frame drawn in the per-epoch bird's-eye image (default: the first training
            frame without augmentation).
        resume_ignore_keys: dotted config keys allowed to differ on resume.
        stored_config: on resume, turns the config a checkpoint stores into today's keys before it is compared
            with `run_config` (the model registry's upgrade of configs stored by earlier versions).
        resume_hint: how the user resumes, printed after Ctrl-C.
        progress: show tqdm bars (rank 0 only).
    Returns:
        TrainResult. After Ctrl-C / SIGTERM it returns `interrupted=True` once a checkpoint of
        the last completed step is written (resume replays the rest exactly on CPU).
    """
    info = dist_info or DistInfo()
    run = _setup(model, train_set, cfg, Path(out_dir), info, model_name=model_name, run_config=run_config,
                 data_info=data_info, resume=resume, resume_ignore_keys=resume_ignore_keys, stored_config=stored_config,
                 preview=preview)
    interrupted = False
    with StopRequest(announce=info.is_main) as stop:
        try:
            for epoch in range(run.state.epoch, cfg.epochs):
                epoch_run = _train_epoch(run, epoch, stop, progress)
                if epoch_run.interrupted:
                    interrupted = True
                    break
                _end_epoch(run, epoch, epoch_run, eval_fn)
                if any_rank([stop.requested], info)[0] and epoch + 1 < cfg.epochs:
                    interrupted = True
                    break
        except NonFiniteTrainingError:
            run.logger.close()  # the TensorBoard events of the skipped steps reach the disk
            raise

    if interrupted and info.is_main:
        tqdm.write(f"Interrupted after {run.state.epoch} epoch(s) + {run.state.step_in_epoch} batch(es); checkpoint "
                   f"saved to {run.last_ckpt}. To resume: {resume_hint}")
    run.logger.close()
    return TrainResult(out_dir=run.out_dir, epochs_completed=run.state.epoch, global_step=run.state.global_step,
                       last_checkpoint=run.last_ckpt if info.is_main else None, interrupted=interrupted,
                       history=list(run.logger.history))


# ---- set-up: model, data, optimizer, schedule, resume ---------------------------------------
@dataclass
class _Run:
    """Everything one training run holds; `state` and `last_ckpt` advance as it goes."""

    cfg: TrainConfig
    info: DistInfo
    out_dir: Path
    core: nn.Module  # the model on its device
    ddp_model: nn.Module  # `core`, wrapped by DistributedDataParallel when distributed
    train_set: Any
    batches: EpochBatches
    loader: DataLoader
    loader_gen: torch.Generator
    steps_per_epoch: int
    optimizer: torch.optim.Optimizer
    scheduler: Any
    scaler: torch.amp.GradScaler
    use_amp: bool
    ckpts: CheckpointManager
    logger: TrainLogger
    preview: Sample | None
    checkpoint_meta: dict  # model_name, config and data: stored in every checkpoint, checked on resume
    state: TrainState
    last_ckpt: Path | None = None
    nonfinite_streak: int = 0  # skipped non-finite steps in a row (across epochs)

    def save(self, state: TrainState, recompute_bn: bool = True) -> Path | None:
        """Write a checkpoint of `state` (rank 0; every rank takes part), its BatchNorm statistics first
        recomputed for its weights (`train.precise_bn_batches`) unless `recompute_bn` is false (a checkpoint
        only resume reads: see `_bn_recompute_due`). Returns its path on rank 0."""
        if recompute_bn and self.cfg.precise_bn_batches > 0:
            recompute_bn_statistics(self.core, _precise_bn_batches(self, state), _forward_batch)
            sync_buffers(self.core, self.info)
        rng_ranks = _gather_rng(self.info)  # every rank resumes its own generators
        path = None
        if self.info.is_main:
            path = self.ckpts.save(state, model=self.core, optimizer=self.optimizer, scheduler=self.scheduler,
                                   scaler=self.scaler, rng=rng_ranks, **self.checkpoint_meta)
        barrier(self.info)
        return path


def _precise_bn_batches(run: _Run, state: TrainState):
    """`train.precise_bn_batches` batches of augmented training samples for the BatchNorm statistics of the
    checkpoint of `state`: frames drawn by a generator seeded from the run's seed, this rank and the step (the
    training's own random streams are not touched), so a resumed run recomputes the same statistics."""
    cfg, n = run.cfg, len(run.train_set)
    rng = np.random.default_rng([cfg.seed, run.info.rank, state.global_step, 7919])
    order = rng.permutation(n)
    for k in range(cfg.precise_bn_batches):
        idx = [int(order[(k * cfg.batch_size + j) % n]) for j in range(cfg.batch_size)]
        yield collate([run.train_set[(state.epoch, i)] for i in idx]).to(run.info.device)


def _forward_batch(model: nn.Module, batch) -> None:
    model(batch)


def _gather_rng(info: DistInfo) -> list[dict]:
    """Every rank's generator states (rank order); a single entry without distribution."""
    state = capture_rng_state()
    if not info.distributed:
        return [state]
    import torch.distributed as dist

    out: list = [None] * info.world_size
    dist.all_gather_object(out, state)
    return out


def _setup(model: nn.Module, train_set, cfg: TrainConfig, out_dir: Path, info: DistInfo, *, model_name: str,
           run_config: Mapping, data_info: Mapping, resume: bool, resume_ignore_keys: Iterable[str],
           stored_config: Callable[[Mapping], Mapping] | None,
           preview: Sample | None) -> _Run:
    """Seed, move the model, build the loader, optimizer and schedule, then resume if asked."""
    device = info.device
    ckpts = CheckpointManager(out_dir / "checkpoints", keep_last=cfg.keep_checkpoints)
    if not resume and ckpts.latest() is not None:
        raise CheckpointError(f"{ckpts.directory} already holds checkpoints of an earlier run ({ckpts.latest().name}); "
                              f"add --resume to continue it, or choose another --out folder (or delete that one)")
    seed_everything(rank_seed(cfg.seed, info.rank))  # each rank its own draws; the weights are rank 0's (DDP)
    core = model.to(device)
    if cfg.channels_last:
        channels_last_2d(core)
    sampler = DistributedSampler(train_set, num_replicas=info.world_size, rank=info.rank, shuffle=True,
                                 seed=cfg.seed, drop_last=False)
    batches = EpochBatches(sampler, cfg.batch_size, cfg.drop_last)
    steps_per_epoch = batches.full_length()
    if steps_per_epoch == 0:
        raise ValueError(f"the training set has {len(train_set)} frames, too few for one batch of {cfg.batch_size} "
                         f"per process with drop_last; lower train.batch_size or set train.drop_last=false")
    loader_gen = torch.Generator()
    # Workers are spawned, not forked: numba's OpenMP kernels (and CUDA) already running in this
    # process make a forked child abort. They persist across epochs, so the start-up is paid once.
    loader = DataLoader(train_set, batch_sampler=batches, num_workers=cfg.workers, collate_fn=collate,
                        worker_init_fn=worker_init_fn, generator=loader_gen, pin_memory=device.type == "cuda",
                        multiprocessing_context="spawn" if cfg.workers > 0 else None,
                        persistent_workers=cfg.workers > 0)
    optimizer = build_optimizer(core, cfg.lr, cfg.weight_decay, cfg.betas)
    scheduler = build_scheduler(optimizer, cfg.lr, cfg.epochs * steps_per_epoch, cfg.pct_start, cfg.div_factor,
                                cfg.final_div_factor, cfg.momentum_range)
    use_amp = _use_amp(cfg, device)
    scaler = torch.amp.GradScaler(device.type, enabled=use_amp)

    meta = {"config": run_config, "data": data_info, "model_name": model_name}
    state, last_ckpt, history = TrainState(seed=cfg.seed), None, []
    if resume:
        state, last_ckpt, history = _resume(ckpts, cfg, info, out_dir, meta, resume_ignore_keys, stored_config,
                                            model=core, optimizer=optimizer, scheduler=scheduler, scaler=scaler)
    if info.is_main:  # the run is accepted: from here on it may write
        remove_stale_temporaries(ckpts.directory)  # checkpoints a killed run was writing
        atomic_write_text(out_dir / "config.yaml", dump(run_config))
    ddp_model = wrap_model(core, info, cfg.find_unused_parameters)
    logger = TrainLogger(out_dir, enabled=info.is_main, tensorboard=cfg.tensorboard,
                         purge_step=state.global_step + 1 if last_ckpt is not None else None)
    logger.set_history(history)
    if preview is None and len(train_set) > 0 and hasattr(train_set, "get"):
        preview = train_set.get(0, 0, augment=False)
    return _Run(cfg=cfg, info=info, out_dir=out_dir, core=core, ddp_model=ddp_model, train_set=train_set,
                batches=batches, loader=loader, loader_gen=loader_gen, steps_per_epoch=steps_per_epoch,
                optimizer=optimizer, scheduler=scheduler, scaler=scaler, use_amp=use_amp, ckpts=ckpts, logger=logger,
                preview=preview, checkpoint_meta=meta, state=state, last_ckpt=last_ckpt)


def _resume(ckpts: CheckpointManager, cfg: TrainConfig, info: DistInfo, out_dir: Path, meta: dict,
            ignore_keys: Iterable[str], stored_config: Callable[[Mapping], Mapping] | None,
            **objects) -> tuple[TrainState, Path | None, list[dict]]:
    """(state, checkpoint, history so far) of the newest checkpoint, restored into `objects`
    (model, optimizer, scheduler, scaler); a fresh state when there is none."""
    last_ckpt = ckpts.latest()
    if last_ckpt is None:
        if info.is_main:
            tqdm.write(f"--resume: no checkpoint in {ckpts.directory}; starting a new run")
        return TrainState(seed=cfg.seed), None, []
    ckpt = load_checkpoint(last_ckpt, model_name=meta["model_name"], config=meta["config"], data=meta["data"],
                           ignore_keys=ignore_keys, stored_config=stored_config)
    state = restore_training(ckpt, path=last_ckpt, rank=info.rank, **objects)
    history = []
    if (out_dir / "history.json").is_file():
        history = [r for r in read_json(out_dir / "history.json").get("epochs", []) if r["epoch"] <= state.epoch]
    if info.is_main:
        done = " - already complete, nothing to do" if state.epoch >= cfg.epochs else ""
        tqdm.write(f"resuming from {last_ckpt} ({state.epoch} epochs + {state.step_in_epoch} batches done){done}")
    return state, last_ckpt, history


# ---- one epoch of steps ---------------------------------------------------------------------
@dataclass
class _EpochRun:
    """What an epoch's steps leave for its end: loss sums, counts, the last learning rate."""

    lr: float
    t0: float  # perf_counter at the epoch's start, seconds
    cpu0: float  # this process's CPU time (process_time) at the epoch's start, seconds
    sums: dict[str, float] = field(default_factory=dict)  # over the steps that updated the model
    n_steps: int = 0  # steps that updated the model
    n_frames: int = 0
    n_skipped: int = 0  # steps skipped for a non-finite loss or gradient
    n_scaler_skipped: int = 0  # steps the GradScaler skipped (scaled gradients overflowed; mixed precision)
    skipped: list[dict] = field(default_factory=list)  # the first NONFINITE_RECORDS_PER_EPOCH of them
    interrupted: bool = False  # stopped mid-epoch (a checkpoint of the last step is written)


@dataclass
class _StepResult:
    loss: float  # the step's loss (NaN or inf for a skipped step)
    parts: dict
    lr: float  # the rate this step used
    skipped: str | None  # what was not finite: "loss" or "gradient" (None: finite, see scaler_skipped)
    stop_requested: bool  # Ctrl-C / SIGTERM on any rank
    scaler_skipped: bool = False  # the scaled gradients overflowed: the GradScaler skipped the update


def _train_epoch(run: _Run, epoch: int, stop: StopRequest, progress: bool) -> _EpochRun:
    """The steps of `epoch` (from the resumed step on), with logging, mid-epoch checkpoints and the stop check."""
    cfg, info = run.cfg, run.info
    run.batches.set_epoch(epoch, skip=run.state.step_in_epoch if epoch == run.state.epoch else 0)
    run.loader_gen.manual_seed(cfg.seed * 100_003 + epoch)
    run.core.train()
    ep = _EpochRun(lr=run.optimizer.param_groups[0]["lr"], t0=time.perf_counter(), cpu0=time.process_time())
    bar = tqdm(stop.start_iter(run.loader), total=len(run.batches), desc=f"epoch {epoch + 1}/{cfg.epochs}",
               unit="batch", disable=not (progress and info.is_main), leave=False, dynamic_ncols=True)
    try:
        for batch in bar:
            batch: Batch = batch.to(info.device, non_blocking=True)
            res = _step(run, batch, stop)
            ep.lr = res.lr

            run.state = TrainState(epoch, run.state.step_in_epoch + 1, run.state.global_step + 1, cfg.seed)
            ep.n_frames += batch.batch_size
            if res.skipped is not None:
                _nonfinite_step(run, ep, epoch, batch, res)
            elif res.scaler_skipped:  # no update: not in the epoch's losses, counted apart
                ep.n_scaler_skipped += 1
                if info.is_main:
                    run.logger.scalars({"loss_scale": run.scaler.get_scale()}, run.state.global_step, prefix="train/")
            else:
                run.nonfinite_streak = 0
                ep.n_steps += 1
                values = {"loss": res.loss, **{k: float(v) for k, v in res.parts.items()}}
                for k, v in values.items():
                    ep.sums[k] = ep.sums.get(k, 0.0) + v
                if info.is_main and run.state.global_step % cfg.log_every == 0:
                    run.logger.scalars({**values, "lr": ep.lr}, run.state.global_step, prefix="train/")
            bar.set_postfix(loss=f"{res.loss:.4f}", lr=f"{ep.lr:.2e}", refresh=False)

            at_epoch_end = run.state.step_in_epoch == run.steps_per_epoch
            stop_now = res.stop_requested
            if not at_epoch_end and (stop_now or (cfg.checkpoint_every_steps
                                                  and run.state.global_step % cfg.checkpoint_every_steps == 0)):
                run.last_ckpt = run.save(run.state) or run.last_ckpt
                if stop_now:
                    ep.interrupted = True
                    break
    finally:
        bar.close()
    return ep


def _step(run: _Run, batch: Batch, stop: StopRequest) -> _StepResult:
    """One optimisation step on `batch` (already on the device), or none when its loss or gradient is not finite.

    Mixed precision: the forward pass runs under float16 autocast while the parameters and the
    optimizer state stay float32 (the master copy); the loss is scaled before backward and the
    gradients unscaled (in float32) before clipping and the update. A skipped step (a non-finite
    loss or gradient, or scaled gradients that overflowed, which the GradScaler skips) leaves the
    weights, the optimizer state and the BatchNorm statistics as they were.
    """
    saved = _float_buffers(run.core)
    with torch.autocast(device_type=run.info.device.type, dtype=torch.float16, enabled=run.use_amp):
        outputs = run.ddp_model(batch)
        loss, parts = run.core.loss(outputs, batch)
    outputs_finite = not run.use_amp or _all_finite(outputs)
    run.optimizer.zero_grad(set_to_none=True)
    run.scaler.scale(loss).backward()  # every rank runs backward (DDP's all-reduce), finite or not
    loss_value = float(loss.detach())
    if run.use_amp:
        run.scaler.unscale_(run.optimizer)  # float32 gradients, ready for the check and clipping
    grads = _grads(run.core)
    norm = _grad_norm(grads)
    grads_finite = bool(torch.isfinite(norm))
    scaler_owns = run.use_amp and run.scaler.get_scale() > 1.0  # an overflow of scaled gradients is the scaler's
    if not math.isfinite(loss_value):
        cause = "loss"
    elif not outputs_finite:  # a float16 overflow in the forward pass that the loss does not show
        cause = "output"
    elif not grads_finite and not scaler_owns:
        cause = "gradient"
    else:
        cause = None
    overflow = cause is None and not grads_finite  # the scaler skips this step and halves its scale
    stop_requested, bad, overflow = any_rank([stop.requested, cause is not None, overflow], run.info)
    lr = run.optimizer.param_groups[0]["lr"]
    if bad or overflow:
        for buf, copy in saved:
            buf.copy_(copy)
        if run.use_amp:  # halves the scale for an overflow of the scaled gradients, keeps it for the model's fault
            run.scaler.update(None if overflow and not bad else run.scaler.get_scale())
        with warnings.catch_warnings():  # "scheduler.step() before optimizer.step()" when the first step is skipped
            warnings.simplefilter("ignore", UserWarning)
            run.scheduler.step()
        if bad:
            return _StepResult(loss_value, parts, lr, cause or "loss or gradient on another process", stop_requested)
        return _StepResult(loss_value, parts, lr, None, stop_requested, scaler_skipped=True)
    if run.cfg.grad_clip > 0:
        _clip_(grads, norm, run.cfg.grad_clip)
    run.scaler.step(run.optimizer)  # plain optimizer.step() without mixed precision
    run.scaler.update()
    run.scheduler.step()
    return _StepResult(loss_value, parts, lr, None, stop_requested)


def _nonfinite_step(run: _Run, ep: _EpochRun, epoch: int, batch: Batch, res: _StepResult) -> None:
    """Report a skipped step; stop the run after `max_nonfinite_steps` in a row."""
    cfg, info = run.cfg, run.info
    run.nonfinite_streak += 1
    ep.n_skipped += 1
    record = {"epoch": epoch + 1, "step_in_epoch": run.state.step_in_epoch, "global_step": run.state.global_step,
              "nonfinite": res.skipped, "loss": repr(res.loss) if not math.isfinite(res.loss) else res.loss,
              "frames": list(batch.frame_ids)}
    if len(ep.skipped) < NONFINITE_RECORDS_PER_EPOCH:
        ep.skipped.append(record)
    if info.is_main:
        tqdm.write(f"epoch {epoch + 1}, step {run.state.step_in_epoch}: non-finite {res.skipped} (loss {res.loss}); "
                   f"step skipped, the model is unchanged ({run.nonfinite_streak} in a row, "
                   f"{cfg.max_nonfinite_steps} stop the run); frames {list(batch.frame_ids)}")
        run.logger.scalars({"nonfinite_steps": run.nonfinite_streak}, run.state.global_step, prefix="train/")
    if run.nonfinite_streak >= cfg.max_nonfinite_steps:
        last = run.ckpts.latest()
        good = (f"the newest checkpoint, {last}, holds the weights of the last step with a finite loss and "
                f"gradient (skipped steps change no weight; if that step's update is what broke the model, take an "
                f"earlier checkpoint of {last.parent})") if last else "no checkpoint was written yet"
        raise NonFiniteTrainingError(
            f"{run.nonfinite_streak} steps in a row had a non-finite loss or gradient (the last at epoch {epoch + 1}, "
            f"step {run.state.step_in_epoch}: {res.skipped}; frames {list(batch.frame_ids)}; loss parts "
            f"{ {k: float(v) for k, v in res.parts.items()} }); the run stopped. {good}. Lower train.lr, set "
            f"train.grad_clip, or check those frames (tools/validate.py); train.max_nonfinite_steps sets how many "
            f"skipped steps in a row are tolerated")


def _use_amp(cfg: TrainConfig, device: torch.device) -> bool:
    """Mixed precision runs on CUDA only (CPU float16 kernels are slow and bfloat16 training is not tested)."""
    return cfg.amp and device.type == "cuda"


def _all_finite(outputs: Any) -> bool:
    """Every floating-point tensor in a model's outputs (named tuples, dataclasses, dicts, sequences) is finite;
    one host sync."""
    flags = []

    def walk(o):
        if isinstance(o, torch.Tensor):
            if o.is_floating_point():
                flags.append(torch.isfinite(o).all())
        elif dataclasses.is_dataclass(o) and not isinstance(o, type):
            for f in dataclasses.fields(o):
                walk(getattr(o, f.name))
        elif isinstance(o, Mapping):
            for v in o.values():
                walk(v)
        elif isinstance(o, (list, tuple)):
            for v in o:
                walk(v)

    walk(outputs)
    return bool(torch.stack(flags).all()) if flags else True


def _float_buffers(model: nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(buffer, copy) of every buffer, taken before a forward pass that may have to be undone."""
    return [(b, b.detach().clone()) for b in model.buffers()]


def _grads(model: nn.Module) -> list[torch.Tensor]:
    return [p.grad for p in model.parameters() if p.grad is not None]


def _grad_norm(grads: list[torch.Tensor]) -> torch.Tensor:
    """Global L2 norm of the gradients (a tensor, NaN or inf when a gradient is not finite)."""
    if not grads:
        return torch.zeros(())
    return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g.detach(), 2.0).float() for g in grads]))


def _clip_(grads: list[torch.Tensor], norm: torch.Tensor, max_norm: float) -> None:
    """Scale the gradients so their global norm `norm` is at most `max_norm` (torch's clip_grad_norm_ rule)."""
    coef = torch.clamp(max_norm / (norm + 1e-6), max=1.0)
    for g in grads:
        g.detach().mul_(coef.to(g.device, g.dtype))


# ---- epoch end: checkpoint, evaluation, logs ---------------------------------------------------
def _end_epoch(run: _Run, epoch: int, ep: _EpochRun,
               eval_fn: Callable[[nn.Module, int], Mapping[str, float]] | None) -> None:
    """Average the losses over ranks, checkpoint, evaluate (rank 0) and log the epoch."""
    cfg, info, core = run.cfg, run.info, run.core
    run.state = TrainState(epoch + 1, 0, run.state.global_step, cfg.seed)
    losses = reduce_mean({k: v / max(ep.n_steps, 1) for k, v in ep.sums.items()}, info)
    seconds = time.perf_counter() - ep.t0
    cpu_seconds = time.process_time() - ep.cpu0  # the training process's own (its data workers are apart)
    frames_all = int(reduce_mean({"f": ep.n_frames}, info)["f"] * info.world_size)
    sync_buffers(core, info)  # every rank ends the epoch with the same BatchNorm statistics
    step, lr = run.state.global_step, ep.lr
    # the epoch's line goes to history.json before its checkpoint: a kill during the (long) evaluation
    # then loses only the metrics, and a kill before the checkpoint replays the epoch and its line
    record = {"epoch": epoch + 1, "global_step": step, "lr": lr, "seconds": round(seconds, 3),
              "cpu_seconds": round(cpu_seconds, 3), "frames": frames_all, "losses": losses, "metrics": {},
              "checkpoint": run.ckpts.name_for(run.state)}
    if ep.n_skipped:  # steps skipped for a non-finite loss or gradient (this rank's, listed with their frames)
        record.update(skipped_steps=ep.n_skipped, nonfinite_steps=ep.skipped)
    if run.use_amp:  # the steps the GradScaler skipped and where its scale ended: a collapsing scale shows
        record.update(scaler_skipped_steps=ep.n_scaler_skipped, loss_scale=run.scaler.get_scale())
    run.logger.add_epoch(record)
    run.last_ckpt = run.save(run.state, recompute_bn=_bn_recompute_due(run, epoch, eval_fn)) or run.last_ckpt
    if info.is_main:
        metrics = _evaluate(run, epoch, eval_fn)
        run.logger.scalars({**losses, "lr": lr, "seconds": seconds, "epoch": epoch + 1}, step, prefix="epoch/")
        run.logger.scalars(metrics, step, prefix="eval/")
        run.logger.set_last_metrics(metrics)
        tqdm.write(format_epoch_summary(epoch + 1, cfg.epochs, losses, lr, seconds, frames_all, metrics))
    barrier(info)


def _eval_due(run: _Run, epoch: int, eval_fn) -> bool:
    """Whether epoch `epoch` (0-based) ends with an evaluation: every `train.eval_every` epochs and the last."""
    return eval_fn is not None and ((epoch + 1) % run.cfg.eval_every == 0 or epoch + 1 == run.cfg.epochs)


def _preview_due(run: _Run) -> bool:
    """Whether an epoch ends with the bird's-eye preview in TensorBoard (`train.bev_image`)."""
    return run.cfg.bev_image and run.logger.writer is not None and run.preview is not None


def _bn_recompute_due(run: _Run, epoch: int, eval_fn) -> bool:
    """Whether the checkpoint of epoch `epoch` gets BatchNorm statistics recomputed for its weights: when its
    model is used in eval mode (an evaluation or the preview), when it is the last, and when every checkpoint is
    kept (`train.keep_checkpoints: 0`, e.g. for tools/curves.py). The others are only read by a resume, which
    needs no recomputation: train mode normalises with the batch's statistics, and a later recomputation
    replaces the running ones whole, so the trained weights and the last checkpoint are the same either way
    (as detectron2's PreciseBN, which recomputes before evaluations only)."""
    due = (epoch + 1 == run.cfg.epochs or run.cfg.keep_checkpoints == 0 or _eval_due(run, epoch, eval_fn)
           or _preview_due(run))
    # every rank takes part in the recomputation's buffer all-reduce, and only rank 0 writes the preview
    return any_rank([due], run.info)[0]


def _evaluate(run: _Run, epoch: int, eval_fn: Callable[[nn.Module, int], Mapping[str, float]] | None
              ) -> dict[str, float]:
    """The epoch's evaluation metrics (when due) and preview image; the training's random stream is untouched."""
    core = run.core
    metrics: dict[str, float] = {}
    rng_before = capture_rng_state()  # evaluation must not shift the training's random stream
    if _eval_due(run, epoch, eval_fn):
        core.eval()
        with torch.no_grad():
            metrics = {k: float(v) for k, v in dict(eval_fn(core, epoch + 1)).items()}
    if _preview_due(run):
        run.logger.preview("bev/predictions_vs_ground_truth", run.state.global_step,
                           lambda: _preview_figure(core, run.preview, run.train_set, epoch + 1, run.info.device),
                           f"the bird's-eye preview of epoch {epoch + 1}")
    restore_rng_state(rng_before)
    core.train()
    return metrics


def _preview_figure(model: nn.Module, preview: Sample, train_set, epoch: int, device: torch.device) -> Figure:
    """Run the model on the preview frame and draw the bird's-eye image (ground truth vs predictions)."""
    model.eval()
    with torch.no_grad():
        batch = collate([preview]).to(device)
        dets = model.predict(model(batch), batch)[0]
    boxes, scores, _ = dets.numpy()
    pc_range = getattr(train_set, "point_cloud_range", None)
    if pc_range is None:
        pts = preview.points
        pc_range = [pts[:, 0].min(), pts[:, 1].min(), 0.0, pts[:, 0].max() + 1e-3, pts[:, 1].max() + 1e-3, 1.0] \
            if len(pts) else [0.0, -1.0, 0.0, 1.0, 1.0, 1.0]
    return bev_figure(preview.points, preview.gt_boxes, boxes, scores, pc_range,
                      title=f"frame {preview.frame_id}, epoch {epoch}: ground truth (green) vs predictions (red)")
