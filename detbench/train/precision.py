"""Inference at reduced precision against float32 on the same checkpoint.

`compare_precision(model, frames, point_cloud_range)` runs a detector over frames once in
float32 and once per reduced precision (bfloat16 autocast on the CPU; float16 and bfloat16
autocast on CUDA), and reports for each precision:

- AP@R40 and recall per range (level All, 3D IoU `iou_threshold`, the paper's evaluator) and
  their difference to float32 (positive: the reduced precision scores higher);
- the largest box difference between the two runs' detections of the same vehicle: the
  detections (score >= `score_threshold`) of each frame are matched one to one, highest
  float32 score first, to the reduced-precision detection with the highest BEV IoU >=
  `match_iou`; for matched pairs the largest corner displacement (m; the 8 corners, so centre,
  size and heading in one figure), centre distance (m), size difference (m), heading
  difference (rad) and score difference, comparing the boxes as solids (a heading turned
  round by pi is counted as a direction flip, not as a 5 m corner difference); detections left
  without a partner are counted (flips across the score threshold, or NMS keeping another box);
- NaN / inf counts: values in the raw model outputs (every floating tensor of the output
  structure), frames whose outputs hold any, and detections dropped for a non-finite box or score;
- wall time per frame (seconds; the first batch of each run included, so compilation and
  warm-up show).

The model runs with `torch.autocast(device, dtype)` around its forward pass and its
post-processing; parameters stay float32. The whole comparison runs with TensorFloat-32 off for
matrix products and cuDNN convolutions (`strict_float32`): cuDNN's default on Ampere and later GPUs
computes float32 convolutions in TF32 (10-bit mantissa), which would make the float32 reference row
partly reduced precision itself. The report records both settings (`float32_settings`).
(It lives in detbench.train beside `predict_frames`, whose frame preparation and NaN count it
shares: detbench.eval sits below the training layer.)
Results are plain dicts (JSON-ready), one schema for the tool (tools/precision.py), the tests
and the trade study. `precision_markdown(report)` renders one.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from tqdm import tqdm

from detbench.config import shipped_default
from detbench.data import Height3Dataset
from detbench.data.frame import key_label
from detbench.data.batch import collate
from detbench.data.detections import Detections
from detbench.data.errors import DatasetError
from detbench.data.regions import RANGE_NAMES, detected_point_counts
from detbench.data.road import RoadConfig
from detbench.eval import EvalFrame, evaluate
from detbench.ops import boxes_iou_bev, boxes_to_corners_3d, normalize_heading
from detbench.train.inference import count_nonfinite, frame_sample

__all__ = ["PRECISIONS", "PrecisionRun", "available_precisions", "autocast_for", "box_differences",
           "checkpoint_precision_markdown", "checkpoint_precision_report", "compare_precision", "float32_settings",
           "precision_frames", "precision_markdown", "precision_summary_lines", "run_at_precision", "strict_float32"]

PRECISIONS: dict[str, torch.dtype | None] = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}
REFERENCE = "float32"


def available_precisions(device: torch.device | str) -> list[str]:
    """The precisions compared by default on `device`: float32 and bfloat16 on the CPU; float32, float16 and
    bfloat16 (when the GPU supports it) on CUDA."""
    device = torch.device(device)
    if device.type == "cuda":
        out = ["float32", "float16"]
        if torch.cuda.is_bf16_supported():
            out.append("bfloat16")
        return out
    return ["float32", "bfloat16"]


def autocast_for(precision: str, device: torch.device | str):
    """The context that runs a forward pass at `precision` ("float32": none)."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; use one of {', '.join(PRECISIONS)}")
    dtype = PRECISIONS[precision]
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=torch.device(device).type, dtype=dtype)


def _tf32_switches() -> list[tuple[object, str, object]]:
    """(object, attribute, its IEEE float32 value) of the matmul and cuDNN precision switches this torch has:
    the `fp32_precision` strings of torch >= 2.9 (the legacy `allow_tf32` flags must not be mixed with them),
    else the legacy flags."""
    matmul, cudnn = torch.backends.cuda.matmul, torch.backends.cudnn
    if hasattr(matmul, "fp32_precision") and hasattr(getattr(cudnn, "conv", None), "fp32_precision"):
        return [(matmul, "fp32_precision", "ieee"), (cudnn.conv, "fp32_precision", "ieee"),
                (cudnn.rnn, "fp32_precision", "ieee")]
    return [(matmul, "allow_tf32", False), (cudnn, "allow_tf32", False)]


