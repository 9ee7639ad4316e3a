"""Where a detector's time goes (tools/benchmark.py --profile): one training step and one inference, by stage
and by kind of operation, with the data pipeline that feeds them and what this machine can do.

- Data: milliseconds per training sample for each step of `TrainingSet.get` (read the frame, its
  LiDAR-detected ground truth, augmentation with ground-truth sampling, the crop and road removal).
- Training step (forward by stage, loss, backward, optimiser step) and inference (forward by stage,
  post-processing), median milliseconds over the profiled steps.
- Operations: torch.profiler's self CPU time of every torch op, grouped by kind (dense convolution,
  matrix products, gathers and scatters, rule books and sorting, normalisation, element-wise, optimiser),
  with the time spent outside any torch op (Python, numba kernels, the data) as its own row. Where
  torch counts floating-point operations (forward convolutions and matrix products) the row gives the
  achieved GFLOP/s of those ops (their floating-point operations over their own time, children
  included); where it moves memory (gathers, scatters, copies) the estimated GB/s from the operands'
  shapes. Beside them, the machine's limits measured in the same process on its threads: the best
  float32 matrix product or dense convolution (GFLOP/s) and a 64 MiB copy (GB/s, bytes read plus
  written).

Units: milliseconds, GFLOP/s = 10^9 floating-point operations per second, GB/s = 10^9 bytes per second.
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from detbench.data.augment import augment_frame
from detbench.data.batch import collate
from detbench.data.regions import lidar_detected
from detbench.data.road import crop_model_input
from detbench.train.inference import frame_sample
from detbench.train.rng import sample_rng
from detbench.utils.bench import StageTimer

__all__ = ["OP_KINDS", "machine_limits", "op_kind", "profile_detector", "profile_markdown"]

# the kind of a torch op by its name (first match); the rest are "other torch ops"
OP_KINDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("dense convolution", ("conv", "mkldnn_convolution", "slow_conv", "convolution_backward")),
    ("matrix products", ("mm", "addmm", "bmm", "matmul", "linear", "scaled_dot_product", "baddbmm")),
    ("gather / scatter", ("index_select", "index_add", "index_put", "scatter", "gather", "aten::index",
                          "_index_put", "embedding", "masked_select")),
    ("rule books and sorting", ("sort", "argsort", "searchsorted", "unique", "nonzero", "cumsum", "topk",
                                "bincount", "histc")),
    ("normalisation", ("batch_norm", "layer_norm", "native_norm")),
    ("optimiser", ("adam", "optimizer", "_foreach", "addcdiv", "addcmul", "lerp")),
    ("element-wise and copies", ("add", "mul", "sub", "div", "relu", "clamp", "threshold", "sigmoid", "exp",
                                 "log", "copy_", "fill_", "where", "pow", "sqrt", "cat", "stack", "max", "min",
                                 "sum", "mean", "abs", "neg", "zero_", "to", "cos", "sin", "atan2", "floor",
                                 "eq", "ne", "lt", "gt", "le", "ge", "bitwise", "logical", "clone", "contiguous")),
)
# ops whose operands move memory: bytes estimated as the largest operand read and written once
_MEMORY_OPS = ("index_select", "index_add", "index_put", "scatter", "gather", "aten::index", "copy_", "cat")


def op_kind(name: str) -> str:
    """The kind (OP_KINDS) of the torch op `name`, e.g. aten::mkldnn_convolution -> dense convolution."""
    low = name.lower()
    for kind, keys in OP_KINDS:
        if any(k in low for k in keys):
            return kind
    return "other torch ops"


def machine_limits(repeats: int = 5) -> dict:
    """What this process reaches on its threads: the best float32 GFLOP/s of matrix products (512^3 to
    2048^3) and of a dense 3x3 convolution (64 -> 64 channels on 128 x 128), and the GB/s of a 64 MiB copy
    (bytes read plus written; beyond the caches, so ops on cache-resident data can exceed it)."""
    def best(fn) -> float:
        fn()
        t = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            t.append(time.perf_counter() - t0)
        return min(t)

    gflops = []
    for n in (512, 1024, 2048):
        a, b = torch.randn(n, n), torch.randn(n, n)
        gflops.append(2 * n**3 / best(lambda a=a, b=b: a @ b) / 1e9)
    x, w = torch.randn(1, 64, 128, 128), torch.randn(64, 64, 3, 3)
    with torch.no_grad():
        conv = 2 * 64 * 64 * 9 * 128 * 128 / best(lambda: torch.nn.functional.conv2d(x, w, padding=1)) / 1e9
    src = torch.randn(16 * 2**20)  # 64 MiB of float32
    dst = torch.empty_like(src)
    copy_s = best(lambda: dst.copy_(src))
    return {"matmul_gflops": round(max(gflops), 1), "conv_gflops": round(conv, 1),
            "peak_gflops": round(max(max(gflops), conv), 1),
            "copy_gb_per_s": round(2 * src.numel() * 4 / copy_s / 1e9, 1), "threads": torch.get_num_threads()}


def _data_ms(train_set, count: int) -> dict:
    """Milliseconds per sample of each step of TrainingSet.get (its own calls, timed one by one)."""
    steps = {"read frame": [], "ground truth": [], "augment": [], "crop and road": []}
    n_points = []
    for i in range(count):
        index = i % len(train_set)
        t0 = time.perf_counter()
        frame = train_set.frames[index]
        points = np.asarray(frame.points, dtype=np.float32)
        boxes = np.asarray(frame.boxes, dtype=np.float32).reshape(-1, 7)
        t1 = time.perf_counter()
        gt = boxes[lidar_detected(points, boxes, train_set.min_points, train_set.bottom_lift)]
        t2 = time.perf_counter()
        points, gt = augment_frame(points, gt, sample_rng(train_set.seed, 0, index), train_set.augment,
                                   train_set.sampler, avoid_boxes=boxes)
        t3 = time.perf_counter()
        points, gt, _ = crop_model_input(points, gt, train_set.point_cloud_range, train_set.road)
        t4 = time.perf_counter()
        for key, dt in zip(steps, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            steps[key].append(dt * 1e3)
        n_points.append(len(points))
    out = {k: round(statistics.median(v), 2) for k, v in steps.items()}
    out["total"] = round(sum(out.values()), 2)
    out["points_per_sample"] = int(statistics.median(n_points))
    return out


def _op_table(prof, wall_ms: float, repeats: int) -> list[dict]:
    """Self CPU milliseconds per repeat of each kind of op, its GFLOP/s and GB/s where known, and the rest."""
    rows: dict[str, dict] = {}
    for e in prof.key_averages(group_by_input_shape=True):
        if e.key.startswith(("ProfilerStep", "autograd::engine")):
            continue
        kind = op_kind(e.key)
        row = rows.setdefault(kind, {"kind": kind, "ms": 0.0, "flops": 0, "flop_ms": 0.0, "bytes": 0, "calls": 0})
        row["ms"] += e.self_cpu_time_total / 1e3 / repeats
        if e.flops:  # counted on the op that dispatches (aten::conv2d, aten::mm): its time with its children
            row["flops"] += int(e.flops) // repeats
            row["flop_ms"] += e.cpu_time_total / 1e3 / repeats
        row["calls"] += e.count // repeats
        if any(k in e.key for k in _MEMORY_OPS):
            row["bytes"] += _bytes_moved(e.input_shapes) * e.count // repeats
    table = sorted(rows.values(), key=lambda r: -r["ms"])
    inside = sum(r["ms"] for r in table)
    table.append({"kind": "outside torch ops (Python, numba, data)", "ms": max(0.0, wall_ms - inside), "flops": 0,
                  "flop_ms": 0.0, "bytes": 0, "calls": 0})
    for r in table:
        r["share"] = round(r["ms"] / wall_ms, 3) if wall_ms > 0 else None
        r["gflops"] = round(r["flops"] / (r.pop("flop_ms") * 1e-3) / 1e9, 1) if r["flops"] else None
        r.pop("flop_ms", None)
        r["gb_per_s"] = round(r["bytes"] / (r["ms"] * 1e-3) / 1e9, 1) if r["bytes"] and r["ms"] > 0 else None
        r["ms"] = round(r["ms"], 2)
    return table


def _bytes_moved(shapes) -> int:
    """An op's memory traffic, estimated as its largest float32 operand read once and written once."""
    sizes = [int(np.prod(s)) for s in (shapes or []) if isinstance(s, (list, tuple)) and s]
    return 2 * 4 * max(sizes, default=0)


