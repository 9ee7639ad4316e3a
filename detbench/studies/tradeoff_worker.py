"""The trade sweep's measuring worker: one point's latency, memory and accuracy, in its own process.

Each measurement runs as `python -m detbench.studies.tradeoff_worker SPEC_JSON` (started by
detbench.studies.tradeoff_sweep), so its peak memory and thread count are its own. A point
spec names the checkpoint, what changes at inference (precision, threads, a point budget,
model keys), the dataset, height, timed frames and warm-up, and the JSON file to write; a
curve spec names a training run whose checkpoints are evaluated one file each.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
from detbench.data.regions import RANGE_NAMES
from detbench.studies.registry import ModelRegistry, import_registry
from detbench.studies.tradeoff_points import set_dotted
from detbench.utils.cli import UserError, run_main
from detbench.utils.atomic import atomic_write_json


class SubsampledFrames:
    """The frames of a dataset with each one's points prepared as the model's input (cropped to its range,
    without the road when `road.drop`) and then cut to `budget` points by "random" (seeded per frame) or
    "fps" (farthest point sampling); `seconds` sums the time spent subsampling."""

    def __init__(self, frames, point_cloud_range, method: str, budget: int, road=None):
        self.frames, self.pcr, self.method, self.budget = frames, point_cloud_range, method, int(budget)
        self.road = road
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
        cropped = frame_sample(frame, self.pcr, self.road).points
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


def load_for_inference(registry: ModelRegistry, ckpt_path: str, device, model_overrides: dict):
    """(model in eval mode, checkpoint dict, model config): the checkpoint's model, its stored config in
    today's keys, rebuilt with `model_overrides` (dotted keys under `model:` that change inference only, e.g.
    the test proposals)."""
    from detbench.train.checkpoint import load_checkpoint, load_model_weights

    ck = load_checkpoint(ckpt_path)
    cfg = registry.upgrade_stored_model_config(ck["model_name"], ck["config"]["model"])
    for key, value in (model_overrides or {}).items():
        set_dotted(cfg, key, value)
    model = registry.build_model(ck["model_name"], cfg)
    load_model_weights(model, ck, ckpt_path)
    return model.to(device).eval(), ck, cfg


def evaluate_checkpoint(model, cfg_model: dict, ck: dict, test, device, precision, subsample, eval_frames: int):
    """{range: {ap_r40, recall, lidar_detected}} of all vehicles on the test split (or `eval_frames`
    evenly spaced frames of it), predicted under `precision` and `subsample`."""
    import numpy as np

    from detbench.data.road import RoadConfig
    from detbench.eval.evaluate import EvalConfig, evaluate_predictions
    from detbench.train.inference import predict_frames

    frames = test
    if eval_frames and eval_frames < len(test):
        frames = [test[int(i)] for i in np.linspace(0, len(test) - 1, eval_frames).astype(int)]
    ecfg = EvalConfig.from_dict(ck["config"].get("eval"))
    road = RoadConfig.of_run_config(ck["config"])
    source = SubsampledFrames(frames, cfg_model["point_cloud_range"], *subsample, road=road) if subsample else frames
    with _autocast(device, precision):
        preds = predict_frames(model, source, cfg_model["point_cloud_range"], device=device, batch_size=4,
                               progress=False, road=None if subsample else road)  # subsampled: prepared already
    rep = evaluate_predictions(frames, preds, iou_threshold=ecfg.iou_threshold,
                               score_threshold=ecfg.score_threshold, extras=False, progress=False)
    return {r: {k: rep["results"][r]["all"][k] for k in ("ap_r40", "recall", "lidar_detected")}
            for r in RANGE_NAMES}, len(frames)


def measure_point(registry: ModelRegistry, spec: dict) -> dict:
    """Latency (split by stage), peak memory, parameters and accuracy of one point."""
    import io

    import numpy as np
    import torch

    from detbench import runtime
    from detbench.data import Height3Dataset
    from detbench.data.batch import Sample, collate
    from detbench.data.road import RoadConfig
    from detbench.train.inference import frame_sample
    from detbench.utils.bench import StageTimer, median_p90, peak_rss_mib, reset_peak_rss, rss_mib

    infer = spec["infer"]
    if infer.get("threads"):
        runtime.set_threads(int(infer["threads"]))
    device = torch.device(spec["device"])
    peak_reset = reset_peak_rss()  # the peak below then covers the model, frames and timed passes only
    rss0 = rss_mib() or peak_rss_mib()
    model, ck, cfg_model = load_for_inference(registry, spec["ckpt"], device, infer.get("model"))
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    test = Height3Dataset(spec["data"], spec["height"], "test")
    if len(test) == 0:
        raise UserError(f"{spec['data']}: the test split at {spec['height']:g} m has no frames")
    pcr = cfg_model["point_cloud_range"]
    road = RoadConfig.of_run_config(ck["config"])
    sub = SubsampledFrames(test, pcr, *infer["subsample"], road=road) if infer.get("subsample") else None
    timer = StageTimer(model, model.STAGES, device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rows, npts = [], []
    n = spec["warmup"] + spec["frames"]
    with torch.no_grad(), _autocast(device, infer.get("precision")):
        for i in range(n):
            frame = test[i % len(test)]
            points = frame_sample(frame, pcr, road).points  # crop and road removal are input preparation, not timed
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
              "threads": torch.get_num_threads(), "point_cloud_range": pcr, "road_dropped": road.drop}
    if device.type == "cuda":
        result["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated(device) / 2 ** 20, 1)
    try:
        result["accuracy"], result["frames_evaluated"] = evaluate_checkpoint(
            model, cfg_model, ck, test, device, infer.get("precision"), infer.get("subsample"), spec["eval_frames"])
    except FloatingPointError as e:  # e.g. a precision whose outputs overflow: reported, not fatal
        result["accuracy"], result["error"] = None, str(e)
    result["runtime"] = runtime.describe()
    return result


def curve_worker(registry: ModelRegistry, spec: dict) -> None:
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
        model, ck, cfg_model = load_for_inference(registry, str(path), device, {})
        acc, n = evaluate_checkpoint(model, cfg_model, ck, test, device, None, None, spec["eval_frames"])
        atomic_write_json(target, {"checkpoint": path.name, "global_step": int(ck["state"]["global_step"]),
                                   "epoch": int(ck["state"]["epoch"]), "accuracy": acc, "frames_evaluated": n})


def run_spec(spec: dict) -> None:
    """One worker task: "mode" "point" measures a point into spec["out"] (its "key" stored as "spec",
    which tells a rerun whether the result still applies); "curve" evaluates a run's checkpoints.
    spec["registry"] names the detector registry's module."""
    registry = import_registry(spec["registry"])
    if spec["mode"] == "curve":
        curve_worker(registry, spec)
        return
    result = measure_point(registry, spec)
    atomic_write_json(spec["out"], {"spec": spec["key"], **result})


def main(argv: list[str] | None = None) -> int:
    """`python -m detbench.studies.tradeoff_worker SPEC_JSON`: run one task of the trade sweep."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        raise UserError("usage: python -m detbench.studies.tradeoff_worker SPEC_JSON (started by tools/tradeoff.py)")
    run_spec(json.loads(args[0]))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