def float32_settings() -> dict[str, str]:
    """How float32 matrix products and cuDNN convolutions compute now: "ieee" (full float32) or "tf32"
    (TensorFloat-32 on GPUs that have it; "none": torch's default for this torch version)."""
    def name(value) -> str:
        return value if isinstance(value, str) else ("tf32" if value else "ieee")

    switches = _tf32_switches()
    return {"cuda_matmul": name(getattr(switches[0][0], switches[0][1])),
            "cudnn_conv": name(getattr(switches[1][0], switches[1][1])),
            "float32_matmul_precision": torch.get_float32_matmul_precision()}


@contextlib.contextmanager
def strict_float32():
    """Run the block with float32 matrix products and cuDNN convolutions in full float32 (TF32 off), then put
    the settings back as they were."""
    switches = _tf32_switches()
    before = [getattr(obj, attr) for obj, attr, _ in switches]
    precision = torch.get_float32_matmul_precision()
    try:
        for obj, attr, value in switches:
            setattr(obj, attr, value)
        torch.set_float32_matmul_precision("highest")
        yield
    finally:
        for (obj, attr, _), value in zip(switches, before):
            setattr(obj, attr, value)
        torch.set_float32_matmul_precision(precision)


@dataclass
class PrecisionRun:
    """One pass of a model over the frames at one precision."""

    precision: str
    predictions: dict[str, Detections]  # frame_id -> numpy: boxes (K, 7) float64, scores (K,), labels (K,)
    nonfinite_values: int = 0  # NaN / inf values in the raw outputs
    nonfinite_frames: list[str] = field(default_factory=list)  # frames of batches whose outputs held any
    nonfinite_detections: int = 0  # detections dropped for a non-finite box or score
    seconds: float = 0.0  # wall time of the whole pass


@torch.no_grad()
def run_at_precision(model: nn.Module, frames: Sequence, point_cloud_range: Sequence[float], precision: str,
                     device: torch.device | str = "cpu", batch_size: int = 4, progress: bool = False,
                     road: RoadConfig | None = None) -> PrecisionRun:
    """Run `model` (the detector contract: forward, predict) over `frames` in eval mode under `precision`'s
    autocast, on the input `frame_sample` prepares (`road`: the model's road setting). Never raises for
    NaN / inf outputs: they are counted (see the module doc)."""
    device = torch.device(device)
    was_training = model.training
    model.eval()
    run = PrecisionRun(precision, {})
    n = len(frames)
    bar = tqdm(total=n, desc=f"predict {precision}", unit="frame", disable=not progress, leave=False,
               dynamic_ncols=True)
    t0 = time.perf_counter()
    try:
        for start in range(0, n, batch_size):
            samples = [frame_sample(frames[i], point_cloud_range, road)
                       for i in range(start, min(n, start + batch_size))]
            batch = collate(samples).to(device)
            with autocast_for(precision, device):
                outputs = model(batch)
                dets = model.predict(outputs, batch)
            bad = count_nonfinite(outputs)
            if bad:
                run.nonfinite_values += bad
                run.nonfinite_frames.extend(s.frame_id for s in samples)
            for s, d in zip(samples, dets):
                host = d.numpy()
                boxes = host.boxes.astype(np.float64).reshape(-1, 7)
                scores = host.scores.astype(np.float64).reshape(-1)
                ok = np.isfinite(boxes).all(axis=1) & np.isfinite(scores)
                run.nonfinite_detections += int((~ok).sum())
                run.predictions[s.frame_id] = Detections(boxes[ok], scores[ok], host.labels.reshape(-1)[ok])
            bar.update(len(samples))
    finally:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        run.seconds = time.perf_counter() - t0
        bar.close()
        model.train(was_training)
    return run


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.asarray(normalize_heading(np.asarray(a, dtype=np.float64)), dtype=np.float64)


_NONE = (np.zeros((0, 7)), np.zeros(0))  # the detections of a frame without any


