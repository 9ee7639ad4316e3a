"""Where a detector's recall goes: for each LiDAR-detected vehicle of a range, the best 3D IoU any kept
prediction reaches and how that prediction's box is off.

Recall at 3D IoU 0.7 counts a vehicle found only when one prediction overlaps it that well; a vehicle
the detector saw but boxed loosely (best IoU 0.5-0.7) is a miss like one it never saw (best IoU 0). This
diagnosis tells the two apart, per frame set: the share of vehicles in each best-IoU band, the median
error of the best-overlapping prediction (by bird's-eye IoU) in centre and size, and the same by the
vehicle's length and distance, so a user sees whether recall is lost to detection, to localisation, or to
one kind of vehicle (the length of a vehicle seen only from behind, say). A vehicle counts as found when any
kept prediction overlaps it enough, without the evaluator's one-to-one matching, so this recall can exceed
the report's where one prediction overlaps two vehicles.

Units: metres; IoU and shares are fractions. Signed errors are prediction minus ground truth.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from detbench.config import shipped_default
from detbench.data.regions import RANGES, check_range_name, lidar_detected
from detbench.ops import boxes_iou3d, boxes_iou_bev

__all__ = ["IOU_BANDS", "LENGTH_BANDS", "DISTANCE_BANDS", "Misses", "misses", "misses_markdown"]

IOU_BANDS: tuple[tuple[float, float], ...] = ((0.0, 0.01), (0.01, 0.3), (0.3, 0.5), (0.5, 0.6), (0.6, 0.7),
                                              (0.7, 1.01))
LENGTH_BANDS: tuple[tuple[float, float], ...] = ((0.0, 4.2), (4.2, 4.8), (4.8, 5.5), (5.5, 7.0), (7.0, 99.0))
DISTANCE_BANDS: tuple[tuple[float, float], ...] = ((0.0, 15.0), (15.0, 30.0), (30.0, 50.0), (50.0, 100.0),
                                                   (100.0, 150.0))
_ERRORS = ("x", "y", "z", "length", "width", "height")


@dataclass(frozen=True)
class Misses:
    """Per LiDAR-detected vehicle of the range (arrays of one length): its best 3D IoU, the bird's-eye IoU
    and box error (prediction minus truth: x, y, z, length, width, height) of the prediction overlapping it
    most in bird's-eye view, its length and distance ahead (x)."""

    range_name: str
    iou_threshold: float
    best_iou3d: np.ndarray
    best_iou_bev: np.ndarray
    error: np.ndarray  # (V, 6)
    length: np.ndarray
    distance: np.ndarray

    def to_dict(self) -> dict:
        n = len(self.best_iou3d)
        found = self.best_iou3d >= self.iou_threshold
        near = (self.best_iou3d >= 0.3) & ~found

        def med(mask, signed=False):
            if not mask.any():
                return None
            e = self.error[mask]
            return {k: round(float(np.median(e[:, i] if signed else np.abs(e[:, i]))), 3)
                    for i, k in enumerate(_ERRORS)}

        def bands(values, edges):
            out = []
            for lo, hi in edges:
                m = (values >= lo) & (values < hi)
                if m.any():
                    out.append({"from": lo, "to": hi, "vehicles": int(m.sum()),
                                "recall": round(float(found[m].mean()), 4),
                                "median_best_iou3d": round(float(np.median(self.best_iou3d[m])), 3),
                                "median_length_error": round(float(np.median(self.error[m, 3])), 3),
                                "median_x_error": round(float(np.median(self.error[m, 0])), 3)})
            return out

        return {"range": self.range_name, "iou_threshold": self.iou_threshold, "vehicles": n,
                "recall": round(float(found.mean()), 4) if n else None,
                "best_iou3d_bands": [{"from": lo, "to": hi, "share": round(float(((self.best_iou3d >= lo)
                                                                                   & (self.best_iou3d < hi)).mean()), 4)
                                      if n else None} for lo, hi in IOU_BANDS],
                "near_misses": {"share": round(float(near.mean()), 4) if n else None,
                                "median_abs_error_m": med(near), "median_signed_error_m": med(near, True)},
                "found": {"median_abs_error_m": med(found), "median_signed_error_m": med(found, True)},
                "by_length": bands(self.length, LENGTH_BANDS), "by_distance": bands(self.distance, DISTANCE_BANDS)}


