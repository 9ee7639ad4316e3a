#!/usr/bin/env python3
"""What each detector costs: parameters, checkpoint size, peak memory and latency per frame.

Latency is the median over --frames real (simulated or --data) frames after --warmup
passes, split by stage (voxelize / backbone / head / post-processing; each model names its
stages), on CPU and on CUDA when present. With --study DIR (a tools/study.py output) the
models' trained checkpoints are used, timed on the test frames of the dataset they were trained on, and
each model's AP@R40 / recall is joined to its cost, like the paper's Table III next to its accuracy.
--train-steps N also times N training steps (forward, loss, backward, AdamW step) on batches of
--train-batch frames. --load N measures everything again beside N busy-loop processes (started
for it, stopped after) and reports idle and loaded figures side by side. --profile adds where the
time goes: the data pipeline per training sample, a training step and an inference split by stage
and by kind of torch op (dense convolution, matrix products, gathers and scatters, rule books,
normalisation, element-wise, optimiser, and the time outside torch ops), with the achieved GFLOP/s
and GB/s beside this machine's single-thread limits (detbench.benchmarks.profile).

Examples:
  python tools/benchmark.py                         # every model, its cpu-preset size, CPU
  python tools/benchmark.py --preset paper --device cuda
  python tools/benchmark.py --study runs/study_cpu --height 1.8
  python tools/benchmark.py --models second --train-steps 3 --load 1   # idle vs one busy process
  python tools/benchmark.py --preset cpu --height 1.8 --profile       # where each detector's time goes

Writes OUT/benchmark.json and OUT/benchmark.md (default OUT = runs/benchmark).
Units: milliseconds per frame, MB = 10^6 bytes (checkpoint), MiB = 2^20 bytes (memory).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
import models
from detbench.benchmarks.detectors import (benchmark_markdown, loaded_figures, measure_detector,
                                            peak_rss_mib)
from detbench.benchmarks.profile import profile_markdown
from detbench.data.road import RoadConfig
from detbench.train.detector import channels_last_2d
from detbench.train.run_config import preset_names
from detbench.utils.bench import idle_and_loaded
from detbench.utils.cli import (
    EXIT_USER_ERROR, UserError, claim_output, doc_parser, output_folder, require, require_distinct, run_main,
    torch_device,
)
from detbench.utils.report_folders import BENCHMARK_FOLDER
from detbench.utils.atomic import atomic_write_json, atomic_write_text, read_json


def build_parser() -> argparse.ArgumentParser:
    ap = doc_parser(__doc__)
    ap.add_argument("--models", nargs="+", default=None, help="detectors (default: all registered)")
    ap.add_argument("--preset", default="cpu", choices=preset_names(),
                    help="training budget, configs/presets/NAME.yaml: the model size to build when no checkpoint is "
                         "given (default cpu)")
    ap.add_argument("--study", default=None, metavar="DIR",
                    help="a tools/study.py output: use its trained checkpoints, time them on its dataset's test "
                         "frames and join their reports")
    ap.add_argument("--height", type=float, default=1.8, help="LiDAR height of the frames (and of --study runs)")
    ap.add_argument("--data", default=None, metavar="ROOT",
                    help="dataset for the frames (default: the one each checkpoint was trained on, as with --study, "
                         "else the smoke preset's simulated set)")
    ap.add_argument("--frames", type=int, default=10, help="timed frames (default 10)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed passes first (default 3)")
    ap.add_argument("--device", default="auto", help="cpu, cuda, or auto = cpu and also cuda when present")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads (default: detbench's, OMP_NUM_THREADS; see docs/benchmarks.md)")
    ap.add_argument("--train-steps", type=int, default=0, metavar="N",
                    help="also time N training steps after one untimed step (default 0: none)")
    ap.add_argument("--train-batch", type=int, default=2, metavar="B",
                    help="frames per training step (default 2, the cpu preset's batch size)")
    ap.add_argument("--load", type=int, default=0, metavar="N",
                    help="measure each model again beside N busy-loop processes (default 0: idle only)")
    ap.add_argument("--profile", action="store_true",
                    help="also profile the data pipeline, one training step and one inference by stage and by kind "
                         "of op (a few seconds per model more); the training frames come from the same dataset")
    ap.add_argument("--channels-last", action="store_true",
                    help="hold the models' 2D convolution weights in channels-last memory format (NHWC), so "
                         "the dense BEV maps run through the NHWC convolution kernels; to measure whether it "
                         "pays on this CPU (docs/benchmarks.md) against the same command without it")
    ap.add_argument("--out", default="runs/benchmark", help="output folder (default runs/benchmark)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: one model in a child process
    return ap


def worker(args) -> dict:
    """Benchmark one model (in its own process so its peak memory is its own)."""
    import numpy as np
    import torch

    from detbench.data import Height3Dataset
    from detbench.sim.dataset import default_dataset
    from detbench.train.run_config import load_run_config

    if args.threads:
        torch.set_num_threads(args.threads)
    spec = json.loads(args.worker)
    name, device, ckpt = spec["model"], torch.device(spec["device"]), spec.get("ckpt")
    rss0 = peak_rss_mib()
    if ckpt:
        model, ck = models.load_from_checkpoint(ckpt, device)
        cfg_model = ck["config"]["model"]
        road = RoadConfig.of_run_config(ck["config"])
    else:
        cfg = load_run_config(name, args.preset)
        root_for_sizes = default_dataset({**cfg["data"], "root": args.data} if args.data else
                                         load_run_config(name, "smoke")["data"], progress=False)
        train = Height3Dataset(root_for_sizes, args.height, "train")
        boxes = np.concatenate([train[i].boxes for i in range(min(len(train), 20))])
        cfg_model = models.prepare_model_config(name, cfg["model"], boxes)
        road = RoadConfig.of_run_config(cfg)
        model = models.build_model(name, cfg_model).to(device).eval()
    if args.channels_last:
        model = channels_last_2d(model)
    source = frames_source(args.data, ck if ckpt else None)
    data_root = default_dataset({"root": source} if source else load_run_config(name, "smoke")["data"],
                                progress=False)
    test = Height3Dataset(data_root, args.height, "test")
    res = measure_detector(model, name, test, cfg_model["point_cloud_range"], device, frames=args.frames,
                           warmup=args.warmup, checkpoint=ckpt, rss_before_model=rss0,
                           train_steps=args.train_steps, train_batch=args.train_batch, road=road)
    if args.profile and device.type == "cpu":
        res["profile"] = profile(model, ck["config"] if ckpt else cfg, data_root, args, road)
    return {**res, "frames_from": str(data_root)}


def profile(model, run_cfg: dict, data_root, args, road) -> dict:
    """detbench.benchmarks.profile on a copy of `model` (the profile trains it), with the run config's
    augmentation on the training split of `data_root` at --height."""
    import copy

    from detbench.benchmarks.profile import profile_detector
    from detbench.data import Height3Dataset
    from detbench.data.augment import AugmentConfig
    from detbench.train.dataset import TrainingSet

    pcr = run_cfg["model"]["point_cloud_range"]
    augment = AugmentConfig.from_dict(run_cfg["augment"])
    train_set = TrainingSet.from_dataset(data_root, args.height, pcr, augment=augment, road=road, progress=False)
    return profile_detector(copy.deepcopy(model), train_set, Height3Dataset(data_root, args.height, "test"), pcr,
                            road=road, steps=max(2, min(args.train_steps or 4, 8)), frames=min(args.frames, 8),
                            batch_size=args.train_batch)


def frames_source(data: str | None, ck: dict | None) -> str | None:
    """The dataset whose test frames are timed: --data; else the one a checkpoint was trained on (so a --study's
    models run on the frames they were tested on), when it is on this machine; else None, the smoke preset's
    simulated set."""
    if data:
        return data
    source = ((ck or {}).get("data") or {}).get("source")
    return str(source) if source and Path(source).is_dir() else None


def check_arguments(args: argparse.Namespace) -> None:
    """UserError for a value that would time nothing or cannot run, before any model is built."""
    for flag, v, low in (("--frames", args.frames, 1), ("--warmup", args.warmup, 0),
                         ("--train-steps", args.train_steps, 0), ("--train-batch", args.train_batch, 1),
                         ("--load", args.load, 0), ("--threads", args.threads, 1)):
        require(v is None or v >= low, f"{flag} {v}: must be an integer >= {low}")
    require(math.isfinite(args.height) and args.height > 0,
            f"--height {args.height:g}: must be a positive number of metres")
    if args.device != "auto":
        torch_device(args.device)
    require_distinct(args.models, "--models", what="model")
    output_folder(args.out, BENCHMARK_FOLDER)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    import torch

    from detbench.train.run_layout import eval_report_path, study_run_dir

    check_arguments(args)

    names = args.models or sorted(models.REGISTRY)
    for name in names:
        try:
            models.get_model_class(name)
        except ValueError as e:
            raise UserError(f"--models: {e}") from None
    if args.study and not Path(args.study).is_dir():
        raise UserError(f"--study {args.study}: no such folder; give the --out folder of a tools/study.py run")
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else []) if args.device == "auto" else [args.device]
    results = []
    for name in names:
        models.get_model_class(name)
        ckpt, report = None, None
        if args.study:
            run_dir = study_run_dir(args.study, name, args.height)
            summary = run_dir / "train_summary.json"
            if summary.is_file():
                ckpt = read_json(summary)["checkpoint"]
            rep = eval_report_path(run_dir, args.height)
            report = read_json(rep) if rep.is_file() else None
        for dev in devices:
            spec = json.dumps({"model": name, "device": dev, "ckpt": ckpt})
            cmd = [sys.executable, __file__, "--worker", spec, "--preset", args.preset, "--height", str(args.height),
                   "--frames", str(args.frames), "--warmup", str(args.warmup)]
            if args.threads:
                cmd += ["--threads", str(args.threads)]
            if args.data:
                cmd += ["--data", args.data]
            if args.train_steps > 0:
                cmd += ["--train-steps", str(args.train_steps)]
            cmd += ["--train-batch", str(args.train_batch)] + (["--profile"] if args.profile else [])
            cmd += ["--channels-last"] if args.channels_last else []

            def run_worker(cmd=cmd, name=name, dev=dev):
                proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
                if proc.returncode != 0:
                    msg = f"benchmark of {name} on {dev} failed:\n{proc.stderr[-3000:]}"
                    raise UserError(msg) if proc.returncode == EXIT_USER_ERROR else SystemExit(msg)
                return json.loads(proc.stdout.strip().splitlines()[-1])

            res, loaded, load_info = idle_and_loaded(run_worker, args.load)
            if loaded is not None:
                res["loaded"] = loaded_figures(res, loaded, load_info)
            if report is not None:
                res["accuracy"] = {r: {k: report["results"][r]["all"][k] for k in ("recall", "ap_r40")}
                                   for r in report["results"]}
            results.append(res)
            lat = res["latency_ms"]
            print(f"{name:10s} {dev:5s} {res['parameters'] / 1e6:6.2f} M params  {res['weights_mb']:7.2f} MB  "
                  f"{lat['total']:8.1f} ms/frame  peak {res['peak_rss_mib']:.0f} MiB"
                  + (f"  train step {res['train_step_ms']:.0f} ms" if "train_step_ms" in res else "")
                  + (f"  | loaded: {res['loaded']['latency_ms']['total']:.1f} ms/frame "
                     f"(x{res['loaded']['ratio']['total']})" if "loaded" in res else ""))
    meta = {"machine": platform.machine(), "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(), "torch": torch.__version__,
            "threads": results[0]["threads"] if results else args.threads,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "preset": args.preset, "study": args.study, "height": args.height,
            "memory_format": "channels_last" if args.channels_last else "contiguous",
            "frames_from": sorted({r["frames_from"] for r in results})}
    with claim_output(args.out, BENCHMARK_FOLDER) as out:
        atomic_write_json(out / "benchmark.json", {"meta": meta, "results": results})
        atomic_write_text(out / "benchmark.md", benchmark_markdown(meta, results)
                          + ("\n" + "\n".join(profile_markdown(results)) if args.profile else ""))
    print(f"wrote {out / 'benchmark.json'}, {out / 'benchmark.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