def box_differences(reference: dict[str, Detections | tuple[np.ndarray, np.ndarray]],
                    other: dict[str, Detections | tuple[np.ndarray, np.ndarray]],
                    score_threshold: float | None = None, match_iou: float = 0.5) -> dict:
    """How far `other`'s detections lie from `reference`'s, frame by frame (see the module doc for the matching).

    A matched pair whose headings differ by more than pi/2 is counted in "heading_flips" (the direction
    classifier turned round: the same solid with its front at the back) and compared as solids, i.e. with one
    heading turned by pi, so the corner, centre, size and heading figures measure where the box lies.

    Returns {"matched", "unmatched_reference", "unmatched_other", "heading_flips", "max_corner_diff_m",
    "mean_corner_diff_m", "p99_corner_diff_m", "max_centre_diff_m", "max_size_diff_m", "max_heading_diff_rad"
    (after the flip, so <= pi/2), "max_score_diff", "worst_frame" (of the largest corner difference)}; the
    figures are 0.0 when nothing matched. Detections below `score_threshold` (None: the evaluator's,
    configs/default.yaml) are not compared.
    """
    score_threshold = shipped_default("eval.score_threshold", score_threshold)
    corner, centre, size, heading, score = [], [], [], [], []
    unmatched_ref = unmatched_other = flips = 0
    worst, worst_frame = -1.0, None
    for fid in sorted(set(reference) | set(other)):
        rb, rs = reference.get(fid, _NONE)[:2]
        ob, os_ = other.get(fid, _NONE)[:2]
        rk, ok = rs >= score_threshold, os_ >= score_threshold
        rb, rs, ob, os_ = rb[rk], rs[rk], ob[ok], os_[ok]
        if len(rb) == 0 or len(ob) == 0:
            unmatched_ref += len(rb)
            unmatched_other += len(ob)
            continue
        iou = boxes_iou_bev(rb, ob)
        taken = np.zeros(len(ob), dtype=bool)
        pairs = []
        for i in np.argsort(-rs, kind="stable"):
            cand = np.where(taken, -1.0, iou[i])
            j = int(np.argmax(cand))
            if cand[j] >= match_iou:
                taken[j] = True
                pairs.append((i, j))
        unmatched_ref += len(rb) - len(pairs)
        unmatched_other += len(ob) - len(pairs)
        if not pairs:
            continue
        ii, jj = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
        a, b = rb[ii], ob[jj].copy()
        dh = _wrap(b[:, 6] - a[:, 6])
        flip = np.abs(dh) > math.pi / 2  # the direction turned round: the same solid, its front at the back
        flips += int(flip.sum())
        b[flip, 6] = b[flip, 6] - math.pi  # compare the solids: corners in the same order
        c = np.linalg.norm(boxes_to_corners_3d(a) - boxes_to_corners_3d(b), axis=2).max(axis=1)
        corner.append(c)
        centre.append(np.linalg.norm(a[:, :3] - b[:, :3], axis=1))
        size.append(np.abs(a[:, 3:6] - b[:, 3:6]).max(axis=1))
        heading.append(np.abs(_wrap(b[:, 6] - a[:, 6])))
        score.append(np.abs(rs[ii] - os_[jj]))
        if c.max() > worst:
            worst, worst_frame = float(c.max()), fid

    def mx(parts):
        return float(np.concatenate(parts).max()) if parts else 0.0

    matched = int(sum(len(c) for c in corner))
    return {"matched": matched, "unmatched_reference": int(unmatched_ref), "unmatched_other": int(unmatched_other),
            "max_corner_diff_m": mx(corner), "max_centre_diff_m": mx(centre), "max_size_diff_m": mx(size),
            "max_heading_diff_rad": mx(heading), "max_score_diff": mx(score), "heading_flips": flips,
            "mean_corner_diff_m": float(np.concatenate(corner).mean()) if corner else 0.0,
            "p99_corner_diff_m": float(np.percentile(np.concatenate(corner), 99)) if corner else 0.0,
            "worst_frame": worst_frame}


def _accuracy(eval_base: list[tuple], run: PrecisionRun, iou_threshold: float, score_threshold: float) -> dict:
    frames = [EvalFrame(boxes, counts, lanes, *run.predictions.get(fid, _NONE)[:2], frame_id=fid)
              for fid, boxes, counts, lanes in eval_base]
    rep = evaluate(frames, iou_threshold=iou_threshold, score_threshold=score_threshold)
    res = rep["results"]
    return {"ap_r40": {r: res[r]["all"]["ap_r40"] for r in RANGE_NAMES},
            "recall": {r: res[r]["all"]["recall"] for r in RANGE_NAMES},
            "lidar_detected": {r: res[r]["all"]["lidar_detected"] for r in RANGE_NAMES}}


def _diff(a, b):
    return None if a is None or b is None else b - a


