#!/usr/bin/env python3
"""What each detector costs: parameters, checkpoint size, peak memory and latency per frame.

Latency is the median over --frames real (simulated or --data) frames after --warmup
passes, split by stage (voxelize / backbone / head / post-processing; each model names its
stages), on CPU and on CUDA when present. With --study DIR (a tools/study.py output) the
models' trained checkpoints are used and each model's AP@R40 / recall is joined to its cost,
like the paper's Table III next to its accuracy. --train-steps N also times N training steps
(forward, loss, backward, AdamW step) on batches of --train-batch frames. --load N measures
everything again beside N busy-loop processes (started for it, stopped after) and reports
idle and loaded figures side by side.

Examples:
  python tools/benchmark.py                         # every model, its cpu-preset size, CPU
  python tools/benchmark.py --preset paper --device cuda
  python tools/benchmark.py --study runs/study_cpu --height 1.8
  python tools/benchmark.py --models second --train-steps 3 --load 1   # idle vs one busy process

Writes OUT/benchmark.json and OUT/benchmark.md (default OUT = runs/benchmark).
Units: milliseconds per frame, MB = 10^6 bytes (checkpoint), MiB = 2^20 bytes (memory).
"""
from __future__ import annotations

import argparse
import io
import json
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)
import models  # noqa: E402
from detbench import runtime  # noqa: E402
from detbench.train.run_config import preset_names  # noqa: E402
from detbench.utils.bench import StageTimer, idle_and_loaded, load_line, ratio, runtime_line  # noqa: E402
from detbench.utils.cli import EXIT_USER_ERROR, UserError, run_main  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text, read_json  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", default=None, help="detectors (default: all registered)")
    ap.add_argument("--preset", default="cpu", choices=preset_names(),
                    help="model size to build when no checkpoint is given (default cpu)")
    ap.add_argument("--study", default=None, metavar="DIR",
                    help="a tools/study.py output: use its trained checkpoints and join their reports")
    ap.add_argument("--height", type=float, default=1.8, help="LiDAR height of the frames (and of --study runs)")
    ap.add_argument("--data", default=None, metavar="ROOT", help="dataset for the frames (default: simulated smoke set)")
    ap.add_argument("--frames", type=int, default=10, help="timed frames (default 10)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed passes first (default 3)")
    ap.add_argument("--device", default="auto", help="cpu, cuda, or auto = cpu and also cuda when present")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads (default: detbench's, OMP_NUM_THREADS; see docs/architecture.md)")
    ap.add_argument("--train-steps", type=int, default=0, metavar="N",
                    help="also time N training steps after one untimed step (default 0: none)")
    ap.add_argument("--train-batch", type=int, default=2, metavar="B",
                    help="frames per training step (default 2, the cpu preset's batch size)")
    ap.add_argument("--load", type=int, default=0, metavar="N",
                    help="measure each model again beside N busy-loop processes (default 0: idle only)")
    ap.add_argument("--out", default="runs/benchmark", help="output folder (default runs/benchmark)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: one model in a child process
    return ap


def worker(args) -> dict:
    """Benchmark one model (in its own process so its peak memory is its own)."""
    import numpy as np
    import torch

    from detbench.data.batch import collate
    from detbench.sim.dataset import default_dataset
    from detbench.train.inference import frame_sample
    from detbench.train.run_config import load_run_config

    if args.threads:
        torch.set_num_threads(args.threads)
    spec = json.loads(args.worker)
    name, device, ckpt = spec["model"], torch.device(spec["device"]), spec.get("ckpt")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if ckpt:
        model, ck = models.load_from_checkpoint(ckpt, device)
        cfg_model = ck["config"]["model"]
    else:
        cfg = load_run_config(name, args.preset)
        root_for_sizes = default_dataset({**cfg["data"], "root": args.data} if args.data else
                                         load_run_config(name, "smoke")["data"], progress=False)
        from detbench.data import Height3Dataset

        train = Height3Dataset(root_for_sizes, args.height, "train")
        boxes = np.concatenate([train[i].boxes for i in range(min(len(train), 20))])
        cfg_model = models.prepare_model_config(name, cfg["model"], boxes)
        model = models.build_model(name, cfg_model).to(device).eval()
    buf = io.BytesIO()  # the model's weights as torch.save writes them (no optimizer state)
    torch.save(model.state_dict(), buf)
    ckpt_bytes = buf.tell()
    params = sum(p.numel() for p in model.parameters())
    from detbench.data import Height3Dataset

    data_root = default_dataset({"root": args.data} if args.data else load_run_config(name, "smoke")["data"],
                                progress=False)
    test = Height3Dataset(data_root, args.height, "test")
    n = args.frames + args.warmup
    samples = [frame_sample(test[i % len(test)], cfg_model["point_cloud_range"]) for i in range(n)]
    stages = model.STAGES
    timer = StageTimer(model, stages, device)
    sync = timer.sync  # CUDA-synchronising on a GPU, a no-op on CPU
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rows = []
    with torch.no_grad():
        for i, s in enumerate(samples):
            ms = timer.time_inference(model, collate([s]).to(device))
            if i >= args.warmup:
                rows.append({**ms, "points": int(len(s.points))})
    med = {k: round(statistics.median(r[k] for r in rows), 2) for k in rows[0]}
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    result = {"model": name, "device": str(device), "checkpoint": ckpt, "parameters": params,
              "weights_mb": round(ckpt_bytes / 1e6, 2), "latency_ms": med,
              "latency_ms_min_total": round(min(r["total"] for r in rows), 2),
              "peak_rss_mib": round(peak_rss, 1), "rss_before_model_mib": round(rss0, 1),
              "frames": len(rows), "threads": torch.get_num_threads()}
    if device.type == "cuda":
        result["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    if args.train_steps > 0:
        result["train_step_ms"] = _train_steps(model, test, cfg_model["point_cloud_range"], args, device, sync)
        result["train_batch"] = args.train_batch
    result["runtime"] = runtime.describe()
    return result


def _train_steps(model, frames, point_cloud_range, args, device, sync) -> float:
    """Median milliseconds of one training step (forward, loss, backward, AdamW step) over
    --train-steps steps after one untimed step; batches of --train-batch frames with their
    boxes cropped to the model's range. The model is trained in place (benchmark only)."""
    import numpy as np
    import torch

    from detbench.data.augment import crop_to_range
    from detbench.data.batch import Sample, collate

    def sample(i):
        f = frames[i % len(frames)]
        pts, boxes, _ = crop_to_range(np.asarray(f.points, np.float32), np.asarray(f.boxes, np.float32),
                                      point_cloud_range)
        return Sample(np.ascontiguousarray(pts[:, :4]), boxes, f.frame_id)

    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    model.train()
    times = []
    for step in range(args.train_steps + 1):
        batch = collate([sample(step * args.train_batch + k) for k in range(args.train_batch)]).to(device)
        sync()
        t0 = time.perf_counter()
        loss, _ = model.loss(model(batch), batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        sync()
        if step > 0:
            times.append((time.perf_counter() - t0) * 1000)
    model.eval()
    return round(statistics.median(times), 2)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args)))
        return 0
    import torch

    from detbench.data.frame import height_key

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
            run_dir = Path(args.study) / f"{name}_h{height_key(args.height)}"
            summary = run_dir / "train_summary.json"
            if summary.is_file():
                ckpt = read_json(summary)["checkpoint"]
            rep = run_dir / f"eval_h{height_key(args.height)}_test" / "report.json"
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
                cmd += ["--train-steps", str(args.train_steps), "--train-batch", str(args.train_batch)]

            def run_worker():
                proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
                if proc.returncode != 0:
                    msg = f"benchmark of {name} on {dev} failed:\n{proc.stderr[-3000:]}"
                    raise UserError(msg) if proc.returncode == EXIT_USER_ERROR else SystemExit(msg)
                return json.loads(proc.stdout.strip().splitlines()[-1])

            res, loaded, load_info = idle_and_loaded(run_worker, args.load)
            if loaded is not None:
                res["loaded"] = _loaded_figures(res, loaded, load_info)
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
            "preset": args.preset, "study": args.study, "height": args.height}
    out = Path(args.out)
    atomic_write_json(out / "benchmark.json", {"meta": meta, "results": results})
    stage_names = []  # in the models' own stage order, post-processing last
    for r in results:
        stage_names += [k for k in r["latency_ms"] if k not in ("total", "points", "post") and k not in stage_names]
    stage_names.append("post")
    head = ["model", "device", "params (M)", "weights (MB)", "peak RSS (MiB)", "total (ms/frame)",
            *[f"{s} (ms)" for s in stage_names], "points/frame"]
    has_acc = any("accuracy" in r for r in results)
    if has_acc:
        head += ["AP@R40 small", "AP@R40 moderate", "AP@R40 large", "recall large"]
    lines = [f"# Detector cost ({meta['processor']}, torch {meta['torch']}, {meta['threads']} CPU threads"
             f"{', ' + meta['cuda'] if meta['cuda'] else ''})", "",
             "Latency: median per frame after warm-up, batch of 1. Weights: the state_dict as torch.save writes it "
             "(no optimizer state). Units: ms, MB = 10^6 bytes, MiB = 2^20 bytes.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        lat = r["latency_ms"]
        row = [r["model"], r["device"], f"{r['parameters'] / 1e6:.2f}", f"{r['weights_mb']:.2f}",
               f"{r['peak_rss_mib']:.0f}", f"{lat['total']:.1f}", *[f"{lat[s]:.1f}" if s in lat else "-" for s in stage_names],
               str(int(lat["points"]))]
        if has_acc:
            acc = r.get("accuracy") or {}
            fmt = (lambda v: "-" if v is None else f"{v:.3f}")
            row += [fmt(acc.get(k, {}).get("ap_r40")) for k in ("small", "moderate", "large")]
            row += [fmt(acc.get("large", {}).get("recall"))]
        lines.append("| " + " | ".join(row) + " |")
    if any("train_step_ms" in r or "loaded" in r for r in results):
        lines += ["", *_idle_loaded_markdown(results)]
    if results:
        lines += ["", f"Thread runtimes: {runtime_line(results[0]['runtime'])}."]
    atomic_write_text(out / "benchmark.md", "\n".join(lines) + "\n")
    print(f"wrote {out / 'benchmark.json'}, {out / 'benchmark.md'}")
    return 0


def _loaded_figures(idle: dict, loaded: dict, load_info: dict) -> dict:
    """The loaded worker's latency (and training step) with each figure's loaded / idle ratio."""
    out = {"load": load_info, "latency_ms": loaded["latency_ms"],
           "ratio": {k: ratio(v, idle["latency_ms"].get(k)) for k, v in loaded["latency_ms"].items() if k != "points"}}
    if "train_step_ms" in loaded:
        out["train_step_ms"] = loaded["train_step_ms"]
        out["ratio"]["train_step"] = ratio(loaded["train_step_ms"], idle["train_step_ms"])
    return out


def _idle_loaded_markdown(results: list[dict]) -> list[str]:
    """Forward latency and training step, idle and (with --load) loaded with the ratio, per model."""
    loaded = any("loaded" in r for r in results)
    head = ["model", "device", "forward + post, idle (ms/frame)"]
    head += ["loaded (ms/frame)", "x idle"] if loaded else []
    head += ["training step, idle (ms)"] + (["loaded (ms)", "x idle"] if loaded else [])
    lines = ["## Idle and loaded" if loaded else "## Training step", ""]
    if loaded:
        lines += [f"Loaded: the same measurement beside {load_line(results[0]['loaded']['load'])}. "
                  "Training step: forward, loss, backward and AdamW step, median.", ""]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    fmt = (lambda v: "-" if v is None else f"{v:.1f}")
    for r in results:
        lo = r.get("loaded", {})
        row = [r["model"], r["device"], fmt(r["latency_ms"]["total"])]
        if loaded:
            row += [fmt(lo.get("latency_ms", {}).get("total")), str(lo.get("ratio", {}).get("total", "-"))]
        row += [fmt(r.get("train_step_ms"))]
        if loaded:
            row += [fmt(lo.get("train_step_ms")), str(lo.get("ratio", {}).get("train_step", "-"))]
        lines.append("| " + " | ".join(row) + " |")
    return lines


if __name__ == "__main__":
    sys.exit(run_main(main))
