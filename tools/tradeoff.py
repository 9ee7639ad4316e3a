#!/usr/bin/env python3
"""The speed/accuracy trade of each detector: latency, memory and AP@R40 across the knobs users turn.

For each model, from the preset's point, one knob at a time and a few joint points:
  voxel      voxel / pillar size x0.5 and x2 (trained; the grid is re-fitted to a whole number of cells
             when the preset's range does not divide)
  width      every channel width x0.5 and x2 (trained)
  region     the grid shrunk to x <= 50 m, |y| <= 5 m and to x <= 100 m, |y| <= 10 m plus the config's
             margins (trained), against the full grid evaluated on the same range
  points     input point budget at test time, 16384 and 4096 points by random or farthest-point
             subsampling (preset model); PointRCNN also its sampled points per frame x0.5 / x2 (trained)
  proposals  two-stage models: proposals refined at test time x0.25 / x0.5 (preset model), training
             RoIs per frame x0.5 / x2 (trained)
  precision  bfloat16 autocast on CPU; float16 and bfloat16 autocast on CUDA (preset model)
  threads    torch and numba threads, powers of two up to the cores (preset model)
  joint      fast (voxel x2 + width x0.5, also run in bfloat16), near field (small region + voxel x0.5),
             bfloat16 + 16384 random points
  curve      the training budget: one run of --curve-scale x the preset's epochs, its checkpoints
             evaluated on the test split (AP@R40 against training CPU-minutes)
Each point: latency per frame (median and 90th percentile after warm-up, split by stage), peak
memory, parameters, AP@R40 and recall at 3D IoU 0.7 per range on the test split, and a Pareto
flag per range (latency against AP@R40, all models on one device).

Examples:
  python tools/tradeoff.py --preset smoke --out runs/tradeoff_smoke
  python tools/tradeoff.py --preset cpu --models second pillarnet --budget 240 --out runs/tradeoff_cpu
  python tools/tradeoff.py --preset cpu --knobs precision threads points --out runs/tradeoff_cpu
  python tools/tradeoff.py --preset cpu --budget 240 --out runs/tradeoff_cpu --dry-run   # the plan only

--budget MINUTES keeps the sweep within that wall time: tasks are planned in priority order
(the preset's points, the inference-only knobs, the trained knobs, the learning curves, the
joint points; cheapest first within a tier) by estimated cost, re-planned after each task with
the costs measured so far; what does not fit is listed as skipped, and a task still running at
the deadline is stopped (a training run keeps its checkpoint). The sweep resumes: a finished
point or training run in OUT is reused, an interrupted run continues; run it again with a
larger budget to add what was skipped.
Writes OUT/tradeoff.json, tradeoff.md, tradeoff.png (latency against AP@R40 per range, one
curve per model), learning_curve.png, and OUT/points/, runs/, curve/, logs/.
Units: milliseconds per frame, MiB = 2^20 bytes, seconds and minutes of wall time; AP and recall
are fractions.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import math
import os
import platform
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)
import models  # noqa: E402
from detbench.config import CONFIG_DIR, ConfigError  # noqa: E402
from detbench.data.regions import RANGE_NAMES, RANGES  # noqa: E402
from detbench.eval.tradeoff import (  # noqa: E402
    PRIOR_SECONDS, CostModel, Task, mark_pareto, plan_within_budget, plot_learning_curves, plot_tradeoff,
    train_seconds_at_step, tradeoff_markdown,
)
from detbench.train.run_config import load_run_config, preset_names  # noqa: E402
from detbench.utils.cli import UserError, run_main  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text, read_json  # noqa: E402

KNOBS = ("voxel", "width", "region", "points", "proposals", "precision", "threads", "joint", "curve")
VOXEL_FACTORS = (0.5, 2.0)
WIDTH_FACTORS = (0.5, 2.0)
REGION_RANGES = ("small", "moderate")  # "large" is the full grid: the preset's point
TEST_POINT_BUDGETS = (16384, 4096)
PROPOSAL_FACTORS = (0.25, 0.5)
ROI_FACTORS = (0.5, 2.0)
NUM_POINTS_FACTORS = (0.5, 2.0)
# Channel widths scaled by the width knob, per model (dotted keys under `model:`); a model not
# listed has no width knob.
WIDTH_KEYS = {
    "second": ("backbone3d.channels", "backbone3d.out_channels", "backbone2d.num_filters",
               "backbone2d.num_upsample_filters"),
    "pillarnet": ("encoder.pillar_channels", "encoder.channels", "neck.semantic_channels", "neck.up_channels",
                  "neck.out_channels", "head.shared_channels", "head.head_channels"),
    "pointrcnn": ("backbone.mlps", "backbone.fp_mlps", "point_head.cls_fc", "point_head.reg_fc", "roi_head.xyz_up",
                  "roi_head.sa_mlps", "roi_head.fc"),
}
WIDTH_KEYS["ct3d"] = WIDTH_KEYS["second"] + ("roi_head.hidden_dim", "roi_head.mlp_hidden",
                                             "roi_head.dim_feedforward", "roi_head.fc")
# one vehicle-sized box: enough for the data-derived config values when only a grid is checked
_PROBE_BOXES = [[20.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0]]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="smoke", choices=preset_names(),
                    help="the point every knob starts from (models trained at that preset's size and schedule); "
                         "default smoke")
    ap.add_argument("--models", nargs="+", default=None,
                    help=f"detectors (default all: {', '.join(models.REGISTRY)})")
    ap.add_argument("--knobs", nargs="+", default=list(KNOBS), choices=KNOBS, metavar="KNOB",
                    help=f"knobs to sweep (default all: {' '.join(KNOBS)}); the preset's point is always measured")
    ap.add_argument("--out", required=True, help="output folder (resumed when it exists)")
    ap.add_argument("--budget", type=float, default=None, metavar="MINUTES",
                    help="wall-time budget of the sweep in minutes (default: none, every point runs)")
    ap.add_argument("--height", type=float, default=1.8, help="LiDAR mounting height in metres (default 1.8)")
    ap.add_argument("--data", default=None, metavar="ROOT",
                    help="dataset root (docs/data-format.md); default: the preset's simulated dataset")
    ap.add_argument("--device", default="auto",
                    help="cpu, cuda or auto (cuda when present) for training and measuring (default auto)")
    ap.add_argument("--frames", type=int, default=20, help="timed test frames per point (default 20)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed passes first (default 3)")
    ap.add_argument("--eval-frames", type=int, default=0, metavar="N",
                    help="evaluate AP on N evenly spaced test frames (default 0: the whole test split)")
    ap.add_argument("--curve-scale", type=float, default=2.0,
                    help="the learning-curve run trains this many times the preset's epochs (default 2, so the "
                         "curve goes past the preset's budget; 1 reuses the preset's own run)")
    ap.add_argument("--curve-points", type=int, default=8,
                    help="about this many checkpoints of the learning-curve run are evaluated (default 8)")
    ap.add_argument("--dry-run", action="store_true", help="print the plan with estimated costs; run nothing")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: one measurement process
    return ap


# ---------------------------------------------------------------------------------------------
# the sweep: which points, with which config changes
# ---------------------------------------------------------------------------------------------
@dataclass
class Point:
    """One point of the sweep. `train`: dotted config overrides of the model trained for it ({} =
    the preset's model); `infer`: what changes at inference only (precision, threads, subsample
    [method, points], model {dotted: value})."""

    model: str
    name: str
    knob: str
    value: str
    train: dict = field(default_factory=dict)
    infer: dict = field(default_factory=dict)
    train_factor: float = 1.0  # estimated training cost relative to the preset's
    measure_factor: float = 1.0
    region_range: str | None = None  # region points: the range the shrunk grid models
    tier: int = 0  # planning priority: 0 preset, 1 inference-only, 2 trained, 4 joint (3 is the curve)

    @property
    def id(self) -> str:
        return _slug(self.name)

    train_id: str = ""  # the training run's folder: "preset", or the first point trained so + a digest

    @property
    def train_key(self) -> str:
        return json.dumps(self.train, sort_keys=True)


def _slug(text: str) -> str:
    out = "".join(c if c.isalnum() or c in ".-" else "_" for c in text.lower())
    return "_".join(p for p in out.split("_") if p)


def _get(cfg: dict, dotted: str):
    node = cfg
    for k in dotted.split("."):
        if not isinstance(node, dict) or k not in node:
            return None
        node = node[k]
    return node


def _set(cfg: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    node = cfg
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def scale_widths(model: str, model_cfg: dict, factor: float) -> dict:
    """{"model.<key>": scaled value} for the model's WIDTH_KEYS present in `model_cfg`: every
    integer (nested lists too) times `factor`, rounded, at least 1; CT3D's hidden_dim stays a
    multiple of its attention heads. {} when the model has no width keys."""
    def scale(v):
        if isinstance(v, list):
            return [scale(x) for x in v]
        if isinstance(v, bool) or not isinstance(v, int):
            return v
        return max(1, int(round(v * factor)))

    out = {}
    for key in WIDTH_KEYS.get(model, ()):
        value = _get(model_cfg, key)
        if value is None:
            continue
        new = scale(value)
        if key == "roi_head.hidden_dim":
            heads = int(_get(model_cfg, "roi_head.heads") or 1)
            new = max(heads, int(round(new / heads)) * heads)
        out[f"model.{key}"] = new
    return out


def _builds(model: str, model_cfg: dict) -> bool:
    import numpy as np

    try:
        cfg = models.prepare_model_config(model, model_cfg, np.asarray(_PROBE_BOXES, np.float32))
        models.build_model(model, cfg)
    except ValueError:
        return False
    return True


def fit_range(model: str, model_cfg: dict, x_max: float, y_half: float) -> list[float]:
    """The smallest point-cloud range [x0, -y, z0, x1, y, z1] with x1 >= `x_max` and y >= `y_half`
    (metres; x0, z0, z1 as the config's) on which the model builds: a whole number of voxels
    that divides by the network's strides (tried as multiples of voxel x 2^k). Raises
    ValueError when none up to 2^7 voxels does."""
    pcr = [float(v) for v in model_cfg["point_cloud_range"]]
    vs = model_cfg.get("voxel_size")
    if not vs:  # a point-based model: no grid to fit
        cand = [pcr[0], -round(y_half, 6), pcr[2], round(x_max, 6), round(y_half, 6), pcr[5]]
        return cand if _builds(model, {**model_cfg, "point_cloud_range": cand}) else _no_fit(model, x_max, y_half)
    for k in range(8):
        sx, sy = float(vs[0]) * 2 ** k, float(vs[1]) * 2 ** k
        x1 = pcr[0] + math.ceil((x_max - pcr[0]) / sx - 1e-6) * sx
        half = math.ceil(2 * y_half / sy - 1e-6) * sy / 2
        cand = [pcr[0], -round(half, 6), pcr[2], round(x1, 6), round(half, 6), pcr[5]]
        if _builds(model, {**model_cfg, "point_cloud_range": cand}):
            return cand
    return _no_fit(model, x_max, y_half)


def _no_fit(model, x_max, y_half):
    raise ValueError(f"{model}: no point-cloud range with x up to >= {x_max:g} m and |y| >= {y_half:g} m builds "
                     f"with this voxel size; change the knob's values in tools/tradeoff.py")


def sweep_points(model: str, model_cfg: dict, knobs, device: str, cores: int, default_threads: int) -> list[Point]:
    """The points of one model's sweep, from its preset `model:` config section."""
    pts = [Point(model, "preset", "preset", "the preset's settings")]
    mc = model_cfg
    pcr = [float(v) for v in mc["point_cloud_range"]]
    vs = mc.get("voxel_size")
    margin_x = max(0.0, pcr[3] - RANGES["large"][1])
    margin_y = max(0.0, pcr[4] - RANGES["large"][2])
    is_two_stage = isinstance(_get(mc, "roi_head.proposals"), dict)
    num_points = _get(mc, "sampling.num_points")

    def voxel_over(f: float) -> dict:
        new_vs = [round(float(vs[0]) * f, 6), round(float(vs[1]) * f, 6), float(vs[2])]
        over = {"model.voxel_size": new_vs}
        cfg = {**mc, "voxel_size": new_vs}
        if not _builds(model, cfg):
            over["model.point_cloud_range"] = fit_range(model, cfg, pcr[3], pcr[4])
        return over

    if "voxel" in knobs and vs:
        for f in VOXEL_FACTORS:
            pts.append(Point(model, f"voxel x{f:g}", "voxel", f"{float(vs[0]) * f:g} x {float(vs[1]) * f:g} m",
                             voxel_over(f), train_factor=1 / f ** 2, tier=2))
    if "width" in knobs and WIDTH_KEYS.get(model):
        for f in WIDTH_FACTORS:
            pts.append(Point(model, f"width x{f:g}", "width", f"channels x{f:g}", scale_widths(model, mc, f),
                             train_factor=f ** 2, tier=2))
    region_over = {}
    if "region" in knobs or "joint" in knobs:
        for r in REGION_RANGES:
            _, x1, y = RANGES[r]
            fitted = fit_range(model, mc, x1 + margin_x, y + margin_y)
            region_over[r] = (fitted, (fitted[3] - fitted[0]) * (fitted[4] - fitted[1])
                              / ((pcr[3] - pcr[0]) * (pcr[4] - pcr[1])))
    if "region" in knobs:
        for r in REGION_RANGES:
            fitted, area = region_over[r]
            _, x1, y = RANGES[r]
            pts.append(Point(model, f"region {r}", "region", f"x <= {x1:g} m, |y| <= {y:g} m (grid x to {fitted[3]:g}, "
                             f"|y| to {fitted[4]:g} m)", {"model.point_cloud_range": fitted},
                             train_factor=max(area, 0.05), region_range=r, tier=2))
    if "points" in knobs:
        for method in ("random", "fps"):
            for n in TEST_POINT_BUDGETS:
                pts.append(Point(model, f"{method} {n} points", "points", f"{n} points per frame ({method}, test time)",
                                 infer={"subsample": [method, n]}, measure_factor=1.2 if method == "fps" else 1.0,
                                 tier=1))
        if num_points:
            for f in NUM_POINTS_FACTORS:
                n = max(64, int(round(num_points * f)))
                pts.append(Point(model, f"sampled points x{f:g}", "points", f"{n} sampled points per frame (trained)",
                                 {"model.sampling.num_points": n}, train_factor=f, tier=2))
    if "proposals" in knobs and is_two_stage:
        test_k = int(_get(mc, "roi_head.proposals.test.post_nms_top_k"))
        for f in PROPOSAL_FACTORS:
            k = max(1, int(round(test_k * f)))
            pts.append(Point(model, f"test proposals x{f:g}", "proposals", f"{k} proposals refined (test time)",
                             infer={"model": {"roi_head.proposals.test.post_nms_top_k": k}}, tier=1))
        rois = int(_get(mc, "roi_head.targets.roi_per_image"))
        for f in ROI_FACTORS:
            k = max(2, int(round(rois * f)))
            pts.append(Point(model, f"training rois x{f:g}", "proposals", f"{k} training RoIs per frame (trained)",
                             {"model.roi_head.targets.roi_per_image": k}, tier=2))
    if "precision" in knobs:
        for prec in (("fp16", "bf16") if device.startswith("cuda") else ("bf16",)):
            pts.append(Point(model, prec, "precision", {"bf16": "bfloat16 autocast", "fp16": "float16 autocast"}[prec],
                             infer={"precision": prec}, measure_factor=1.5, tier=1))
    if "threads" in knobs:
        counts = sorted({2 ** k for k in range(8) if 2 ** k <= cores} | {cores})
        for n in counts:
            if n != default_threads:
                pts.append(Point(model, f"{n} threads", "threads", f"{n} torch / numba threads", infer={"threads": n},
                                 tier=1))
    if "joint" in knobs:
        fast = dict(scale_widths(model, mc, 0.5))
        if vs:
            fast.update(voxel_over(2.0))
        elif num_points:
            fast["model.sampling.num_points"] = max(64, int(round(num_points * 0.5)))
        if fast:
            pts.append(Point(model, "fast", "joint", "voxel x2 (or sampled points x0.5) + width x0.5", fast,
                             train_factor=0.25 * 0.25, tier=4))
            pts.append(Point(model, "fast + bf16", "joint", "fast, run in bfloat16", fast,
                             infer={"precision": "bf16"}, train_factor=0.25 * 0.25, measure_factor=1.5, tier=4))
        fitted, area = region_over["small"]
        near = {"model.point_cloud_range": fitted}
        if vs:
            fine_vs = [round(float(vs[0]) * 0.5, 6), round(float(vs[1]) * 0.5, 6), float(vs[2])]
            near["model.voxel_size"] = fine_vs
            near["model.point_cloud_range"] = fit_range(model, {**mc, "voxel_size": fine_vs},
                                                        RANGES["small"][1] + margin_x, RANGES["small"][2] + margin_y)
        elif num_points:
            near["model.sampling.num_points"] = int(num_points * 2)
        pts.append(Point(model, "near field", "joint", "small region + voxel x0.5 (or sampled points x2)", near,
                         train_factor=max(area, 0.05) * 4, region_range="small", tier=4))
        pts.append(Point(model, "bf16 + random 16384 points", "joint", "bfloat16 and 16384 random points (test time)",
                         infer={"precision": "bf16", "subsample": ["random", 16384]}, measure_factor=1.5, tier=4))
    seen, runs = set(), {}
    for p in pts:
        if p.id in seen:
            raise AssertionError(f"two points of {model} named {p.name!r}")
        seen.add(p.id)
        digest = hashlib.sha1(p.train_key.encode()).hexdigest()[:6]
        p.train_id = runs.setdefault(p.train_key, "preset" if not p.train else f"{p.id}-{digest}")
    return pts


# ---------------------------------------------------------------------------------------------
# the measuring worker (its own process: its peak memory and thread count are its own)
# ---------------------------------------------------------------------------------------------
class SubsampledFrames:
    """The frames of a dataset with each one's points cropped to the model's range and then cut to
    `budget` points by "random" (seeded per frame) or "fps" (farthest point sampling);
    `seconds` sums the time spent subsampling."""

    def __init__(self, frames, point_cloud_range, method: str, budget: int):
        self.frames, self.pcr, self.method, self.budget = frames, point_cloud_range, method, int(budget)
        self.seconds = 0.0

    def __len__(self):
        return len(self.frames)

    def subsample(self, points, index: int):
        import numpy as np
        import torch

        from detbench.ops import farthest_point_sample

        if len(points) <= self.budget:
            return points
        if self.method == "random":
            keep = np.sort(np.random.default_rng(index).choice(len(points), self.budget, replace=False))
        elif self.method == "fps":
            keep = np.sort(farthest_point_sample(torch.from_numpy(np.ascontiguousarray(points[:, :3])),
                                                 self.budget).numpy())
        else:
            raise ValueError(f"unknown subsampling method {self.method!r}; use random or fps")
        return np.ascontiguousarray(points[keep])

    def __getitem__(self, i):
        from detbench.train.inference import frame_sample

        frame = self.frames[i]
        cropped = frame_sample(frame, self.pcr).points
        t0 = time.perf_counter()
        pts = self.subsample(cropped, i)
        self.seconds += time.perf_counter() - t0
        return dataclasses.replace(frame, points=pts)


def _autocast(device, precision: str | None):
    import contextlib

    import torch

    if not precision or precision == "fp32":
        return contextlib.nullcontext()
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}[precision]
    return torch.autocast(device_type=device.type, dtype=dtype)