def compare_precision(model: nn.Module, frames: Sequence, point_cloud_range: Sequence[float],
                      precisions: Sequence[str] | None = None, device: torch.device | str = "cpu",
                      batch_size: int = 4, score_threshold: float | None = None, iou_threshold: float | None = None,
                      match_iou: float = 0.5, progress: bool = False, road: RoadConfig | None = None) -> dict:
    """Float32 against each reduced precision on the same model and frames (see the module doc).

    Args:
        model: a detector (forward, predict) already on `device`, weights float32.
        frames: a sequence of `detbench.data.Frame` with ground truth (e.g. a Height3Dataset split).
        point_cloud_range: the model's [x_min, y_min, z_min, x_max, y_max, z_max] (metres).
        precisions: names from PRECISIONS; default `available_precisions(device)`. float32 is always run
            first, as the reference.
        score_threshold / iou_threshold: the evaluator's; None: configs/default.yaml `eval:` (the paper's
            0.1 and 3D IoU 0.7); the score threshold also selects the detections compared box by box.
        match_iou: BEV IoU a reduced-precision detection needs with a float32 one to count as the same vehicle.
        road: the model's road setting (`RoadConfig.of_run_config` of its run config).
    Returns:
        {"reference": "float32", "device", "float32" (`float32_settings` during the runs: "ieee" matmul and cuDNN),
         "num_frames", "score_threshold", "iou_threshold", "match_iou", "precisions": {name: {"autocast_dtype",
         "seconds_per_frame", "detections", "nonfinite_values", "nonfinite_frames", "nonfinite_detections",
         "ap_r40": {range}, "recall": {range},
         ["ap_r40_diff": {range}, "recall_diff": {range}, "max_abs_ap_r40_diff", "boxes": box_differences]}}}
    """
    score_threshold = shipped_default("eval.score_threshold", score_threshold)
    iou_threshold = shipped_default("eval.iou_threshold", iou_threshold)
    device = torch.device(device)
    names = list(precisions) if precisions is not None else available_precisions(device)
    for p in names:
        autocast_for(p, device)  # validates the name
    names = [REFERENCE] + [p for p in dict.fromkeys(names) if p != REFERENCE]
    eval_base = []
    for i in range(len(frames)):
        f = frames[i]
        boxes = np.asarray(f.boxes, dtype=np.float64).reshape(-1, 7)
        eval_base.append((f.frame_id, boxes, detected_point_counts(np.asarray(f.points), boxes), np.asarray(f.lanes)))
    out = {"reference": REFERENCE, "device": str(device), "num_frames": len(frames),
           "score_threshold": float(score_threshold), "iou_threshold": float(iou_threshold),
           "match_iou": float(match_iou), "precisions": {}}
    ref_run, ref_acc = None, None
    for p in names:
        with strict_float32():
            out["float32"] = float32_settings()
            run = run_at_precision(model, frames, point_cloud_range, p, device, batch_size, progress, road)
        acc = _accuracy(eval_base, run, iou_threshold, score_threshold)
        entry = {"autocast_dtype": None if PRECISIONS[p] is None else str(PRECISIONS[p]).replace("torch.", ""),
                 "seconds_per_frame": run.seconds / max(len(frames), 1),
                 "detections": int(sum(int((d.scores >= score_threshold).sum()) for d in run.predictions.values())),
                 "nonfinite_values": run.nonfinite_values, "nonfinite_frames": len(run.nonfinite_frames),
                 "nonfinite_frame_ids": run.nonfinite_frames[:10], "nonfinite_detections": run.nonfinite_detections,
                 **acc}
        if ref_run is None:
            ref_run, ref_acc = run, acc
        else:
            entry["ap_r40_diff"] = {r: _diff(ref_acc["ap_r40"][r], acc["ap_r40"][r]) for r in RANGE_NAMES}
            entry["recall_diff"] = {r: _diff(ref_acc["recall"][r], acc["recall"][r]) for r in RANGE_NAMES}
            diffs = [abs(v) for v in entry["ap_r40_diff"].values() if v is not None]
            entry["max_abs_ap_r40_diff"] = max(diffs) if diffs else None
            entry["boxes"] = box_differences(ref_run.predictions, run.predictions, score_threshold, match_iou)
        out["precisions"][p] = entry
    return out