def profile_detector(model: nn.Module, train_set, test: Sequence, point_cloud_range, *, road, steps: int = 4,
                     frames: int = 4, batch_size: int = 2, data_samples: int = 8) -> dict:
    """Profile `model` (a Detector on the CPU; trained in place, so pass one built for the purpose): the data
    pipeline of `train_set` (a TrainingSet), `steps` training steps on batches of `batch_size` of its samples
    (after one untimed step) and `frames` inferences on frames of `test` (after one untimed), by stage and by
    kind of op. Returns the figures as a dict (module doc: units)."""
    data = _data_ms(train_set, data_samples)
    timer = StageTimer(model, model.STAGES, "cpu")
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    batches = [collate([train_set[(0, (k * batch_size + j) % len(train_set))] for j in range(batch_size)])
               for k in range(steps + 1)]

    def train_step(batch) -> dict:
        timer.reset()
        t0 = time.perf_counter()
        out = model(batch)
        t1 = time.perf_counter()
        loss, _ = model.loss(out, batch)
        t2 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        t3 = time.perf_counter()
        optimizer.step()
        t4 = time.perf_counter()
        return {**{f"forward: {k}": v * 1e3 for k, v in timer.times.items()}, "loss": (t2 - t1) * 1e3,
                "backward": (t3 - t2) * 1e3, "optimiser step": (t4 - t3) * 1e3, "total": (t4 - t0) * 1e3}

    model.train()
    train_step(batches[0])
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True,
                                with_flops=True) as prof:
        rows = [train_step(b) for b in batches[1:]]
    train = {k: round(statistics.median(r[k] for r in rows), 2) for k in rows[0]}
    train_ops = _op_table(prof, sum(r["total"] for r in rows) / len(rows), len(rows))

    model.eval()
    samples = [frame_sample(test[i % len(test)], point_cloud_range, road) for i in range(frames + 1)]
    with torch.no_grad():
        timer.time_inference(model, collate([samples[0]]))
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True,
                                    with_flops=True) as prof:
            rows = [timer.time_inference(model, collate([s])) for s in samples[1:]]
    infer = {k: round(statistics.median(r[k] for r in rows), 2) for k in rows[0]}
    infer_ops = _op_table(prof, sum(r["total"] for r in rows) / len(rows), len(rows))
    return {"data_ms_per_sample": data, "train_step_ms": train, "train_ops": train_ops, "inference_ms": infer,
            "inference_ops": infer_ops, "batch_size": batch_size, "steps": steps, "frames": frames,
            "points_per_test_frame": int(statistics.median(len(s.points) for s in samples[1:])),
            "machine": machine_limits()}


