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
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)
import numpy as np  # noqa: E402
import torch  # noqa: E402

import models  # noqa: E402
from detbench.config import ConfigError  # noqa: E402
from detbench.data.frame import height_key  # noqa: E402
from detbench.train.checkpoint import CheckpointError, init_from_checkpoint  # noqa: E402
from detbench.train.run_config import load_run_config, preset_names  # noqa: E402
from detbench.utils.cli import UserError, run_main  # noqa: E402
from detbench.utils.io import DiskFullError, atomic_write_json, atomic_write_text  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="second", help=f"detector: {', '.join(sorted(models.REGISTRY))} "
                                                      f"(default second)")
    ap.add_argument("--height", type=float, required=True, help="LiDAR mounting height in metres, e.g. 1.8")
    ap.add_argument("--data", default=None, metavar="ROOT",
                    help="dataset root (docs/data-format.md); default: the simulated default dataset")
    ap.add_argument("--preset", default="cpu", choices=preset_names(),
                    help="smoke: proves the pipeline in a minute or two; cpu: learns for real in about 10 min on "
                         "2 CPU cores; paper: the paper's scale (8000 frames, full model; a GPU). Default cpu")
    ap.add_argument("--config", default=None, help="a config file instead of configs/<model>.yaml")
    ap.add_argument("--epochs", type=int, default=None, help="override train.epochs")
    ap.add_argument("--batch-size", type=int, default=None, help="override train.batch_size (frames per process)")
    ap.add_argument("--workers", type=int, default=None, help="override train.workers (DataLoader processes)")
    ap.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (cuda when available)")
    ap.add_argument("--out", default=None, help="run folder (default runs/<model>_h<height>_<preset>)")
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


def collect_train_boxes(train_set, limit: int = 400) -> np.ndarray:
    """LiDAR-detected boxes of up to `limit` evenly spaced training frames (for anchor sizes)."""
    n = len(train_set)
    idx = np.unique(np.linspace(0, n - 1, num=min(n, limit)).astype(int)) if n else []
    boxes = [train_set.get(int(i), 0, augment=False).gt_boxes for i in idx]
    return np.concatenate(boxes) if boxes else np.zeros((0, 7), np.float32)


def run_config_from_args(args) -> dict:
    """The merged, checked run config (every section's keys and value kinds, before anything runs)."""
    overrides = list(args.overrides)
    for flag, key in ((args.epochs, "train.epochs"), (args.batch_size, "train.batch_size"),
                      (args.workers, "train.workers")):
        if flag is not None:
            overrides.append(f"{key}={flag}")
    if args.data:
        overrides.append(f"data.root={Path(args.data).resolve()}")
    try:
        cfg = load_run_config(args.model, args.preset, args.config, overrides)
        models.get_model_class(cfg["model"]["name"])
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    return cfg


def check_training_frames(frames) -> None:
    """Read every training frame once now (about 1 ms a frame), so a bad file stops the run before it trains
    instead of when the data loader reaches it mid-epoch."""
    from detbench.data.validate import check_frames

    check_frames(frames, fix=f"a training frame cannot be read: fix or re-create the file (python tools/validate.py "
                             f"{frames.root} lists every problem), or remove its id from "
                             f"{frames.root / 'ImageSets' / 'train.txt'}")


def eval_frames(root: Path, height: float, ecfg):
    """The frames evaluated after each epoch, each read once now, so a bad file stops the run before it trains."""
    from detbench.data import Height3Dataset
    from detbench.data.validate import check_frames

    test_set = Height3Dataset(root, height, ecfg.split)
    n = len(test_set)
    if ecfg.max_frames and ecfg.max_frames < n:
        return [test_set[int(i)] for i in np.linspace(0, n - 1, ecfg.max_frames).astype(int)]
    check_frames(test_set)
    return test_set


def make_eval_fn(frames, ecfg, point_cloud_range, device, batch_size: int):
    """`eval_fn(model, epoch)` for the training loop: recall and AP@R40 of all vehicles per range."""
    from detbench.data.regions import RANGE_NAMES
    from detbench.eval.evaluate import evaluate_predictions
    from detbench.train.inference import predict_frames

    def eval_fn(m, epoch):
        preds = predict_frames(m, frames, point_cloud_range, device=device, batch_size=batch_size, progress=False)
        rep = evaluate_predictions(frames, preds, iou_threshold=ecfg.iou_threshold,
                                   score_threshold=ecfg.score_threshold, extras=False, progress=False)
        res = {}
        for r in RANGE_NAMES:
            cell = rep["results"][r]["all"]
            res[f"ap_r40_{r}"] = cell["ap_r40"] if cell["ap_r40"] is not None else float("nan")
            res[f"recall_{r}"] = cell["recall"] if cell["recall"] is not None else float("nan")
        return res

    return eval_fn