def misses(frames: Sequence, predictions: Mapping, range_name: str = "small", score_threshold: float | None = None,
           iou_threshold: float | None = None) -> Misses:
    """`Misses` of the LiDAR-detected vehicles whose centre lies in `range_name` over `frames` (Frames with
    points and boxes), against `predictions` ({frame_id: Detections or (boxes, scores)}) kept at
    `score_threshold`; None: the evaluator's thresholds (configs/default.yaml `eval:`)."""
    check_range_name(range_name)
    score_threshold = float(shipped_default("eval.score_threshold", score_threshold))
    iou_threshold = float(shipped_default("eval.iou_threshold", iou_threshold))
    x_min, x_max, y_max = RANGES[range_name]
    iou3, iob, err, length, dist = [], [], [], [], []
    for f in frames:
        pts = np.asarray(f.points, np.float32)
        boxes = np.asarray(f.boxes, np.float64).reshape(-1, 7)
        gt = boxes[lidar_detected(pts, boxes)]
        gt = gt[(gt[:, 0] >= x_min) & (gt[:, 0] <= x_max) & (np.abs(gt[:, 1]) <= y_max)]
        if not len(gt):
            continue
        p = predictions.get(f.frame_id)
        pb, ps = (np.zeros((0, 7)), np.zeros(0)) if p is None else (np.asarray(p[0], np.float64).reshape(-1, 7),
                                                                     np.asarray(p[1], np.float64).reshape(-1))
        pb = pb[ps >= score_threshold]
        if len(pb):
            i3, ib = boxes_iou3d(gt, pb), boxes_iou_bev(gt, pb)
            best = pb[np.argmax(ib, axis=1)]
            iou3.append(i3.max(axis=1))
            iob.append(ib.max(axis=1))
            err.append(best[:, :6] - gt[:, :6])
        else:
            iou3.append(np.zeros(len(gt)))
            iob.append(np.zeros(len(gt)))
            err.append(np.full((len(gt), 6), np.nan))
        length.append(gt[:, 3])
        dist.append(gt[:, 0])

    def cat(parts, shape=(0,)):
        return np.concatenate(parts) if parts else np.zeros(shape)

    return Misses(range_name, float(iou_threshold), cat(iou3), cat(iob), cat(err, (0, 6)), cat(length), cat(dist))


def misses_markdown(d: Mapping, title: str = "") -> str:
    """Misses.to_dict() as Markdown: the best-IoU bands, the near misses' errors, by length and by distance."""
    def errs(e):
        return "-" if not e else ", ".join(f"{k} {v:+.2f}" for k, v in e.items())

    lines = [f"# Where recall goes: {d['range']} range" + (f" ({title})" if title else ""), "",
             f"{d['vehicles']} LiDAR-detected vehicles; recall at 3D IoU {d['iou_threshold']:g}: "
             + ("-" if d["recall"] is None else f"{d['recall']:.3f}") + ". Each vehicle's best 3D IoU with a kept "
             "prediction; errors are the bird's-eye best-overlapping prediction minus the truth, in metres.", "",
             "| best 3D IoU | share of vehicles |", "|---|---:|"]
    lines += [f"| [{b['from']:.2f}, {min(b['to'], 1.0):.2f}) | {b['share']:.3f} |" for b in d["best_iou3d_bands"]
              if b["share"] is not None]
    nm = d["near_misses"]
    lines += ["", f"Near misses (best 3D IoU 0.3 to {d['iou_threshold']:g}): "
              + ("-" if nm["share"] is None else f"{nm['share']:.3f}") + " of the vehicles; median error "
              f"{errs(nm['median_signed_error_m'])} (absolute: {errs(nm['median_abs_error_m'])}). Found vehicles: "
              f"median absolute error {errs(d['found']['median_abs_error_m'])}.", ""]
    for key, name, unit in (("by_length", "vehicle length", "m"), ("by_distance", "distance ahead", "m")):
        lines += [f"| {name} ({unit}) | vehicles | recall | median best 3D IoU | median length error | "
                  "median x error |", "|---|---:|---:|---:|---:|---:|"]
        lines += [f"| {b['from']:g}-{b['to']:g} | {b['vehicles']} | {b['recall']:.3f} | {b['median_best_iou3d']:.3f} | "
                  f"{b['median_length_error']:+.2f} | {b['median_x_error']:+.2f} |" for b in d[key]]
        lines.append("")
    return "\n".join(lines)
