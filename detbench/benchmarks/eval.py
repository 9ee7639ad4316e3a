"""The evaluator benchmark (tools/bench_eval.py): wall time of detbench.eval.evaluate, by stage, on a
synthetic test set of the paper's size (vehicles on lanes, jittered detections and false positives), and
with a scene bootstrap its time and the size of the report.json it writes."""
from __future__ import annotations

import os
import platform
import statistics
import time

import numba
import numpy as np

from detbench.data.frame import LANE_OPPOSITE
from detbench.eval import EvalFrame, evaluate
from detbench.utils.atomic import to_json

__all__ = ["eval_bench_markdown", "run_eval_bench", "synthetic_frames"]

FRAMES_PER_SCENE = 10  # a simulated test scene: 200 frames at 2 Hz, every 20th kept (configs: data.frame_stride)


def synthetic_frames(num_frames: int, gt_per_frame: float, preds_per_frame: int, seed: int):
    """List of EvalFrame: vehicles on lanes, predictions = jittered vehicles + false positives.

    Units: metres and radians. Vehicles: lanes -2..2 of the ego carriageway (3.5 m wide) and
    the opposite carriageway (lane 99), x in [-10, 170] m; 10 % trucks (10 x 2.5 x 3.5 m),
    the rest cars (about 4.6 x 1.9 x 1.6 m). Frames come in scenes of FRAMES_PER_SCENE (the scene
    bootstrap's clusters).
    """
    rng = np.random.default_rng(seed)
    frames = []
    for f in range(num_frames):
        n = int(rng.poisson(gt_per_frame))
        lane_slot = rng.integers(-2, 5, n)  # 3 and 4: opposite carriageway
        y = np.where(lane_slot <= 2, lane_slot * 3.5, -(lane_slot + 1) * 3.5) + rng.normal(0, 0.3, n)
        lane = np.where(lane_slot <= 2, lane_slot, LANE_OPPOSITE).astype(np.int64)
        x = rng.uniform(-10, 170, n)
        truck = rng.random(n) < 0.1
        dims = np.where(truck[:, None], [10.0, 2.5, 3.5], [4.6, 1.9, 1.6]) * rng.uniform(0.9, 1.1, (n, 3))
        heading = np.where(lane == LANE_OPPOSITE, np.pi - 1e-3, 0.0) + rng.normal(0, 0.02, n)
        heading = (heading + np.pi) % (2 * np.pi) - np.pi
        gt = np.column_stack([x, y, dims[:, 2] / 2, dims, heading])
        p_det = np.clip(0.95 - 0.003 * np.abs(x), 0.3, 0.95)
        points = np.where(rng.random(n) < p_det, rng.integers(1, 400, n), 0)

        preds, scores = [], []
        for i in np.flatnonzero(points > 0):
            if rng.random() < 0.85:
                copies = 2 if rng.random() < 0.1 else 1
                for _ in range(copies):
                    b = gt[i].copy()
                    b[:2] += rng.normal(0, 0.15, 2)
                    b[3:6] *= rng.normal(1, 0.03, 3)
                    b[6] += rng.normal(0, 0.03)
                    b[2] = b[5] / 2
                    preds.append(b)
                    scores.append(rng.uniform(0.3, 1.0))
        while len(preds) < preds_per_frame:
            d = np.array([4.6, 1.9, 1.6]) * rng.uniform(0.9, 1.1, 3)
            preds.append(np.array([rng.uniform(-10, 170), rng.uniform(-20, 20), d[2] / 2, *d,
                                   rng.uniform(-np.pi, np.pi)]))
            scores.append(rng.uniform(0.0, 0.5))
        frames.append(EvalFrame(gt, points, lane, np.array(preds[:preds_per_frame]).reshape(-1, 7),
                                np.array(scores[:preds_per_frame]), frame_id=f"{f:06d}",
                                scene_id=f"{f // FRAMES_PER_SCENE:04d}"))
    return frames


def _bootstrap_bench(frames: list, replicates: int, repeats: int) -> dict:
    """Seconds of `evaluate(frames, bootstrap=replicates)` (median of `repeats`) and the size of its report.json
    (indented, as tools/eval.py writes it), with and without the AP ranking."""
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        report = evaluate(frames, bootstrap=replicates)
        runs.append(time.perf_counter() - t)
    unc = report["uncertainty"]
    bare = {**report, "uncertainty": {k: v for k, v in unc.items() if k != "ap_ranking"}}
    return {"bootstrap_replicates": replicates, "bootstrap_scenes": unc["num_clusters"],
            "bootstrap_seconds_median": statistics.median(runs),
            "ranked_detections": len(unc["ap_ranking"]["scene"].split()),
            "report_json_bytes": len(to_json(report).encode()),
            "report_json_bytes_without_ap_ranking": len(to_json(bare).encode())}


