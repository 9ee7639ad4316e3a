"""The detector cost benchmark (tools/benchmark.py): latency per frame split by the model's stages, peak
memory, weights size and training-step time of one built detector, and the report of several.

The caller builds the model (the `models` registry sits above this library) and runs each in its own
process, so that peak memory is its own. Units: milliseconds, MB = 10^6 bytes, MiB = 2^20 bytes.
"""
from __future__ import annotations

import io
import resource
import statistics
import time

import numpy as np
import torch
from torch import nn

from detbench import runtime
from detbench.data.batch import Sample, collate
from detbench.data.road import RoadConfig, crop_model_input
from detbench.train.inference import frame_sample
from detbench.utils.bench import StageTimer, load_line, ratio, runtime_line

__all__ = ["benchmark_markdown", "idle_loaded_markdown", "loaded_figures",
           "measure_detector", "peak_rss_mib", "train_step_ms"]


def peak_rss_mib() -> float:
    """This process's peak resident memory so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure_detector(model: nn.Module, name: str, test, point_cloud_range, device: torch.device, *, frames: int,
                     warmup: int, checkpoint=None, rss_before_model: float, train_steps: int = 0,
                     train_batch: int = 2, road: RoadConfig | None = None) -> dict:
    """The cost of `model` (named `name`, eval mode, on `device`): latency per stage over `frames` frames of
    `test` after `warmup` passes, weights size, peak memory, and with `train_steps` the training step. The
    frames are prepared as the model's input (`road`: its road setting; the road fit is not timed)."""
    rss0 = rss_before_model
    buf = io.BytesIO()  # the model's weights as torch.save writes them (no optimizer state)
    torch.save(model.state_dict(), buf)
    ckpt_bytes = buf.tell()
    params = sum(p.numel() for p in model.parameters())
    n = frames + warmup
    samples = [frame_sample(test[i % len(test)], point_cloud_range, road) for i in range(n)]
    stages = model.STAGES
    timer = StageTimer(model, stages, device)
    sync = timer.sync  # CUDA-synchronising on a GPU, a no-op on CPU
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rows = []
    with torch.no_grad():
        for i, s in enumerate(samples):
            ms = timer.time_inference(model, collate([s]).to(device))
            if i >= warmup:
                rows.append({**ms, "points": int(len(s.points))})
    med = {k: round(statistics.median(r[k] for r in rows), 2) for k in rows[0]}
    peak_rss = peak_rss_mib()
    result = {"model": name, "device": str(device), "checkpoint": checkpoint, "parameters": params,
              "weights_mb": round(ckpt_bytes / 1e6, 2), "latency_ms": med,
              "latency_ms_min_total": round(min(r["total"] for r in rows), 2),
              "peak_rss_mib": round(peak_rss, 1), "rss_before_model_mib": round(rss0, 1),
              "frames": len(rows), "threads": torch.get_num_threads(), "road_dropped": bool(road and road.drop)}
    if device.type == "cuda":
        result["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    if train_steps > 0:
        result["train_step_ms"] = train_step_ms(model, test, point_cloud_range, train_steps, train_batch, device, sync,
                                                road)
        result["train_batch"] = train_batch
    result["runtime"] = runtime.describe()
    return result


def train_step_ms(model: nn.Module, frames, point_cloud_range, steps: int, batch_size: int, device: torch.device,
                  sync, road: RoadConfig | None = None) -> float:
    """Median milliseconds of one training step (forward, loss, backward, AdamW step) over
    `steps` steps after one untimed step; batches of `batch_size` frames with their
    boxes cropped to the model's range (and its road dropped, as `road` says). The model is trained in place
    (benchmark only)."""
    def sample(i):
        f = frames[i % len(frames)]
        pts, boxes, _ = crop_model_input(np.asarray(f.points, np.float32), np.asarray(f.boxes, np.float32),
                                         point_cloud_range, road)
        return Sample(np.ascontiguousarray(pts[:, :4]), boxes, f.frame_id)

    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    model.train()
    times = []
    for step in range(steps + 1):
        batch = collate([sample(step * batch_size + k) for k in range(batch_size)]).to(device)
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


def benchmark_markdown(meta: dict, results: list[dict]) -> str:
    """benchmark.md: one row per model and device, the stages in the models' own order."""
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
             "(no optimizer state). Units: ms, MB = 10^6 bytes, MiB = 2^20 bytes."
             + (f" Frames: the test split of {', '.join(meta['frames_from'])}." if meta.get("frames_from") else "")
             + (" 2D convolution weights in channels-last memory format (--channels-last)."
                if meta.get("memory_format") == "channels_last" else ""),
             "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        lat = r["latency_ms"]
        row = [r["model"], r["device"], f"{r['parameters'] / 1e6:.2f}", f"{r['weights_mb']:.2f}",
               f"{r['peak_rss_mib']:.0f}", f"{lat['total']:.1f}",
               *[f"{lat[s]:.1f}" if s in lat else "-" for s in stage_names],
               str(int(lat["points"]))]
        if has_acc:
            acc = r.get("accuracy") or {}

            def fmt(v):
                return "-" if v is None else f"{v:.3f}"

            row += [fmt(acc.get(k, {}).get("ap_r40")) for k in ("small", "moderate", "large")]
            row += [fmt(acc.get("large", {}).get("recall"))]
        lines.append("| " + " | ".join(row) + " |")
    if any("train_step_ms" in r or "loaded" in r for r in results):
        lines += ["", *idle_loaded_markdown(results)]
    if results:
        lines += ["", f"Thread runtimes: {runtime_line(results[0]['runtime'])}."]
    return "\n".join(lines) + "\n"


def loaded_figures(idle: dict, loaded: dict, load_info: dict) -> dict:
    """The loaded worker's latency (and training step) with each figure's loaded / idle ratio."""
    out = {"load": load_info, "latency_ms": loaded["latency_ms"],
           "ratio": {k: ratio(v, idle["latency_ms"].get(k)) for k, v in loaded["latency_ms"].items() if k != "points"}}
    if "train_step_ms" in loaded:
        out["train_step_ms"] = loaded["train_step_ms"]
        out["ratio"]["train_step"] = ratio(loaded["train_step_ms"], idle["train_step_ms"])
    return out


def idle_loaded_markdown(results: list[dict]) -> list[str]:
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

    def fmt(v):
        return "-" if v is None else f"{v:.1f}"

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
