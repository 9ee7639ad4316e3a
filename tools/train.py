#!/usr/bin/env python3
"""Train a detector on one LiDAR height's training split.

Ground truth is the LiDAR-detected vehicles of that height (>= 1 point inside the box with
its bottom raised 0.05 m), as in the Height3 paper. Without --data the simulated default
dataset is used (generated once, then cached; see configs/default.yaml `data:`).

Examples:
  python tools/train.py --model second --height 1.8 --preset smoke
  python tools/train.py --model second --height 1.8 --preset cpu --out runs/second_1.8
  python tools/train.py --model second --height 0.5 --data /data/height3 --preset paper --device cuda
  torchrun --nproc_per_node=4 tools/train.py --model second --height 1.8 --preset paper
  python tools/train.py ... --resume          # continue an interrupted run in the same --out

Writes OUT/checkpoints/epoch_EEE.pt (the newest is what tools/eval.py --ckpt takes),
OUT/tensorboard/, OUT/history.json, OUT/config.yaml and OUT/train_summary.{json,md}.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from functools import partial
from contextlib import ExitStack
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
import torch

import models
from detbench.config import ConfigError
from detbench.data.frame import height_or_rig_arg, key_label
from detbench.data.errors import DatasetError
from detbench.train.checkpoint import CheckpointError, init_from_checkpoint
from detbench.train.run import (check_training_frames, claim_run_folder, collect_train_boxes, eval_frames,
                                make_eval_fn, option_overrides, training_data_info, write_summary)
from detbench.train.run_config import load_run_config, preset_names
from detbench.utils.cli import UserError, as_user_error, doc_parser, run_main
from detbench.utils.atomic import DiskFullError
from detbench.utils.folder_ownership import FolderNotReplaceable


def build_parser() -> argparse.ArgumentParser:
    ap = doc_parser(__doc__)
    ap.add_argument("--model", default="second", help=f"detector: {', '.join(sorted(models.REGISTRY))} "
                                                      f"(default second)")
    ap.add_argument("--height", type=height_or_rig_arg, required=True,
                    help="LiDAR mounting height in metres, e.g. 1.8, or the name of a rig the dataset holds "
                         "(tools/simulate.py --rigs; docs/rigs.md), e.g. headlights")
    ap.add_argument("--data", default=None, metavar="ROOT",
                    help="dataset root (docs/data-format.md); default: the simulated default dataset")
    ap.add_argument("--preset", default="cpu", choices=preset_names(),
                    help="training budget, configs/presets/NAME.yaml (data, epochs, model widths). "
                         "smoke: proves the pipeline, learns nothing; cpu: learns for real on one CPU core; "
                         "paper: the paper's scale (8000 frames, full model; a GPU). Measured times: "
                         "docs/results.md, 'What each preset costs'. Default cpu")
    ap.add_argument("--config", default=None, help="a config file instead of configs/<model>.yaml")
    ap.add_argument("--epochs", type=int, default=None, help="override train.epochs")
    ap.add_argument("--batch-size", type=int, default=None, help="override train.batch_size (frames per process)")
    ap.add_argument("--workers", type=int, default=None, help="override train.workers (DataLoader processes)")
    ap.add_argument("--device", default="auto",
                    help="cpu, cuda, cuda:N or auto (cuda when available); under torchrun cuda or auto, each "
                         "process on cuda:LOCAL_RANK (CUDA_VISIBLE_DEVICES chooses the GPUs)")
    ap.add_argument("--deterministic", action="store_true",
                    help="ask torch for deterministic kernels on CUDA (slower; an op that has none warns, naming "
                         "itself); on the CPU a run and its --resume repeat exactly without it")
    ap.add_argument("--out", default=None, help="run folder (default runs/<model>_h<height>_<preset>): new, empty or "
                                                "a run's; locked while the run trains")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, repeatable, e.g. --set train.lr=0.002 --set model.voxel_size=[0.2,0.2,0.15]")
    ap.add_argument("--init-from", default=None, metavar="CKPT",
                    help="start from the weights of another run's checkpoint wherever layer names and shapes match "
                         "(e.g. ct3d from a second checkpoint trained on the same data with the same preset: its "
                         "proposal network starts trained); ignored with --resume once the run has a checkpoint")
    ap.add_argument("--no-eval", action="store_true", help="skip the per-epoch evaluation on the test split")
    ap.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return ap


# a DataLoader worker's memory: a spawned worker holds about 313 MiB resident before it reads a frame
# (docs/benchmarks.md, "What a DataLoader worker costs"); rounded up for the frames and buffers of its batches
WORKER_BYTES = 400 << 20


def check_workers(workers: int) -> None:
    """UserError for more DataLoader workers than this process has cores for (its affinity and cgroup CPU
    quota), or than the memory it may still use (the machine's and its cgroup's) holds at WORKER_BYTES each."""
    from detbench.studies.cpu_load import available_memory, usable_cores

    cores = usable_cores()
    if workers > cores:
        raise UserError(f"train.workers {workers}: this process may use {cores} CPU core(s) (its affinity and "
                        f"cgroup quota), so more DataLoader workers than that only compete for them; give "
                        f"--workers {cores} or fewer (0 loads in the training process)")
    free = available_memory()
    if free is not None and workers * WORKER_BYTES > free:
        fit = int(free // WORKER_BYTES)
        raise UserError(f"train.workers {workers}: each DataLoader worker takes about {WORKER_BYTES >> 20} MiB and "
                        f"{free / 2**30:.1f} GiB are free for this process (the machine's and its cgroup's "
                        f"limit); give --workers {fit} or fewer")


def run_config_from_args(args) -> dict:
    """The merged, checked run config (every section's keys and value kinds, before anything runs)."""
    overrides = option_overrides(args.overrides, epochs=args.epochs, batch_size=args.batch_size,
                                 workers=args.workers, data=args.data)
    try:
        cfg = load_run_config(args.model, args.preset, args.config, overrides)
        models.get_model_class(cfg["model"]["name"])
        models.check_model_config(cfg["model"], where=args.config)  # every key and its range, before any data is read
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    return cfg


def check_device(name: str) -> None:
    """UserError naming the device unless this process can train on `--device name`."""
    from detbench.train.distributed import DeviceError, launch_ranks, resolve_device

    try:
        _, world, local_rank = launch_ranks()
        resolve_device(name, local_rank, world)
    except DeviceError as e:
        raise UserError(f"--device {e.device}: {e.reason}") from None
    except ValueError as e:
        raise UserError(str(e)) from None


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from detbench.train import run_layout

    if not isinstance(args.height, str) and not (math.isfinite(args.height) and args.height > 0):
        raise UserError(f"--height {args.height:g}: a mounting height is a positive number of metres (or give a "
                        f"rig's name)")

    check_device(args.device)  # before any folder, data or model: a device this machine lacks is one line
    if args.deterministic:
        from detbench.train.rng import deterministic_algorithms

        deterministic_algorithms()
    cfg = run_config_from_args(args)
    check_workers(int(cfg["train"]["workers"]))
    out = Path(args.out or run_layout.default_train_dir(cfg["model"]["name"], args.height, args.preset))
    with ExitStack() as held:
        try:
            held.enter_context(claim_run_folder(out))
        except FolderNotReplaceable as e:
            raise UserError(f"--out {e}") from None
        return train_in(args, cfg, out, held)


def train_in(args, cfg: dict, out: Path, held: ExitStack) -> int:
    """Train as `args` say into the run folder `out` (held by `main`); the dataset is held for reading in
    `held` (no detbench writer replaces it while the run reads it)."""
    from detbench.utils.staged_folders import reading_folder

    from detbench.eval.evaluate import EvalConfig
    from detbench.data.road import RoadConfig
    from detbench.sim.dataset import default_dataset
    from detbench.train import AugmentConfig, TrainConfig, TrainingSet, cleanup, init_distributed, \
        main_process_first, train
    from detbench.train.distributed import DeviceError

    model_name = cfg["model"]["name"]
    try:
        info = init_distributed(args.device)
    except ValueError as e:  # a device or a torchrun environment this process cannot use: one line
        raise UserError(f"--device {e.device}: {e.reason}" if isinstance(e, DeviceError) else str(e)) from None
    tcfg = TrainConfig.from_dict(cfg["train"])
    road = RoadConfig.of_run_config(cfg)
    torch.manual_seed(tcfg.seed)
    try:
        with main_process_first(info):
            root = default_dataset(cfg["data"], progress=info.is_main and not args.no_progress)
            held.enter_context(reading_folder(root, "a training run"))
            train_set = TrainingSet.from_dataset(root, args.height, cfg["model"]["point_cloud_range"],
                                                 augment=AugmentConfig.from_dict(cfg["augment"]), seed=tcfg.seed,
                                                 road=road, progress=info.is_main and not args.no_progress)
        if train_set.sampler is None:  # with ground-truth sampling on, building its database read every frame
            check_training_frames(train_set.frames)
        data_info = training_data_info(root, args.height, train_set)
        requested_model_cfg = cfg["model"]  # before `auto` values are resolved from the training data
        model_cfg = models.prepare_model_config(model_name, cfg["model"], collect_train_boxes(train_set))
        cfg["model"] = model_cfg
        model = models.build_model(model_name, model_cfg)
        init = None
        resuming = args.resume and any((out / "checkpoints").glob("*.pt"))
        if args.init_from and not resuming:
            init = init_from_checkpoint(model, args.init_from, requested_model_cfg)
        ecfg = EvalConfig.from_dict(cfg["eval"])
        eval_fn = None if args.no_eval else make_eval_fn(eval_frames(root, args.height, ecfg), ecfg,
                                                         model_cfg["point_cloud_range"], info.device,
                                                         tcfg.batch_size, road=road)
    except (FileNotFoundError, ValueError, KeyError, ConfigError, CheckpointError) as e:
        raise as_user_error(e, always=(FileNotFoundError, KeyError, ConfigError, CheckpointError,
                                       DatasetError)) from None

    if info.is_main and init:
        print(f"initialised {init['loaded_tensors']} weight tensors from {init['path']} ({init['model']}); "
              f"{init['new_tensors']} start from scratch")
    if info.is_main:
        print(f"{model_name} at {key_label(args.height)}: {len(train_set)} training frames from {root}; "
              f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters; device {info.device}; "
              f"out {out}")
    t0 = time.perf_counter()
    try:
        result = train(model, train_set, tcfg, out, model_name=model_name, run_config=cfg,
                       data_info=data_info, dist_info=info,
                       resume=args.resume, stored_config=partial(models.upgrade_stored_run_config, model_name),
                       eval_fn=eval_fn, progress=not args.no_progress,
                       resume_hint=f"run the same command again with --resume (--out {out})")
    except (CheckpointError, ConfigError, ValueError, FloatingPointError) as e:
        cleanup(info, wait_for_peers=False)  # a peer may not reach its cleanup: no barrier
        # a bad frame, config or checkpoint is one line; a bug keeps its traceback
        raise as_user_error(e, always=(CheckpointError, ConfigError, DatasetError)) from None
    except DiskFullError as e:
        cleanup(info, wait_for_peers=False)  # a peer may not reach its cleanup: no barrier
        raise UserError(f"{e}; the run then continues from its last complete checkpoint with --resume") from None
    seconds = time.perf_counter() - t0
    if info.is_main:
        write_summary(out, model_name, args.height, args.preset, root, result, seconds, init,
                      frames_sha1=data_info["frames_sha1"])
        print(f"trained in {seconds / 60:.1f} min; checkpoint {result.last_checkpoint}")
        if result.interrupted:
            print("interrupted: resume with the same command and --resume")
    cleanup(info)
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(run_main(main))
