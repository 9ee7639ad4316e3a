"""The small-object probe's figures per rig: LDR and points per object by kind, place and distance.

An object (detbench.sim.probes: cone, tyre, child) is LiDAR-detected by the vehicles' rule: at least one
point inside its box with the bottom raised by the study's lift. Objects ahead (x >= 0, |y| <= the large
range's half width) are binned by x in SMALL_BIN_M bins up to SMALL_MAX_M.
"""
from __future__ import annotations

import math

import numpy as np

from detbench.data.regions import DETECTED_MIN_POINTS, RANGES
from detbench.sim.probes import PROBE_KINDS, PROBE_PLACES

SMALL_BIN_M = 10.0
SMALL_MAX_M = 100.0


class SmallObjectCounts:
    """Per key (rig name), kind and distance bin: objects, detected objects and points on them."""

    def __init__(self):
        self.num_bins = int(math.ceil(SMALL_MAX_M / SMALL_BIN_M))
        self.half_width = RANGES["large"][2]
        self._acc: dict[str, np.ndarray] = {}  # key -> (places, kinds, 3 [total, detected, points], bins)

    def add(self, key: str, boxes: np.ndarray, kinds: np.ndarray, counts: np.ndarray, places=None) -> None:
        acc = self._acc.setdefault(key, np.zeros((len(PROBE_PLACES), len(PROBE_KINDS), 3, self.num_bins), np.int64))
        if not len(boxes):
            return
        x, y = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
        sel = (x >= 0) & (x < SMALL_MAX_M) & (np.abs(y) <= self.half_width)
        b = np.minimum((np.maximum(x, 0) / SMALL_BIN_M).astype(np.int64), self.num_bins - 1)
        k = np.array([PROBE_KINDS.index(str(v)) for v in kinds], np.int64)
        p = np.array([PROBE_PLACES.index(str(v)) for v in places], np.int64) if places is not None \
            else np.zeros(len(k), np.int64)
        det = counts >= DETECTED_MIN_POINTS
        for row, value in enumerate((np.ones(len(k), np.int64), det.astype(np.int64), counts.astype(np.int64))):
            np.add.at(acc[:, :, row], (p[sel], k[sel], b[sel]), value[sel])

    def definitions(self) -> dict:
        return {"kinds": list(PROBE_KINDS), "places": list(PROBE_PLACES),
                "bins_m": [[i * SMALL_BIN_M, (i + 1) * SMALL_BIN_M] for i in range(self.num_bins)],
                "region": f"object centre 0 <= x < {SMALL_MAX_M:g} m, |y| <= {self.half_width:g} m; binned by x",
                "detected": "at least one point inside the object's box with the bottom lift (the vehicles' rule)",
                "points_per_object": "points inside the box per object in the bin (detected or not)"}

    def report(self, key: str) -> dict:
        """{kind: {"total", "detected", "ldr", "points_per_object"} lists by bin, and "by_place": {place: {kind:
        {"total", "detected", "ldr"}}} over all bins}."""
        acc = self._acc.get(key, np.zeros((len(PROBE_PLACES), len(PROBE_KINDS), 3, self.num_bins), np.int64))
        both = acc.sum(axis=0)
        out = {}
        for ki, kind in enumerate(PROBE_KINDS):
            t, d, pts = both[ki]
            out[kind] = {"total": t.tolist(), "detected": d.tolist(),
                         "ldr": [float(a) / b if b else None for a, b in zip(d, t)],
                         "points_per_object": [round(float(a) / b, 3) if b else None for a, b in zip(pts, t)]}
        out["by_place"] = {place: {kind: {"total": int(acc[pi, ki, 0].sum()), "detected": int(acc[pi, ki, 1].sum()),
                                          "ldr": (float(acc[pi, ki, 1].sum()) / acc[pi, ki, 0].sum()
                                                  if acc[pi, ki, 0].sum() else None)}
                                   for ki, kind in enumerate(PROBE_KINDS)} for pi, place in enumerate(PROBE_PLACES)}
        return out


def small_object_markdown(report: dict) -> list[str]:
    """Markdown lines: per kind, LDR and points per object by distance for every rig."""
    d = report["small_object_definitions"]
    rigs = list(report["rigs"])
    out = ["## Small objects: LDR (points per object) by distance", "", f"{d['region']}. {d['detected']}.", ""]
    for kind in d["kinds"]:
        out += [f"**{kind}**", "", "| Distance (m) | " + " | ".join(rigs) + " |", "|" + "---|" * (len(rigs) + 1)]
        for i, (a, b) in enumerate(d["bins_m"]):
            cells = []
            for n in rigs:
                c = report["rigs"][n]["small_objects"][kind]
                q, p = c["ldr"][i], c["points_per_object"][i]
                cells.append("-" if q is None else f"{q:.2f} ({p:.1f}) n={c['total'][i]}")
            out.append(f"| {a:g}-{b:g} | " + " | ".join(cells) + " |")
        out.append("")
    return out


__all__ = ["SmallObjectCounts", "small_object_markdown", "SMALL_BIN_M", "SMALL_MAX_M"]