def write_summary(out: Path, args, model_name: str, root: Path, result, seconds: float,
                  init: dict | None = None) -> None:
    """OUT/train_summary.json and .md."""
    last = result.history[-1] if result.history else {}
    summary = {"model": model_name, "height": float(args.height), "preset": args.preset, "data": str(root),
               "epochs_completed": result.epochs_completed, "global_step": result.global_step,
               "interrupted": result.interrupted, "train_seconds": round(seconds, 1),
               "checkpoint": str(result.last_checkpoint) if result.last_checkpoint else None,
               "init_from": init, "last_epoch": last}
    atomic_write_json(out / "train_summary.json", summary)
    lines = [f"# Training summary: {model_name} at {args.height:g} m ({args.preset} preset)", "",
             "| item | value |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in summary.items() if k != "last_epoch"]
    lines += [f"| last epoch: {k} | {v:.4g} |" if isinstance(v, float) else f"| last epoch: {k} | {v} |"
              for k, v in last.items()]
    atomic_write_text(out / "train_summary.md", "\n".join(lines) + "\n")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from detbench.eval.evaluate import EvalConfig
    from detbench.sim.dataset import default_dataset
    from detbench.train import AugmentConfig, TrainConfig, TrainingSet, cleanup, init_distributed, \
        main_process_first, train

    cfg = run_config_from_args(args)
    model_name = cfg["model"]["name"]
    out = Path(args.out or f"runs/{model_name}_h{height_key(args.height)}_{args.preset}")
    info = init_distributed(args.device)
    tcfg = TrainConfig.from_dict(cfg["train"])
    torch.manual_seed(tcfg.seed)
    try:
        with main_process_first(info):
            root = default_dataset(cfg["data"], progress=info.is_main and not args.no_progress)
            train_set = TrainingSet.from_dataset(root, args.height, cfg["model"]["point_cloud_range"],
                                                 augment=AugmentConfig.from_dict(cfg["augment"]), seed=tcfg.seed,
                                                 progress=info.is_main and not args.no_progress)
        if train_set.sampler is None:  # with ground-truth sampling on, building its database read every frame
            check_training_frames(train_set.frames)
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
                                                         tcfg.batch_size)
    except (FileNotFoundError, ValueError, KeyError, ConfigError, CheckpointError) as e:
        raise UserError(str(e)) from None

    if info.is_main and init:
        print(f"initialised {init['loaded_tensors']} weight tensors from {init['path']} ({init['model']}); "
              f"{init['new_tensors']} start from scratch")
    if info.is_main:
        print(f"{model_name} at {args.height:g} m: {len(train_set)} training frames from {root}; "
              f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters; device {info.device}; "
              f"out {out}")
    t0 = time.perf_counter()
    try:
        result = train(model, train_set, tcfg, out, model_name=model_name, run_config=cfg,
                       data_info={"source": str(root), "height": float(args.height)}, dist_info=info,
                       resume=args.resume, eval_fn=eval_fn, progress=not args.no_progress,
                       resume_hint=f"run the same command again with --resume (--out {out})")
    except (CheckpointError, ConfigError, ValueError, FloatingPointError) as e:
        cleanup(info, wait_for_peers=False)  # a peer may not reach its cleanup: no barrier
        raise UserError(str(e)) from None
    except DiskFullError as e:
        cleanup(info, wait_for_peers=False)  # a peer may not reach its cleanup: no barrier
        raise UserError(f"{e}; the run then continues from its last complete checkpoint with --resume") from None
    seconds = time.perf_counter() - t0
    if info.is_main:
        write_summary(out, args, model_name, root, result, seconds, init)
        print(f"trained in {seconds / 60:.1f} min; checkpoint {result.last_checkpoint}")
        if result.interrupted:
            print(f"interrupted: resume with the same command and --resume")
    cleanup(info)
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(run_main(main))
