"""The point-operations benchmark (tools/bench_points.py): farthest point sampling, and PointRCNN's
set abstraction (FPS, ball query, grouping), feature propagation and RoI point pooling on scans of
a 1.8 m LiDAR, and the proposal NMS of the two-stage detectors' training budget (9000 boxes to 512, the numba
kernel against the torch path, the GPU's, in one run); milliseconds per call on the whole batch (median and best
after one warm-up)."""
from __future__ import annotations

import os
import platform
from dataclasses import dataclass

import numba
import numpy as np
import torch

from detbench.ops import (ball_query, farthest_point_sample, group_neighbours, nms_bev, roi_point_pool,
                          three_nn_interpolate)
from detbench.ops.backend import forced_backend
from detbench.utils.bench import timed

__all__ = ["FPS_TARGET_MS", "PointsBenchSettings", "car_rois", "crowded_proposals", "points_bench_markdown",
           "run_points_bench", "sample_scan"]

# PointRCNN (OpenPCDet pointrcnn.yaml, PointNet2MSG backbone)
SA_NPOINTS = [4096, 1024, 256, 64]
SA_RADII = [[0.1, 0.5], [0.5, 1.0], [1.0, 2.0], [2.0, 4.0]]
SA_NSAMPLE = [[16, 32], [16, 32], [16, 32], [16, 32]]
FPS_TARGET_MS = 200.0  # the target for 16384 -> 4096 points per frame on 2 CPU cores (a PointRCNN frame's first level)

@dataclass
class PointsBenchSettings:
    """What the benchmark measures (the options of tools/bench_points.py)."""

    points: int = 16384  # points per scan (PointRCNN's input)
    samples: int = 4096  # FPS samples per scan
    channels: int = 128  # feature channels C for propagation and pooling
    rois: int = 100  # RoIs per scan for RoI pooling
    nms_boxes: int = 9000  # proposals entering NMS (the two-stage detectors' training budget; 0: no NMS rows)
    nms_keep: int = 512  # proposals NMS keeps
    nms_threshold: float = 0.8  # BEV IoU
    seed: int = 0  # sampling of the scans, RoIs and features
    repeats: int = 5  # timed runs per case after one warm-up
    threads: int = 2  # numba and torch CPU threads (set by the caller; recorded in the results)
    skip_torch: bool = False  # leave out the torch-path rows