def _ops_lines(rows: list[dict], limits: dict) -> list[str]:
    lines = ["| kind of op | ms | share | calls | achieved GFLOP/s | est. GB/s |", "|---|---:|---:|---:|---:|---:|"]
    peak = limits.get("peak_gflops", limits["matmul_gflops"])
    for r in rows:
        g = f"{r['gflops']:.1f} (of {peak:.0f})" if r["gflops"] else "-"
        b = f"{r['gb_per_s']:.1f} (of {limits['copy_gb_per_s']:.0f})" if r["gb_per_s"] else "-"
        lines.append(f"| {r['kind']} | {r['ms']:.1f} | {100 * (r['share'] or 0):.0f} % | {r['calls']} | {g} | {b} |")
    return lines


def profile_markdown(results: list[dict]) -> list[str]:
    """The profile section of benchmark.md: per model, its data, training step and inference tables."""
    lines = ["## Where the time goes (--profile)", "",
             "Self CPU time of torch's ops per training step (batch as given) and per inference frame, grouped by "
             "kind; 'outside torch ops' is the rest of the wall time (Python, numba kernels). GFLOP/s counts the "
             "forward convolutions and matrix products only (torch counts none for backward); GB/s estimates the "
             "memory moved by gathers, scatters and copies. In brackets: the best this process reached on a matrix "
             "product or a dense convolution, and a 64 MiB copy. Units: ms, GFLOP/s, GB/s.", ""]
    for r in results:
        p = r.get("profile")
        if not p:
            continue
        d, t, i = p["data_ms_per_sample"], p["train_step_ms"], p["inference_ms"]
        lines += [f"### {r['model']}", "",
                  "Data pipeline, ms per training sample: " + ", ".join(f"{k} {v:.1f}" for k, v in d.items()
                                                                        if k != "points_per_sample")
                  + f" ({d['points_per_sample']} points per sample after the crop).", "",
                  f"Training step (batch {p['batch_size']}), median ms: " + ", ".join(f"{k} {v:.1f}"
                                                                                  for k, v in t.items()), "",
                  *_ops_lines(p["train_ops"], p["machine"]), "",
                  f"Inference (batch 1, {p['points_per_test_frame']} points), median ms: "
                  + ", ".join(f"{k} {v:.1f}" for k, v in i.items()), "",
                  *_ops_lines(p["inference_ops"], p["machine"]), ""]
    return lines
