"""OpenPCDet's "custom" dataset format, and moving data between it and the detbench layout.

OpenPCDet's custom format (its docs/CUSTOM_DATASET_TUTORIAL.md, read by
pcdet/datasets/custom/custom_dataset.py) is **one** point cloud per frame:

```
ROOT/points/<id>.npy         (N, C) float32, C = len(POINT_FEATURE_ENCODING.src_feature_list), here x y z intensity
ROOT/labels/<id>.txt         one box a line, single spaces: x y z dx dy dz heading class
ROOT/ImageSets/train.txt     frame ids of DATA_SPLIT['train']
ROOT/ImageSets/val.txt       frame ids of DATA_SPLIT['test'] (the shipped config says 'val')
```

What OpenPCDet's reader does with it, and what an export must therefore respect:

- `get_label` splits each line on single spaces, takes the last token as the class and the
  others as float32 box values; `get_infos` then slices `gt_boxes[:, :7]`, so a label file
  with no lines (a frame without vehicles) gives a 1-D empty array and info creation stops
  with an IndexError. Frames without boxes cannot be listed in ImageSets.
- Evaluation maps every ground-truth and predicted class through `MAP_CLASS_TO_KITTI`
  (a KeyError for a class it does not list) to a class of OpenPCDet's KITTI evaluator
  (Car, Pedestrian, Cyclist, Van, Person_sitting in every version; Truck in newer ones).
- Training keeps only the boxes whose class is in the model's `CLASS_NAMES`.
- There is no sensor metadata: points and labels are in one frame of the user's choosing,
  the same for both.

detbench differs: several heights share one label set, points live in `points/<height>/`,
labels are in the ego *ground* frame, the split lists are train.txt and test.txt,
dataset.json carries the sensors. This module holds what both directions share: the format's
split names and classes, class maps (`parse_class_map`) and the frame of a folder's points from
its road (`guess_points_frame`). The export (one height of a detbench dataset as an OpenPCDet
custom folder, `tools/export_openpcdet.py`) is `detbench.data.openpcdet_export`; the import is
`detbench.data.convert`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Iterable, Sequence

import numpy as np

from detbench.data.transforms import sensor_to_ground

# OpenPCDet's split files: DATA_SPLIT {'train': train, 'test': val} in its custom_dataset.yaml
OPENPCDET_SPLITS = {"train": "train", "test": "val"}  # detbench split -> OpenPCDet ImageSets name
# classes OpenPCDet's KITTI evaluator knows in every version (Truck only in newer ones)
KITTI_EVAL_CLASSES = ("Car", "Pedestrian", "Cyclist", "Van", "Person_sitting")
# classes that are not vehicles in OpenPCDet's and KITTI's label sets
NON_VEHICLE_CLASSES = ("Pedestrian", "Cyclist", "Person_sitting", "DontCare")

CLASS_MAP_PRESETS = {
    # every vehicle type (car, suv, van, taxi, truck, bus) -> OpenPCDet's 'Vehicle'
    "vehicle": "*=Vehicle",
    # names unchanged
    "keep": "*=*",
    # drop OpenPCDet's / KITTI's non-vehicle classes, keep every other name unchanged
    "vehicles-only": ",".join(f"{c}=-" for c in NON_VEHICLE_CLASSES) + ",*=*",
}
DEFAULT_EXPORT_CLASS_MAP = "vehicle"
DEFAULT_IMPORT_CLASS_MAP = "vehicles-only"


# --------------------------------------------------------------------------- class maps

@dataclass(frozen=True)
class ClassMap:
    """Rename or drop label classes.

    `rules` maps a class name (compared case-insensitively) to its new name, or to None
    (drop the line); `default` applies to every other name: a new name, None (drop) or "*"
    (keep the name). `spec` is the text it was parsed from.
    """

    rules: dict[str, str | None] = field(default_factory=dict)  # lower-cased source name -> target
    default: str | None = "*"
    spec: str = "*=*"

    def target(self, name: str) -> str | None:
        """The new name of class `name`, or None when its lines are dropped."""
        t = self.rules.get(name.lower(), self.default)
        return name if t == "*" else t

    def apply(self, names: Iterable[str]) -> tuple[np.ndarray, list[str]]:
        """(keep mask (M,) bool, new names of the kept lines) for the class names of M label lines."""
        targets = [self.target(str(n)) for n in names]
        keep = np.array([t is not None for t in targets], dtype=bool)
        return keep, [t for t in targets if t is not None]


def parse_class_map(specs: str | Sequence[str] | None, default: str = DEFAULT_EXPORT_CLASS_MAP) -> ClassMap:
    """A ClassMap from `--class-map` values (one string or several; later rules win).

    Each value is a preset name (vehicle, keep, vehicles-only) or comma-separated rules
    `SRC=DST`: SRC a class name (case-insensitive) or `*` (every class no rule names); DST a
    class name, `-` (or nothing) to drop those lines, or `*` to keep the name. Names not
    covered by any rule are kept unchanged. Raises ValueError with the fix.
    """
    if specs is None or (not isinstance(specs, str) and len(specs) == 0):
        specs = [default]
    if isinstance(specs, str):
        specs = [specs]
    rules: dict[str, str | None] = {}
    dflt: str | None = "*"
    for spec in specs:
        spec = CLASS_MAP_PRESETS.get(spec.strip(), spec)
        for item in spec.split(","):
            item = item.strip()
            if not item:
                continue
            if item in CLASS_MAP_PRESETS:
                sub = parse_class_map(CLASS_MAP_PRESETS[item])
                rules.update(sub.rules)
                dflt = sub.default
                continue
            if "=" not in item:
                raise ValueError(f"--class-map {item!r}: write SRC=DST (e.g. car=Vehicle, *=Vehicle, Pedestrian=-) "
                                 f"or a preset ({', '.join(CLASS_MAP_PRESETS)})")
            src, dst = (s.strip() for s in item.split("=", 1))
            if not src:
                raise ValueError(f"--class-map {item!r}: the class before '=' is missing")
            if any(c.isspace() for c in src + dst):
                raise ValueError(f"--class-map {item!r}: class names cannot hold spaces")
            target = None if dst in ("", "-") else dst
            if target is not None and target != "*":
                try:
                    float(target)
                except ValueError:
                    pass
                else:
                    raise ValueError(f"--class-map {item!r}: {target!r} is a number; a class name must not be")
            if src == "*":
                dflt = target
            else:
                rules[src.lower()] = target
    text = ",".join([f"{k}={'-' if v is None else v}" for k, v in rules.items()]
                    + [f"*={'-' if dflt is None else dflt}"])
    return ClassMap(rules=rules, default=dflt, spec=text)


def count_classes(before: Iterable[str], class_map: ClassMap, into: dict | None = None) -> dict:
    """Add the lines of `before` (class names) to `into`: {source class: {"kept": n, "dropped": n, "as": name}}."""
    into = {} if into is None else into
    for n in before:
        n = str(n)
        t = class_map.target(n)
        c = into.setdefault(n, {"kept": 0, "dropped": 0, "as": t})
        c["kept" if t is not None else "dropped"] += 1
    return into


def class_count_lines(counts: dict) -> list[str]:
    """One printable line per source class: 'car: 120 kept as Vehicle, 0 dropped'."""
    out = []
    for name in sorted(counts):
        c = counts[name]
        as_ = "" if c["as"] in (None, name) else f" as {c['as']}"
        out.append(f"{name}: {c['kept']} line(s) kept{as_}, {c['dropped']} dropped")
    return out


# --------------------------------------------------------------------------- frame of a folder's points

ROAD_REGION = "5 m < x < 40 m, |y| < 4 m"
FRAME_TOLERANCE_M = 0.35  # the road must lie within this of 0 (ground frame) or -height (sensor frame)


def road_surface_z(points: np.ndarray) -> float:
    """Estimated road height (m): 5th percentile of z for 5 < x < 40 m, |y| < 4 m (nan with < 20 points)."""
    p = np.asarray(points)
    sel = p[(p[:, 0] > 5) & (p[:, 0] < 40) & (np.abs(p[:, 1]) < 4)]
    return float(np.percentile(sel[:, 2], 5)) if len(sel) >= 20 else float("nan")


def level_road_z(points: np.ndarray, pitch_deg: float = 0.0) -> float:
    """Road height (m) of raw points after undoing only the sensor's pitch (no height added).

    In the ground frame the road is near 0; in the LiDAR's own frame near -height.
    """
    p = np.asarray(points)
    if pitch_deg:
        p = sensor_to_ground(p[:, :3].astype(np.float64), 0.0, pitch_deg)
    return road_surface_z(p)


def frame_tolerance(height: float) -> float:
    """How far (m) the road may lie from 0 (ground frame) or -height (sensor frame) to name the frame:
    `FRAME_TOLERANCE_M`, at most a third of the height so that the two cannot both fit."""
    return min(FRAME_TOLERANCE_M, float(height) / 3)


MIN_FRAME_HEIGHT_M = 0.3  # below this the road cannot tell the two frames apart


def guess_points_frame(road_z: Sequence[float], height: float) -> tuple[str | None, str]:
    """The frame ("ground" or "sensor") of points whose road lies at `road_z` (m, one value per sampled
    frame, pitch undone), for a LiDAR mounted `height` m above the road; (None, why) when the road
    cannot tell (too few road points, a road at neither 0 nor -height within `frame_tolerance`,
    frames that disagree, or a height below `MIN_FRAME_HEIGHT_M`)."""
    z = np.asarray([v for v in road_z if math.isfinite(v)], dtype=np.float64)
    if len(z) == 0:
        return None, f"too few points on the road ({ROAD_REGION}) to find it"
    if height < MIN_FRAME_HEIGHT_M:
        return None, (f"at {height:g} m the road of the two frames (0 and -{height:g} m) is too close to tell "
                      f"apart")
    tol = frame_tolerance(height)
    votes = ["ground" if abs(v) <= tol else "sensor" if abs(v + height) <= tol else None for v in z]
    med = float(np.median(z))
    shown = ", ".join(f"{v:+.2f}" for v in z[:5]) + (" ..." if len(z) > 5 else "")
    if any(v is None for v in votes):
        return None, (f"the road lies at z = {shown} m, not within {tol:.2f} m of 0 m (ground frame) or of "
                      f"-{height:g} m (the LiDAR's own frame); check the height and --pitch")
    if len(set(votes)) > 1:
        return None, f"the sampled frames disagree (road at z = {shown} m)"
    return votes[0], f"road at z = {med:+.2f} m (median of {len(z)} frame(s))"


def label_bottom_z(boxes: np.ndarray) -> np.ndarray:
    """Bottom heights (m) z - dz/2 of the boxes in front of the car (0 < x < 40 m, |y| < 8 m)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    sel = (b[:, 0] > 0) & (b[:, 0] < 40) & (np.abs(b[:, 1]) < 8)
    return b[sel, 2] - b[sel, 5] / 2


__all__ = [
    "ClassMap", "parse_class_map", "count_classes", "class_count_lines", "CLASS_MAP_PRESETS",
    "DEFAULT_EXPORT_CLASS_MAP", "DEFAULT_IMPORT_CLASS_MAP", "NON_VEHICLE_CLASSES", "KITTI_EVAL_CLASSES",
    "OPENPCDET_SPLITS", "road_surface_z", "level_road_z", "guess_points_frame", "frame_tolerance", "label_bottom_z",
]