def _f(v, digits: int = 3, signed: bool = False) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def precision_markdown(report: dict, title: str = "Inference precision against float32") -> str:
    """A Markdown table of `compare_precision`'s report (units in the headers)."""
    f32 = report.get("float32")
    settings = (f"; float32 matrix products {f32['cuda_matmul']}, cuDNN convolutions {f32['cudnn_conv']} (ieee: "
                f"full float32, tf32: TensorFloat-32)" if f32 else "")
    lines = [f"# {title}", "",
             f"{report['num_frames']} frames on {report['device']}{settings}; AP@R40 / recall at 3D IoU "
             f"{report['iou_threshold']:g}, level All, score >= {report['score_threshold']:g}; boxes matched to the "
             f"float32 run's at BEV IoU >= {report['match_iou']:g}. Differences are the precision's value minus "
             f"float32's. Corner: the largest displacement of any of a matched box's 8 corners (metres), "
             f"boxes compared as solids (a direction flip, heading turned by pi, is counted apart).", "",
             "| precision | s/frame | detections | NaN/inf values (frames) | dropped non-finite boxes | "
             + " | ".join(f"AP@R40 {r} (diff)" for r in RANGE_NAMES)
             + " | matched | unmatched f32 / this | direction flips | max corner (m) | p99 corner (m) | "
               "max centre (m) | max size (m) | max heading (rad) | max score |",
             "|" + "---|" * (5 + len(RANGE_NAMES) + 9)]
    for name, e in report["precisions"].items():
        diff = e.get("ap_r40_diff", {})
        aps = [f"{_f(e['ap_r40'][r])} ({_f(diff.get(r), signed=True)})" if diff else _f(e["ap_r40"][r])
               for r in RANGE_NAMES]
        b = e.get("boxes")
        tail = (["-"] * 9 if b is None else
                [str(b["matched"]), f"{b['unmatched_reference']} / {b['unmatched_other']}", str(b["heading_flips"]),
                 _f(b["max_corner_diff_m"], 4), _f(b["p99_corner_diff_m"], 4), _f(b["max_centre_diff_m"], 4),
                 _f(b["max_size_diff_m"], 4),
                 _f(b["max_heading_diff_rad"], 4), _f(b["max_score_diff"], 4)])
        lines.append("| " + " | ".join([name, _f(e["seconds_per_frame"], 3), str(e["detections"]),
                                         f"{e['nonfinite_values']} ({e['nonfinite_frames']})",
                                         str(e["nonfinite_detections"]), *aps, *tail]) + " |")
    return "\n".join(lines) + "\n"


def precision_frames(root, height: float | str, split: str, limit: int = 0) -> list:
    """The first `limit` frames (0: all) of `split` at `height` in the dataset at `root`; ValueError (naming
    the dataset) when it cannot be read or the split is empty."""
    try:
        dataset = Height3Dataset(root, height, split)
    except (FileNotFoundError, ValueError, KeyError, DatasetError) as e:
        raise ValueError(f"{e} (give --data ROOT --height H of a dataset in the Height3 layout)") from None
    n = len(dataset) if limit == 0 else min(limit, len(dataset))
    if n == 0:
        raise ValueError(f"{root}: the {split!r} split at {key_label(height)} has no frames; try --split all")
    return [dataset[i] for i in range(n)]


def checkpoint_precision_report(model: nn.Module, ck: dict, checkpoint, frames: Sequence, *, root, height: float,
                                split: str, precisions: Sequence[str] | None, device: torch.device,
                                batch_size: int = 4, score_threshold: float | None = None, match_iou: float = 0.5,
                                progress: bool = True) -> dict:
    """`compare_precision` of a loaded checkpoint (`model`, its dict `ck`) on `frames`, headed by where the
    checkpoint and the frames come from (the report of precision.json)."""
    report = compare_precision(model, frames, ck["config"]["model"]["point_cloud_range"], precisions, device,
                               batch_size, score_threshold=score_threshold, match_iou=match_iou, progress=progress,
                               road=RoadConfig.of_run_config(ck["config"]))
    return {"checkpoint": str(checkpoint), "model": ck["model_name"], "data": str(root), "height": height,
            "split": split, "torch": torch.__version__, "threads": torch.get_num_threads(), **report}


def checkpoint_precision_markdown(report: dict) -> str:
    """precision.md of a `checkpoint_precision_report`."""
    md = precision_markdown(report, f"{report['model']} at {key_label(report['height'])}: inference precision against "
                                    f"float32")
    return md + f"\nCheckpoint: {report['checkpoint']}; torch {report['torch']}, {report['threads']} threads.\n"


def precision_summary_lines(report: dict) -> list[str]:
    """One line per precision: speed, AP@R40 per range, non-finite values and box differences."""
    lines = []
    for name, e in report["precisions"].items():
        line = (f"{name:9s} {e['seconds_per_frame']:.3f} s/frame, AP@R40 "
                + " / ".join(f"{e['ap_r40'][r]:.3f}" if e["ap_r40"][r] is not None else "-" for r in e["ap_r40"])
                + f", NaN/inf values {e['nonfinite_values']}")
        if "boxes" in e:
            b = e["boxes"]
            line += (f", max |AP diff| {e['max_abs_ap_r40_diff']:.3f}" if e["max_abs_ap_r40_diff"] is not None else "")
            line += (f", largest box difference {b['max_corner_diff_m']:.4f} m (corner) over {b['matched']} matched "
                     f"detections, {b['unmatched_reference']} / {b['unmatched_other']} unmatched")
        lines.append(line)
    return lines