def run_eval_bench(num_frames: int, gt_per_frame: float, preds_per_frame: int, *, repeats: int = 5,
                   threads: int = 2, seed: int = 0, extras: bool = False, bootstrap: int = 0) -> dict:
    """Time `evaluate` on `synthetic_frames(...)`: the results dict of bench_eval.json (seconds; median of
    `repeats` runs after one warm-up call). `threads` is recorded; the caller sets numba's thread count.
    `bootstrap` > 0 also times `evaluate(..., bootstrap=bootstrap)` and measures its report.json."""
    t0 = time.perf_counter()
    frames = synthetic_frames(num_frames, gt_per_frame, preds_per_frame, seed)
    gen_s = time.perf_counter() - t0
    n_gt = sum(len(f.gt_boxes) for f in frames)
    n_pred = sum(len(f.pred_boxes) for f in frames)

    def timed(with_extras: bool):
        t = time.perf_counter()
        evaluate(frames, extras=with_extras)  # warm-up: numba compilation / cache load
        warm = time.perf_counter() - t
        runs, stages = [], []
        for _ in range(repeats):
            st: dict = {}
            t = time.perf_counter()
            report = evaluate(frames, extras=with_extras, timings=st)
            runs.append(time.perf_counter() - t)
            stages.append(st)
        stage_median = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
        return warm, runs, stage_median, report

    warm, runs, stage_median, report = timed(False)
    result = {
        "what": "wall seconds of detbench.eval.evaluate(frames) (3D IoU 0.7, score 0.1, 9 range/level pairs), "
                "median over repeats after one warm-up call",
        "frames": num_frames,
        "gt_boxes": n_gt,
        "predictions": n_pred,
        "gt_per_frame": n_gt / num_frames,
        "predictions_per_frame": n_pred / num_frames,
        "threads": threads,
        "repeats": repeats,
        "seed": seed,
        "seconds_median": statistics.median(runs),
        "seconds_runs": runs,
        "seconds_warmup_call": warm,
        "seconds_by_stage_median": stage_median,
        "seconds_generate_load": gen_s,
        "large_all": report["results"]["large"]["all"],
        "python": platform.python_version(),
        "numba": numba.__version__,
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
    }
    if extras:
        warm_x, runs_x, stage_x, _ = timed(True)
        result["extras_seconds_median"] = statistics.median(runs_x)
        result["extras_seconds_by_stage_median"] = stage_x
    if bootstrap:
        result.update(_bootstrap_bench(frames, bootstrap, repeats))
    return result


def eval_bench_markdown(r: dict) -> str:
    """bench_eval.md: the stages and the total as a table."""
    md = [
        "# Evaluator benchmark",
        "",
        f"`detbench.eval.evaluate` on a synthetic load: {r['frames']} frames, {r['gt_per_frame']:.1f} "
        f"ground-truth vehicles and {r['predictions_per_frame']:.1f} predictions per frame, 3D IoU 0.7, "
        f"score >= 0.1, 9 range/level pairs; {r['threads']} numba threads; median of {r['repeats']} runs "
        f"after a warm-up call (numba compilation excluded). Times in seconds (wall clock).",
        "",
        "| Stage | Seconds |",
        "|---|---:|",
        *[f"| {k} | {v:.3f} |" for k, v in r['seconds_by_stage_median'].items()],
        f"| **total** | **{r['seconds_median']:.3f}** |",
    ]
    if "extras_seconds_median" in r:
        md.append(f"| total with extras (BEV 0.7, 3D 0.5, BEV 0.5) | {r['extras_seconds_median']:.3f} |")
    if "bootstrap_seconds_median" in r:
        md += [f"| total with a scene bootstrap ({r['bootstrap_replicates']} replicates, {r['bootstrap_scenes']} "
               f"scenes) | {r['bootstrap_seconds_median']:.3f} |", "",
               f"report.json with the bootstrap: {r['report_json_bytes'] / 1024:.0f} KiB, of which the AP ranking "
               f"of {r['ranked_detections']} detections "
               f"{(r['report_json_bytes'] - r['report_json_bytes_without_ap_ranking']) / 1024:.0f} KiB."]
    md += ["", f"Machine: {r['machine']}, {r['cpu_count']} CPUs visible, Python {r['python']}, "
               f"numba {r['numba']}."]
    return "\n".join(md) + "\n"