def sample_scan(scan: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points of the scan in scan order (with repeats only when the scan has fewer points)."""
    idx = rng.choice(len(scan), n, replace=len(scan) < n)
    return scan[np.sort(idx)]


def car_rois(rng: np.random.Generator, n: int) -> np.ndarray:
    """n car-sized boxes (x, y, z, dx, dy, dz, heading) on the lanes ahead, metres and radians."""
    return np.c_[rng.uniform(5.0, 80.0, n), rng.choice([-7.0, -3.5, 0.0, 3.5, 7.0], n) + rng.normal(0, 0.3, n),
                 np.full(n, 0.8), rng.uniform(4.0, 5.0, n), rng.uniform(1.7, 2.0, n), rng.uniform(1.4, 1.8, n),
                 rng.normal(0.0, 0.1, n)].astype(np.float32)


def crowded_proposals(rng: np.random.Generator, n: int, vehicles: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A trained first stage's proposals: n boxes (float32) crowded round `vehicles` car_rois, and random scores."""
    cars = car_rois(rng, vehicles).astype(np.float64)
    boxes = cars[rng.integers(0, vehicles, n)] + rng.normal(0, 1, (n, 7)) * [0.5, 0.3, 0.1, 0.2, 0.1, 0.1, 0.1]
    return boxes.astype(np.float32), rng.uniform(0, 1, n).astype(np.float32)


def _nms_cases(add, results: dict, s: PointsBenchSettings, device: torch.device, sync) -> None:
    """NMS of s.nms_boxes proposals to s.nms_keep: the numba kernel, then the torch path; their ratio."""
    boxes, scores = (torch.from_numpy(a) for a in crowded_proposals(np.random.default_rng(s.seed), s.nms_boxes))
    name = f"nms_bev {s.nms_boxes} -> {s.nms_keep} proposals, IoU {s.nms_threshold:g}"
    want = nms_bev(boxes, scores, s.nms_threshold, s.nms_keep)
    numba_row = add(f"{name} (numba, CPU)", timed(lambda: nms_bev(boxes, scores, s.nms_threshold, s.nms_keep),
                                                  s.repeats, lambda: None))
    if s.skip_torch:
        return
    with forced_backend("torch"):
        bd, sd = boxes.to(device), scores.to(device)
        same = bool(torch.equal(nms_bev(bd, sd, s.nms_threshold, s.nms_keep).cpu(), want))
        row = add(f"{name} (torch path, {device})", timed(lambda: nms_bev(bd, sd, s.nms_threshold, s.nms_keep),
                                                           s.repeats, sync), equal_to_numba=same)
    results["nms_torch_over_numba"] = round(row["ms"] / max(numba_row["ms"], 1e-9), 3)


def run_points_bench(scans: list[np.ndarray], source: str, s: PointsBenchSettings,
                     device: torch.device) -> dict:
    """Every case on `scans` (one batch): the results dict of bench_points.json; one line per case printed."""
    frames = len(scans)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    rng = np.random.default_rng(s.seed)
    pts = np.concatenate([sample_scan(scan, s.points, rng) for scan in scans])
    counts = [s.points] * frames
    xyz = torch.from_numpy(np.ascontiguousarray(pts[:, :3]))
    load_before = os.getloadavg()
    results: dict = {
        "source": source, "frames": frames, "points_per_frame": s.points, "samples": s.samples,
        "channels": s.channels, "rois_per_frame": s.rois, "threads": s.threads,
        "numba_threads": numba.get_num_threads(), "device": str(device), "torch": torch.__version__,
        "numba": numba.__version__, "cpu": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "repeats": s.repeats,
        "units": "milliseconds per call on the whole batch (median and best)",
        "load_average_1_5_15min_before": [round(v, 2) for v in load_before], "cases": [],
    }

    def add(name, timing, **extra):
        row = {"case": name, "ms": round(timing["ms"], 3), "ms_best": round(timing["ms_best"], 3), **extra}
        results["cases"].append(row)
        print(f"{name:62s} {timing['ms']:9.2f} ms (best {timing['ms_best']:.2f})", flush=True)
        return row

    # Farthest point sampling: the figure with a target.
    def fps():
        return farthest_point_sample(xyz, s.samples, counts)

    row = add(f"farthest_point_sample {s.points} -> {s.samples} (numba, CPU)", timed(fps, s.repeats, lambda: None))
    results["fps_ms"] = row["ms"]
    results["fps_ms_per_frame"] = round(row["ms"] / frames, 3)
    results["fps_target_ms_per_frame"] = FPS_TARGET_MS
    if not s.skip_torch:
        xd = xyz.to(device)
        same = bool(torch.equal(farthest_point_sample(xd, s.samples, counts, backend="torch").cpu(), fps()))
        add(f"farthest_point_sample {s.points} -> {s.samples} (torch path, {device})",
            timed(lambda: farthest_point_sample(xd, s.samples, counts, backend="torch"), s.repeats, sync),
            equal_to_numba=same)

    # PointRCNN set abstraction: FPS + ball query + grouping per level.
    level_xyz, level_counts = [xyz], [counts]
    cur, cur_counts = xyz, counts
    for level, (npoint, radii, nsamples) in enumerate(zip(SA_NPOINTS, SA_RADII, SA_NSAMPLE)):
        npoint = s.samples if level == 0 else npoint
        idx = farthest_point_sample(cur, npoint, cur_counts)
        centres = cur[idx]
        add(f"  SA level: FPS {cur_counts[0]} -> {npoint}",
            timed(lambda cur=cur, npoint=npoint, cur_counts=cur_counts: farthest_point_sample(cur, npoint, cur_counts),
                  s.repeats, lambda: None))
        for r, ns in zip(radii, nsamples):
            cc = [npoint] * frames

            def step(r=r, ns=ns, cc=cc, cur=cur, centres=centres, cur_counts=cur_counts):
                bq = ball_query(cur, centres, r, ns, cur_counts, cc)
                return group_neighbours(cur, centres, bq.index), bq

            _, bq = step()
            add(f"  SA level: ball query r={r} m, {ns} samples + grouping ({npoint} centres)",
                timed(step, s.repeats, lambda: None), empty_balls=int(bq.empty.sum()),
                mean_points=round(float(bq.count.float().mean()), 2))
        cur, cur_counts = centres, [npoint] * frames
        level_xyz.append(cur)
        level_counts.append(cur_counts)

    # Feature propagation back up the levels.
    for lvl in range(len(level_xyz) - 1, 0, -1):
        src, tgt = level_xyz[lvl], level_xyz[lvl - 1]
        feats = torch.randn(src.shape[0], s.channels)
        add(f"  FP level: three_nn_interpolate {level_counts[lvl][0]} -> {level_counts[lvl - 1][0]}, C={s.channels}",
            timed(lambda tgt=tgt, src=src, feats=feats, lvl=lvl:
                  three_nn_interpolate(tgt, src, feats, level_counts[lvl - 1], level_counts[lvl]),
                  s.repeats, lambda: None))

    # RoI point pooling.
    if s.rois:
        rois = torch.from_numpy(np.concatenate([car_rois(rng, s.rois) for _ in range(frames)]))
        feats = torch.randn(xyz.shape[0], s.channels)

        def pool():
            return roi_point_pool(xyz, rois, 512, 1.0, feats, counts, [s.rois] * frames)

        out = pool()
        add(f"roi_point_pool {s.rois} RoIs x 512 points, C={s.channels} (numba, CPU)",
            timed(pool, s.repeats, lambda: None), empty_rois=int(out.empty.sum()),
            mean_points_inside=round(float(out.count.float().mean()), 1))

    if s.nms_boxes:
        _nms_cases(add, results, s, device, sync)
    results["load_average_1_5_15min_after"] = [round(v, 2) for v in os.getloadavg()]
    return results


def points_bench_markdown(r: dict) -> str:
    """Human-readable report of the results dict."""
    lines = [
        "# Point operations benchmark (tools/bench_points.py)", "",
        f"- scans: {r['source']}",
        f"- batch: {r['frames']} scan(s) x {r['points_per_frame']} points; FPS samples {r['samples']}; "
        f"C = {r['channels']}; RoIs per scan {r['rois_per_frame']}",
        f"- numba threads {r['numba_threads']}, torch threads {r['threads']}, device {r['device']}, "
        f"torch {r['torch']}, "
        f"numba {r['numba']}, {r['cpus']} CPUs, OMP_WAIT_POLICY {r.get('omp_wait_policy')}",
        f"- times in milliseconds per call on the whole batch: median and best of {r['repeats']} runs after a warm-up",
        f"- load average (1 min) before / after: {r['load_average_1_5_15min_before'][0]} / "
        f"{r['load_average_1_5_15min_after'][0]} (a shared machine slows every row)",
        f"- **FPS {r['points_per_frame']} -> {r['samples']}: {r['fps_ms_per_frame']:.1f} ms per frame** "
        f"(target < {r['fps_target_ms_per_frame']:.0f} ms)",
    ]
    if "nms_torch_over_numba" in r:
        lines.append(f"- NMS, torch path / numba kernel (medians of one run): {r['nms_torch_over_numba']:.2f}")
    lines += ["", "| case | median ms | best ms | details |", "|---|---:|---:|---|"]
    for row in r["cases"]:
        details = ", ".join(f"{k}={v}" for k, v in row.items() if k not in ("case", "ms", "ms_best"))
        lines.append(f"| {row['case'].strip()} | {row['ms']:.2f} | {row['ms_best']:.2f} | {details} |")
    return "\n".join(lines) + "\n"