def load_for_inference(ckpt_path: str, device, model_overrides: dict):
    """(model in eval mode, checkpoint dict): the checkpoint's model rebuilt with `model_overrides`
    (dotted keys under `model:` that change inference only, e.g. the test proposals)."""
    from detbench.train.checkpoint import load_checkpoint, load_model_weights

    ck = load_checkpoint(ckpt_path)
    cfg = copy.deepcopy(ck["config"]["model"])
    for key, value in (model_overrides or {}).items():
        _set(cfg, key, value)
    model = models.build_model(ck["model_name"], cfg)
    load_model_weights(model, ck, ckpt_path)
    return model.to(device).eval(), ck, cfg


def evaluate_checkpoint(model, cfg_model: dict, ck: dict, test, device, precision, subsample, eval_frames: int):
    """{range: {ap_r40, recall, lidar_detected}} of all vehicles on the test split (or `eval_frames`
    evenly spaced frames of it), predicted under `precision` and `subsample`."""
    import numpy as np

    from detbench.eval.evaluate import EvalConfig, evaluate_predictions
    from detbench.train.inference import predict_frames

    frames = test
    if eval_frames and eval_frames < len(test):
        frames = [test[int(i)] for i in np.linspace(0, len(test) - 1, eval_frames).astype(int)]
    ecfg = EvalConfig.from_dict(ck["config"].get("eval"))
    source = SubsampledFrames(frames, cfg_model["point_cloud_range"], *subsample) if subsample else frames
    with _autocast(device, precision):
        preds = predict_frames(model, source, cfg_model["point_cloud_range"], device=device, batch_size=4,
                               progress=False)
    rep = evaluate_predictions(frames, preds, iou_threshold=ecfg.iou_threshold,
                               score_threshold=ecfg.score_threshold, extras=False, progress=False)
    return {r: {k: rep["results"][r]["all"][k] for k in ("ap_r40", "recall", "lidar_detected")}
            for r in RANGE_NAMES}, len(frames)


def measure_point(spec: dict) -> dict:
    """Latency (split by stage), peak memory, parameters and accuracy of one point."""
    import io

    import numpy as np
    import torch

    from detbench import runtime
    from detbench.data import Height3Dataset
    from detbench.data.batch import Sample, collate
    from detbench.train.inference import frame_sample
    from detbench.utils.bench import StageTimer, median_p90, peak_rss_mib, reset_peak_rss, rss_mib

    infer = spec["infer"]
    if infer.get("threads"):
        runtime.set_threads(int(infer["threads"]))
    device = torch.device(spec["device"])
    peak_reset = reset_peak_rss()  # the peak below then covers the model, frames and timed passes only
    rss0 = rss_mib() or peak_rss_mib()
    model, ck, cfg_model = load_for_inference(spec["ckpt"], device, infer.get("model"))
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    test = Height3Dataset(spec["data"], spec["height"], "test")
    if len(test) == 0:
        raise UserError(f"{spec['data']}: the test split at {spec['height']:g} m has no frames")
    pcr = cfg_model["point_cloud_range"]
    sub = SubsampledFrames(test, pcr, *infer["subsample"]) if infer.get("subsample") else None
    timer = StageTimer(model, model.STAGES, device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rows, npts = [], []
    n = spec["warmup"] + spec["frames"]
    with torch.no_grad(), _autocast(device, infer.get("precision")):
        for i in range(n):
            frame = test[i % len(test)]
            points = frame_sample(frame, pcr).points  # the crop is input preparation, not timed
            t_sub = 0.0
            if sub is not None:
                ts = time.perf_counter()
                points = sub.subsample(points, i % len(test))
                t_sub = time.perf_counter() - ts
            ms = timer.time_inference(model, collate([Sample(points, np.zeros((0, 7), np.float32),
                                                             frame.frame_id)]).to(device))
            if i >= spec["warmup"]:
                row = {"subsample": t_sub * 1000} if sub is not None else {}
                row.update(ms)
                row["total"] += t_sub * 1000
                rows.append(row)
                npts.append(len(points))
    peak_rss = peak_rss_mib()
    result = {"latency_ms": median_p90(rows), "frames_timed": len(rows),
              "points_per_frame": int(np.median(npts)) if npts else 0,
              "peak_rss_mib": round(peak_rss, 1), "rss_before_model_mib": round(rss0, 1),
              "peak_rss_since": "model load" if peak_reset else "process start",
              "parameters": int(sum(p.numel() for p in model.parameters())), "weights_mb": round(buf.tell() / 1e6, 3),
              "threads": torch.get_num_threads(), "point_cloud_range": pcr}
    if device.type == "cuda":
        result["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated(device) / 2 ** 20, 1)
    try:
        result["accuracy"], result["frames_evaluated"] = evaluate_checkpoint(
            model, cfg_model, ck, test, device, infer.get("precision"), infer.get("subsample"), spec["eval_frames"])
    except FloatingPointError as e:  # e.g. a precision whose outputs overflow: reported, not fatal
        result["accuracy"], result["error"] = None, str(e)
    result["runtime"] = runtime.describe()
    return result


def curve_worker(spec: dict) -> None:
    """Evaluate every checkpoint of a learning-curve run not yet evaluated (one file each)."""
    import torch

    from detbench.data import Height3Dataset

    device = torch.device(spec["device"])
    test = Height3Dataset(spec["data"], spec["height"], "test")
    out = Path(spec["out"])
    for path in sorted((Path(spec["run"]) / "checkpoints").glob("epoch_*.pt")):
        target = out / f"{path.stem}.json"
        if target.is_file():
            continue
        model, ck, cfg_model = load_for_inference(str(path), device, {})
        acc, n = evaluate_checkpoint(model, cfg_model, ck, test, device, None, None, spec["eval_frames"])
        atomic_write_json(target, {"checkpoint": path.name, "global_step": int(ck["state"]["global_step"]),
                                   "epoch": int(ck["state"]["epoch"]), "accuracy": acc, "frames_evaluated": n})


def worker_main(spec_json: str) -> int:
    spec = json.loads(spec_json)
    if spec["mode"] == "curve":
        curve_worker(spec)
        return 0
    result = measure_point(spec)
    atomic_write_json(spec["out"], {"spec": spec["key"], **result})
    return 0


# ---------------------------------------------------------------------------------------------
# the orchestrator
# ---------------------------------------------------------------------------------------------
@dataclass
class Sweep:
    """What one invocation works on: paths, settings, the points, training runs and curve runs."""

    args: argparse.Namespace
    out: Path
    root: Path
    device: str
    preset_cfgs: dict  # model -> run config of the preset
    points: list[Point]
    n_train: int
    costs: CostModel
    t0: float
    deadline: float | None
    done: set = field(default_factory=set)
    failed: dict = field(default_factory=dict)  # task id -> error text


def _run_dir(sw: Sweep, model: str, train_id: str) -> Path:
    return sw.out / "runs" / model / train_id


def _point_file(sw: Sweep, p: Point) -> Path:
    return sw.out / "points" / p.model / f"{p.id}.json"


def _curve_epochs(sw: Sweep, model: str) -> int:
    return max(1, int(round(sw.preset_cfgs[model]["train"]["epochs"] * sw.args.curve_scale)))


def _curve_train_id(sw: Sweep, model: str) -> str:
    """The learning-curve run's folder: the preset's own run at --curve-scale 1, else curve-<epochs>ep."""
    epochs = _curve_epochs(sw, model)
    return "preset" if epochs == int(sw.preset_cfgs[model]["train"]["epochs"]) else f"curve-{epochs}ep"


def _curve_dir(sw: Sweep, model: str) -> Path:
    """Where the learning-curve run's checkpoint evaluations go (one JSON per checkpoint)."""
    return sw.out / "curve" / model / _curve_train_id(sw, model)


def _checkpoint_every(sw: Sweep, model: str) -> int:
    """Steps between the learning-curve run's extra checkpoints: about --curve-points in all."""
    bs = int(sw.preset_cfgs[model]["train"]["batch_size"])
    total = _curve_epochs(sw, model) * math.ceil(sw.n_train / bs)
    return max(1, math.ceil(total / max(1, sw.args.curve_points)))


def _curve_checkpoints(sw: Sweep, model: str) -> int:
    bs = int(sw.preset_cfgs[model]["train"]["batch_size"])
    per = math.ceil(sw.n_train / bs)
    every = _checkpoint_every(sw, model)
    total = _curve_epochs(sw, model) * per
    return len(set(range(every, total + 1, every)) | {per * (e + 1) for e in range(_curve_epochs(sw, model))})


def _train_overrides(sw: Sweep, model: str, train_id: str, point_over: dict) -> list[str]:
    sets = {"train.tensorboard": False, "train.bev_image": False, "train.keep_checkpoints": 1, **point_over}
    if "curve" in sw.args.knobs and train_id == _curve_train_id(sw, model):
        sets.update({"train.keep_checkpoints": 0, "train.checkpoint_every_steps": _checkpoint_every(sw, model)})
    if train_id.startswith("curve-"):
        sets["train.epochs"] = _curve_epochs(sw, model)
    return [f"{k}={json.dumps(v)}" for k, v in sets.items()]


def _train_done(run: Path) -> bool:
    s = run / "train_summary.json"
    return s.is_file() and not read_json(s).get("interrupted", False)


def _point_key(sw: Sweep, p: Point) -> dict:
    """What a point's stored result must match to be reused on a rerun."""
    return {"preset": sw.args.preset, "height": sw.args.height, "data": str(sw.root), "device": sw.device,
            "train": p.train, "infer": p.infer, "frames": sw.args.frames, "warmup": sw.args.warmup,
            "eval_frames": sw.args.eval_frames}


def _point_done(sw: Sweep, p: Point) -> bool:
    f = _point_file(sw, p)
    return f.is_file() and read_json(f).get("spec") == _point_key(sw, p)


def _curve_done(sw: Sweep, model: str) -> bool:
    run = _run_dir(sw, model, _curve_train_id(sw, model))
    if not _train_done(run):
        return False
    ckpts = sorted((run / "checkpoints").glob("epoch_*.pt"))
    return bool(ckpts) and all((_curve_dir(sw, model) / f"{c.stem}.json").is_file() for c in ckpts)


def run_until_deadline(cmd: list[str], log: Path, deadline: float | None, stop_signal=signal.SIGTERM) -> dict:
    """Run `cmd` (output to `log`); at `deadline` (perf_counter seconds) send `stop_signal`, then kill
    after 120 s. Returns {returncode, timed_out, wall_s, cpu_s} (cpu_s: the child's user + system
    seconds, its own children included)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    timed_out = False
    with open(log, "a", encoding="utf-8") as fh:
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        try:
            while True:
                try:
                    left = None if deadline is None else max(0.0, deadline - time.perf_counter())
                    proc.wait(timeout=left)
                    break
                except subprocess.TimeoutExpired:
                    timed_out = True
                    proc.send_signal(stop_signal)
                    try:
                        proc.wait(timeout=120)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
                    break
        except BaseException:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=120)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            raise
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    return {"returncode": proc.returncode, "timed_out": timed_out, "wall_s": time.perf_counter() - t0, "cpu_s": cpu}


def _log_tail(log: Path, n: int = 3000) -> str:
    try:
        return log.read_text(encoding="utf-8", errors="replace")[-n:]
    except OSError:
        return ""


def do_train(sw: Sweep, model: str, train_id: str, over: dict, factor: float) -> None:
    run = _run_dir(sw, model, train_id)
    resume = ["--resume"] if (run / "checkpoints").is_dir() else []
    cmd = [sys.executable, str(ROOT / "tools" / "train.py"), "--model", model, "--height", str(sw.args.height),
           "--preset", sw.args.preset, "--data", str(sw.root), "--device", sw.device, "--out", str(run),
           "--no-eval", "--no-progress", *resume]
    for s in _train_overrides(sw, model, train_id, over):
        cmd += ["--set", s]
    res = run_until_deadline(cmd, sw.out / "logs" / f"train_{model}_{train_id}.log", sw.deadline)
    rec_path = run / "tradeoff_train.json"
    rec = read_json(rec_path) if rec_path.is_file() else {"overrides": over, "wall_s": 0.0, "cpu_s": 0.0,
                                                           "invocations": 0}
    rec.update(wall_s=rec["wall_s"] + res["wall_s"], cpu_s=rec["cpu_s"] + res["cpu_s"],
               invocations=rec["invocations"] + 1)
    atomic_write_json(rec_path, rec)
    if res["timed_out"]:
        raise TimeoutError(f"stopped at the budget's end after {res['wall_s']:.0f} s (its checkpoint is kept; "
                           f"run again with a larger --budget to continue it)")
    if res["returncode"] != 0 or not _train_done(run):
        raise RuntimeError(f"training failed (exit {res['returncode']}); log {sw.out / 'logs'}:\n"
                           + _log_tail(sw.out / "logs" / f"train_{model}_{train_id}.log"))
    if not resume:  # a resumed run's time is partial: not a cost sample
        sw.costs.observe("train", model, factor, res["wall_s"])


def _ckpt_of(sw: Sweep, model: str, train_id: str) -> str:
    return read_json(_run_dir(sw, model, train_id) / "train_summary.json")["checkpoint"]


def _worker(sw: Sweep, spec: dict, log: Path) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec), "--out", str(sw.out)]
    res = run_until_deadline(cmd, log, sw.deadline, stop_signal=signal.SIGKILL)
    if res["timed_out"]:
        raise TimeoutError(f"stopped at the budget's end after {res['wall_s']:.0f} s")
    if res["returncode"] != 0:
        raise RuntimeError(f"exit {res['returncode']}; log {log}:\n{_log_tail(log)}")
    return res


def do_measure(sw: Sweep, p: Point) -> None:
    spec = {"mode": "point", "key": _point_key(sw, p), "ckpt": _ckpt_of(sw, p.model, p.train_id), "infer": p.infer,
            "device": sw.device, "data": str(sw.root), "height": sw.args.height, "frames": sw.args.frames,
            "warmup": sw.args.warmup, "eval_frames": sw.args.eval_frames, "out": str(_point_file(sw, p))}
    res = _worker(sw, spec, sw.out / "logs" / f"measure_{p.model}_{p.id}.log")
    sw.costs.observe("measure", p.model, p.measure_factor, res["wall_s"])


def do_curve(sw: Sweep, model: str) -> None:
    run = _run_dir(sw, model, _curve_train_id(sw, model))
    n = len(list((run / "checkpoints").glob("epoch_*.pt")))
    spec = {"mode": "curve", "run": str(run), "device": sw.device, "data": str(sw.root), "height": sw.args.height,
            "eval_frames": sw.args.eval_frames, "out": str(_curve_dir(sw, model))}
    todo = sum(not (_curve_dir(sw, model) / f"{c.stem}.json").is_file()
               for c in (run / "checkpoints").glob("epoch_*.pt"))
    res = _worker(sw, spec, sw.out / "logs" / f"curve_{model}.log")
    if todo == n and n:
        sw.costs.observe("curve_eval", model, n, res["wall_s"])


def build_tasks(sw: Sweep) -> tuple[list[Task], dict]:
    """Tasks in priority order with their current estimates, and id -> (kind, args) to run them."""
    action: dict = {}
    trains: dict = {}  # (model, train_id) -> Task
    tiers: dict[int, list[tuple[float, list[Task]]]] = {t: [] for t in range(5)}

    def train_task(model, train_id, over, factor) -> str:
        tid = f"train {model} {train_id}"
        if (model, train_id) not in trains:
            done = _train_done(_run_dir(sw, model, train_id))
            trains[(model, train_id)] = Task(tid, 0.0 if done else sw.costs.estimate("train", model, factor))
            action[tid] = ("train", (model, train_id, over, factor))
            if done:
                sw.done.add(tid)
        return tid

    for p in sw.points:
        t = train_task(p.model, p.train_id, p.train, p.train_factor)
        pid = f"measure {p.model} {p.name}"
        done = _point_done(sw, p)
        task = Task(pid, 0.0 if done else sw.costs.estimate("measure", p.model, p.measure_factor), (t,))
        action[pid] = ("measure", (p,))
        if done:
            sw.done.add(pid)
        cost = task.cost_s + trains[(p.model, p.train_id)].cost_s
        tiers[p.tier].append((cost, [task]))
    if "curve" in sw.args.knobs:
        for model in sw.preset_cfgs:
            train_id = _curve_train_id(sw, model)
            t = train_task(model, train_id, {}, sw.args.curve_scale)
            cid = f"curve {model}"
            done = _curve_done(sw, model)
            task = Task(cid, 0.0 if done else sw.costs.estimate("curve_eval", model, _curve_checkpoints(sw, model)),
                        (t,))
            action[cid] = ("curve", (model,))
            if done:
                sw.done.add(cid)
            tiers[3].append((task.cost_s + trains[(model, train_id)].cost_s, [task]))
    ordered = [task for tier in range(5)
               for _, group in (tiers[tier] if tier == 0 else sorted(tiers[tier], key=lambda x: x[0]))
               for task in group]
    # the preset's training first within tier 0 comes through the measure tasks' needs
    return list(trains.values()) + ordered, action


def plan(sw: Sweep):
    tasks, action = build_tasks(sw)
    trains = [t for t in tasks if t.id.startswith("train ")]
    targets = [t for t in tasks if not t.id.startswith("train ")]
    # a training task is planned only as a need of a measurement or curve; failed work is left out
    live = [t for t in targets if t.id not in sw.failed and not any(n in sw.failed for n in t.needs)]
    pending = [t for t in live if t.id not in sw.done]
    left = None
    if sw.deadline is not None:
        left = max(0.0, sw.deadline - time.perf_counter() - _reserve(sw))
    p = plan_within_budget([*trains, *targets], left, goals=[t.id for t in pending]) if pending else None
    return p, {t.id: t for t in tasks}, action


def _reserve(sw: Sweep) -> float:
    """Seconds kept back for writing the report at the end of a budgeted sweep."""
    return min(30.0, 0.05 * sw.args.budget * 60) if sw.args.budget else 0.0


def run_sweep(sw: Sweep, progress: bool) -> list[dict]:
    """Run planned tasks one at a time, re-planning after each; returns the skipped tasks."""
    from tqdm import tqdm

    bar = tqdm(total=0, desc="tradeoff", unit="task", disable=not progress, dynamic_ncols=True)
    try:
        while True:
            p, by_id, action = plan(sw)
            if p is None or not p.run:
                break
            bar.total = bar.n + sum(1 for t in p.run if t not in sw.done)
            bar.refresh()
            tid = next((t for t in p.run if t not in sw.done), None)
            if tid is None:
                break
            est = by_id[tid].cost_s
            kind, a = action[tid]
            t0 = time.perf_counter()
            try:
                if kind == "train":
                    do_train(sw, *a)
                elif kind == "measure":
                    do_measure(sw, *a)
                else:
                    do_curve(sw, *a)
                sw.done.add(tid)
                status = "done"
            except TimeoutError as e:
                sw.failed[tid] = str(e)
                status = "stopped at the deadline"
                tqdm.write(f"{tid}: {e}")
                _write_outputs(sw, [], final=False)
                break
            except RuntimeError as e:
                sw.failed[tid] = str(e)
                status = "FAILED"
                tqdm.write(f"{tid}: failed: {str(e).splitlines()[0]} (log in {sw.out / 'logs'})")
            bar.update(1)
            left = "" if sw.deadline is None else f"; {max(0, sw.deadline - time.perf_counter()) / 60:.1f} min left"
            tqdm.write(f"{tid}: {status} in {time.perf_counter() - t0:.0f} s (estimated {est:.0f} s){left}")
            _write_outputs(sw, [], final=False)
    finally:
        bar.close()
    p, by_id, _ = plan(sw)
    skipped = []
    if p is not None:
        for tid in p.skipped:
            skipped.append({"task": tid, "estimated_s": round(by_id[tid].cost_s + sum(
                by_id[n].cost_s for n in by_id[tid].needs), 1), "reason": p.reasons.get(tid, "")})
        for tid in p.run:  # planned but never reached (the loop stopped at the deadline)
            if tid not in sw.done and not tid.startswith("train "):
                skipped.append({"task": tid, "estimated_s": round(by_id[tid].cost_s, 1),
                                "reason": "the sweep stopped at the budget's end"})
    for tid, t in by_id.items():  # work that needs a failed task
        if tid not in sw.failed and any(n in sw.failed for n in t.needs) and tid not in sw.done:
            skipped.append({"task": tid, "estimated_s": round(t.cost_s, 1),
                            "reason": f"needs {next(n for n in t.needs if n in sw.failed)}, which failed or stopped"})
    return skipped


def collect_points(sw: Sweep) -> list[dict]:
    out = []
    for p in sw.points:
        if not _point_done(sw, p):
            continue
        r = read_json(_point_file(sw, p))
        r.pop("spec", None)
        acc = r.get("accuracy")
        if acc is not None and p.region_range:  # ranges beyond the shrunk grid are not modelled
            inside = RANGE_NAMES[:RANGE_NAMES.index(p.region_range) + 1]
            acc = {k: (v if k in inside else None) for k, v in acc.items()}
        elif acc is None:
            acc = {k: None for k in RANGE_NAMES}
        out.append({"model": p.model, "point": p.name, "knob": p.knob, "value": p.value,
                    "trained": "at this point" if p.train else "preset model", "device": sw.device,
                    "train_overrides": p.train, "inference": p.infer, "region_range": p.region_range,
                    **{k: v for k, v in r.items() if k != "accuracy"}, "accuracy": acc})
    return mark_pareto(out)


def _history(run: Path) -> list[dict]:
    h = run / "history.json"
    return read_json(h).get("epochs", []) if h.is_file() else []


def _cpu_ratio(run: Path) -> float | None:
    rec = run / "tradeoff_train.json"
    if not rec.is_file():
        return None
    r = read_json(rec)
    return r["cpu_s"] / r["wall_s"] if r.get("wall_s") else None


def collect_curves(sw: Sweep) -> tuple[dict, dict]:
    """({model: curve}, {model: the preset run's end: train_cpu_s, accuracy}) from what is on disk."""
    curves, ends = {}, {}
    for model in sw.preset_cfgs:
        run = _run_dir(sw, model, _curve_train_id(sw, model))
        files = sorted(_curve_dir(sw, model).glob("*.json"))
        hist, ratio = _history(run), _cpu_ratio(run)
        if files and hist and ratio is not None:
            per_epoch = hist[0]["global_step"]
            pts = []
            for f in files:
                e = read_json(f)
                try:
                    wall = train_seconds_at_step(hist, e["global_step"])
                except ValueError:
                    continue
                pts.append({**e, "epochs_done": e["global_step"] / per_epoch, "train_wall_s": round(wall, 1),
                            "train_cpu_s": round(wall * ratio, 1)})
            pts.sort(key=lambda e: e["global_step"])
            curves[model] = {"run": str(run.relative_to(sw.out)), "epochs": _curve_epochs(sw, model),
                             "cpu_per_wall": round(ratio, 2), "points": pts}
        prun = _run_dir(sw, model, "preset")
        preset_pt = next((p for p in sw.points if p.model == model and p.knob == "preset"), None)
        if preset_pt is not None and _point_done(sw, preset_pt) and _history(prun) and _cpu_ratio(prun) is not None:
            wall = sum(e["seconds"] for e in _history(prun))
            ends[model] = {"train_wall_s": round(wall, 1), "train_cpu_s": round(wall * _cpu_ratio(prun), 1),
                           "accuracy": read_json(_point_file(sw, preset_pt)).get("accuracy")}
    return curves, ends


def _meta(sw: Sweep) -> dict:
    import torch

    sim = CONFIG_DIR / "sim.yaml"
    return {"preset": sw.args.preset, "height": sw.args.height, "models": list(sw.preset_cfgs),
            "knobs": list(sw.args.knobs), "device": sw.device, "data": str(sw.root),
            "sim_config_sha256": hashlib.sha256(sim.read_bytes()).hexdigest()[:12] if sim.is_file() else None,
            "frames": sw.args.frames, "warmup": sw.args.warmup, "eval_frames": sw.args.eval_frames,
            "budget_min": sw.args.budget, "elapsed_s": round(time.perf_counter() - sw.t0, 1),
            "machine": platform.machine(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "default_threads": torch.get_num_threads(), "load_average_start": sw.args.load_start,
            "load_average_end": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
            "date": time.strftime("%Y-%m-%d %H:%M"), "curve_scale": sw.args.curve_scale}


def _write_outputs(sw: Sweep, skipped: list[dict], final: bool) -> dict:
    points = collect_points(sw)
    curves, ends = collect_curves(sw)
    result = {"meta": _meta(sw), "points": points, "curves": curves, "preset_run_ends": ends, "skipped": skipped,
              "failed": [{"task": k, "error": v} for k, v in sw.failed.items()]}
    atomic_write_json(sw.out / "tradeoff.json", result)
    atomic_write_text(sw.out / "tradeoff.md", tradeoff_markdown(result))
    if final:
        if points:
            plot_tradeoff(points, sw.out / "tradeoff.png")
        if curves:
            plot_learning_curves(curves, sw.out / "learning_curve.png", ends)
    return result


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        return worker_main(args.worker)
    import torch

    t0 = time.perf_counter()
    args.load_start = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    names = args.models or list(models.REGISTRY)
    for bad, ok in ((args.frames < 1, "--frames must be >= 1"), (args.warmup < 0, "--warmup must be >= 0"),
                    (args.eval_frames < 0, "--eval-frames must be >= 0"),
                    (args.budget is not None and not args.budget > 0, "--budget must be > 0 minutes"),
                    (not args.curve_scale > 0, "--curve-scale must be > 0"),
                    (args.curve_points < 1, "--curve-points must be >= 1")):
        if bad:
            raise UserError(ok)
    try:
        for n in names:
            models.get_model_class(n)
        cfgs = {n: load_run_config(n, args.preset) for n in names}
    except (ConfigError, ValueError) as e:
        raise UserError(str(e)) from None
    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"--device {args.device}: CUDA is not available here; use --device cpu")

    from detbench.data import Height3Dataset
    from detbench.sim.dataset import default_dataset

    if args.data:
        root = Path(args.data).resolve()
        if not root.is_dir():
            raise UserError(f"--data {args.data}: no such folder; give the dataset root (docs/data-format.md)")
    else:
        root = default_dataset(cfgs[names[0]]["data"], progress=not args.no_progress)
    try:
        n_train = len(Height3Dataset(root, args.height, "train"))
        Height3Dataset(root, args.height, "test")
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise UserError(str(e)) from None
    cores, default_threads = os.cpu_count() or 1, torch.get_num_threads()
    points = []
    try:
        for n in names:
            points += sweep_points(n, cfgs[n]["model"], args.knobs, device, cores, default_threads)
    except ValueError as e:
        raise UserError(str(e)) from None
    out = Path(args.out).resolve()
    budget_s = args.budget * 60 if args.budget else None
    sw = Sweep(args=args, out=out, root=root, device=device, preset_cfgs=cfgs, points=points, n_train=n_train,
               costs=CostModel(PRIOR_SECONDS.get(args.preset, PRIOR_SECONDS["cpu"])), t0=t0,
               deadline=None if budget_s is None else t0 + budget_s)
    if args.dry_run:
        p, by_id, _ = plan(sw)
        print(f"{len(points)} points over {len(names)} model(s); budget "
              f"{'none' if budget_s is None else f'{args.budget:g} min'}; plan (estimated seconds):")
        for tid in (p.run if p else []):
            print(f"  run   {by_id[tid].cost_s:8.0f}  {tid}")
        for tid in (p.skipped if p else []):
            print(f"  skip  {by_id[tid].cost_s:8.0f}  {tid}: {p.reasons[tid]}")
        print(f"estimated total {p.cost_s if p else 0:.0f} s")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    print(f"tradeoff: {len(points)} points over {', '.join(names)} ({args.preset} preset, {device}); data {root}; "
          f"out {out}", flush=True)
    try:
        skipped = run_sweep(sw, progress=not args.no_progress)
    except KeyboardInterrupt:
        _write_outputs(sw, [], final=True)
        print(f"interrupted: what finished is in {out / 'tradeoff.json'}; run the same command to continue")
        return 130
    result = _write_outputs(sw, skipped, final=True)
    per_model = {n: sum(p["model"] == n for p in result["points"]) for n in names}
    print(f"tradeoff done in {(time.perf_counter() - t0) / 60:.1f} min: points per model "
          + ", ".join(f"{k} {v}" for k, v in per_model.items())
          + (f"; {len(skipped)} task(s) skipped" if skipped else "") + (f"; {len(sw.failed)} failed" if sw.failed else ""))
    print(f"wrote {out / 'tradeoff.json'}, {out / 'tradeoff.md'}" + (", tradeoff.png" if result["points"] else "")
          + (", learning_curve.png" if result["curves"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
