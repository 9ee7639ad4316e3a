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
dataset.json carries the sensors. This module holds what both directions share: class maps
(`parse_class_map`), the frame of a folder's points from its road (`guess_points_frame`),
and `export_openpcdet` (one height of a detbench dataset as an OpenPCDet custom folder;
`tools/export_openpcdet.py`). The import direction is `detbench.data.convert`.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterable, Sequence

import numpy as np

from detbench.data.layout import IMAGESETS_DIR, LABELS_DIR, POINTS_DIR, POINTS_FRAMES
from detbench.data.readers import format_labels
from detbench.data.transforms import boxes_ground_to_sensor, ground_to_sensor, sensor_to_ground
from detbench.utils.atomic import atomic_save, atomic_write_json, atomic_write_text
from detbench.utils.folder_ownership import FolderKind, check_replaceable
from detbench.utils.staged_folders import recover_staged, staged_folder

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

EXPORT_MANIFEST = "detbench_export.json"
EXPORT_MARKDOWN = "detbench_export.md"
EXPORT_YAML = "custom_dataset.yaml"
EXPORT_SCRIPT = "create_infos.sh"
# what OpenPCDet's create_custom_infos writes into the data folder (removed by --overwrite)
_OPENPCDET_GENERATED = ("custom_infos_train.pkl", "custom_infos_val.pkl", "custom_dbinfos_train.pkl", "gt_database")


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


# --------------------------------------------------------------------------- export

# an export folder as `export_openpcdet` replaces it (`detbench.utils.folder_ownership.check_replaceable`): only an
# earlier export, holding the export's files and what OpenPCDet's info generation adds to it
EXPORT_FOLDER = FolderKind(
    name="an earlier export", marker=EXPORT_MANIFEST,
    entries=(POINTS_DIR, LABELS_DIR, IMAGESETS_DIR, EXPORT_MANIFEST, EXPORT_MARKDOWN, EXPORT_YAML, EXPORT_SCRIPT)
    + _OPENPCDET_GENERATED,
    foreign="written by an export or by OpenPCDet's info generation",
    removes="its OpenPCDet infos and gt_database are removed too, as they describe the old files")


def _fmt_num(v: float) -> str:
    return f"{v:.10g}"


def openpcdet_point_cloud_range(frame: str, height: float) -> list[float]:
    """POINT_CLOUD_RANGE for the export: x 0..153.6 m (the LiDAR sees ahead; the study reaches 150 m),
    y -40..40 m, z a 6 m slab from 1 m below the road. With 0.1 x 0.1 x 0.15 m voxels this follows
    OpenPCDet's rules for voxel detectors (x and y voxel counts multiples of 16, 40 voxels in z)."""
    z0 = -1.0 if frame == "ground" else round(-1.0 - float(height), 4)
    return [0.0, -40.0, z0, 153.6, 40.0, round(z0 + 6.0, 4)]


def openpcdet_dataset_yaml(data_path: str | os.PathLike, classes: Sequence[str], frame: str, height: float,
                           pitch_deg: float = 0.0, source: str = "") -> str:
    """Text of a custom_dataset.yaml for the export (OpenPCDet's shipped one with this data's values)."""
    classes = list(classes)
    kitti = {c: (c if c in KITTI_EVAL_CLASSES else "Car") for c in classes}
    pcr = ", ".join(_fmt_num(v) for v in openpcdet_point_cloud_range(frame, height))
    frame_txt = ("ego ground frame: origin on the road below the LiDAR, road at z = 0" if frame == "ground" else
                 f"the LiDAR's own frame: origin at the sensor, road at z = -{height:g} m"
                 + (f" (sensor pitched {pitch_deg:g} deg down: the road rises with x in this frame)"
                    if pitch_deg else ""))
    cls_list = ", ".join(f"'{c}'" for c in classes)
    lines = [
        f"# OpenPCDet dataset config written by detbench (tools/export_openpcdet.py){': ' + source if source else ''}",
        f"# Frame of points and labels: {frame} - {frame_txt}.",
        "# Use it as tools/cfgs/dataset_configs/custom_dataset.yaml (or point your model config's",
        "# DATA_CONFIG._BASE_CONFIG_ at this file) and set in the model config:",
        f"#   CLASS_NAMES: [{cls_list}]",
        "# and its anchor sizes / class lists to these classes.",
        "DATASET: 'CustomDataset'",
        f"DATA_PATH: '{Path(data_path)}'",
        "",
        "# x forward 0..153.6 m (the LiDAR looks ahead), |y| <= 40 m, a 6 m slab in z from 1 m below the road:",
        "# 1536 x 800 x 40 voxels of 0.1 x 0.1 x 0.15 m (x, y multiples of 16; 40 in z).",
        f"POINT_CLOUD_RANGE: [{pcr}]",
        "",
        "MAP_CLASS_TO_KITTI: {",
        *[f"    '{c}': '{k}'," for c, k in kitti.items()],
        "}",
        "",
        "DATA_SPLIT: {",
        "    'train': train,",
        "    'test': val",
        "}",
        "",
        "INFO_PATH: {",
        "    'train': [custom_infos_train.pkl],",
        "    'test': [custom_infos_val.pkl],",
        "}",
        "",
        "POINT_FEATURE_ENCODING: {",
        "    encoding_type: absolute_coordinates_encoding,",
        "    used_feature_list: ['x', 'y', 'z', 'intensity'],",
        "    src_feature_list: ['x', 'y', 'z', 'intensity'],",
        "}",
        "",
        "DATA_AUGMENTOR:",
        "    DISABLE_AUG_LIST: ['placeholder']",
        "    AUG_CONFIG_LIST:",
        "        - NAME: gt_sampling",
        "          USE_ROAD_PLANE: False",
        "          DB_INFO_PATH:",
        "              - custom_dbinfos_train.pkl",
        "          PREPARE: {",
        f"             filter_by_min_points: [{', '.join(repr(c + ':5') for c in classes)}],",
        "          }",
        f"          SAMPLE_GROUPS: [{', '.join(repr(c + ':15') for c in classes)}]",
        "          NUM_POINT_FEATURES: 4",
        "          DATABASE_WITH_FAKELIDAR: False",
        "          REMOVE_EXTRA_WIDTH: [0.0, 0.0, 0.0]",
        "          LIMIT_WHOLE_SCENE: True",
        "",
        "        # mirror y only: the LiDAR sees 180 deg ahead, a flip of x would put the scene behind the car",
        "        - NAME: random_world_flip",
        "          ALONG_AXIS_LIST: ['x']",
        "",
        "        # +-10 deg, as detbench's own training (configs/default.yaml)",
        "        - NAME: random_world_rotation",
        "          WORLD_ROT_ANGLE: [-0.17453293, 0.17453293]",
        "",
        "        - NAME: random_world_scaling",
        "          WORLD_SCALE_RANGE: [0.95, 1.05]",
        "",
        "DATA_PROCESSOR:",
        "    - NAME: mask_points_and_boxes_outside_range",
        "      REMOVE_OUTSIDE_BOXES: True",
        "",
        "    - NAME: shuffle_points",
        "      SHUFFLE_ENABLED: {",
        "        'train': True,",
        "        'test': False",
        "      }",
        "",
        "    - NAME: transform_points_to_voxels",
        "      VOXEL_SIZE: [0.1, 0.1, 0.15]",
        "      MAX_POINTS_PER_VOXEL: 5",
        "      MAX_NUMBER_OF_VOXELS: {",
        "        'train': 150000,",
        "        'test': 150000",
        "      }",
    ]
    return "\n".join(lines) + "\n"


def openpcdet_commands(out: Path, root: Path, height_k: str, frame: str) -> dict:
    """The shell commands that take the export into OpenPCDet and its predictions back (paths absolute)."""
    out = Path(out).resolve()
    return {
        "link": f"ln -sfn {out} OPENPCDET/data/custom",
        "create_infos": f"cd OPENPCDET && python -m pcdet.datasets.custom.custom_dataset create_custom_infos "
                        f"{out / EXPORT_YAML}",
        "evaluate_in_detbench": f"python tools/eval.py --data {Path(root).resolve()} --height {height_k} --split test "
                                f"--pred OPENPCDET/output/.../eval/.../val/default/result.pkl --pred-frame {frame} "
                                f"--out runs/openpcdet_eval_{height_k}",
    }


def _create_infos_script(out: Path, commands: dict) -> str:
    return "\n".join([
        "#!/bin/sh",
        "# Create OpenPCDet's infos (custom_infos_train.pkl, custom_infos_val.pkl, custom_dbinfos_train.pkl,",
        "# gt_database/) for this export. Usage: sh create_infos.sh /path/to/OpenPCDet",
        "# OpenPCDet's create_custom_infos reads OpenPCDet/data/custom, so that path is linked to this folder.",
        "set -e",
        'OPENPCDET="${1:?usage: sh create_infos.sh /path/to/OpenPCDet}"',
        'if [ -e "$OPENPCDET/data/custom" ] && [ ! -L "$OPENPCDET/data/custom" ]; then',
        '  echo "$OPENPCDET/data/custom exists and is not a link; move it away first" >&2; exit 1',
        "fi",
        'mkdir -p "$OPENPCDET/data"',
        f'ln -sfn "{Path(out).resolve()}" "$OPENPCDET/data/custom"',
        f'cd "$OPENPCDET" && python -m pcdet.datasets.custom.custom_dataset create_custom_infos '
        f'"{Path(out).resolve() / EXPORT_YAML}"',
        "",
    ])


def export_openpcdet(root: str | os.PathLike, height: float | str, out: str | os.PathLike, *, frame: str = "ground",
                     class_map: ClassMap | str | Sequence[str] | None = None, overwrite: bool = False,
                     progress: bool = True) -> dict:
    """Write one height of the detbench dataset at `root` as an OpenPCDet custom folder at `out`.

    frame: "ground" (detbench's ego ground frame, road at z = 0) or "sensor" (the LiDAR's own
    frame, each frame's stored height and pitch; boxes stay upright, so a pitched sensor's box
    tilt is dropped). Points are written as `points/<id>.npy` (N, 4) float32, labels as
    `labels/<id>.txt` with single spaces, classes through `class_map` (default: every class ->
    Vehicle). The detbench train split becomes ImageSets/train.txt, the test split val.txt.
    Frames left without boxes (none in the data, or all dropped by the class map) are not
    written or listed: OpenPCDet's info generation cannot read an empty label file. Also
    writes custom_dataset.yaml, create_infos.sh and the manifest (JSON + Markdown). Returns
    the manifest dict.
    """
    from detbench.data.dataset import Height3Dataset

    if frame not in POINTS_FRAMES:
        raise ValueError(f"frame must be one of {', '.join(POINTS_FRAMES)}, got {frame!r}")
    cmap = class_map if isinstance(class_map, ClassMap) else parse_class_map(class_map, DEFAULT_EXPORT_CLASS_MAP)
    root, out = Path(root), Path(out)
    datasets = {s: Height3Dataset(root, height, s) for s in OPENPCDET_SPLITS}
    hk = datasets["train"].height_key
    removed = check_replaceable(out, overwrite, EXPORT_FOLDER, out="--out")
    recover_staged(out)
    # built beside `out` and swapped in whole when complete: a failed or killed export leaves `out` as it was
    with staged_folder(out) as dst:
        (dst / POINTS_DIR).mkdir()
        (dst / LABELS_DIR).mkdir()
        counts: dict = {}
        written: dict[str, list[str]] = {}
        empty: dict[str, list[str]] = {}
        out_classes: list[str] = []
        sensors_used: dict[tuple, int] = {}
        n_boxes = 0
        total = sum(len(d) for d in datasets.values())
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, desc="export", unit="frame")
        for split, ds in datasets.items():
            written[split], empty[split] = [], []
            for fid in ds.frame_ids:
                f = ds.load(fid)
                count_classes(f.classes, cmap, counts)
                keep, names = cmap.apply(f.classes)
                boxes = f.boxes[keep]
                if bar is not None:
                    bar.update(1)
                if len(boxes) == 0:
                    empty[split].append(fid)
                    continue
                points = f.points
                s = f.sensor
                sensors_used[(float(s.height), float(s.pitch_deg))] = sensors_used.get((float(s.height),
                                                                                        float(s.pitch_deg)), 0) + 1
                if frame == "sensor":
                    points = ground_to_sensor(points, s.height, s.pitch_deg)
                    boxes = boxes_ground_to_sensor(boxes, s.height, s.pitch_deg)
                pts = np.ascontiguousarray(points, dtype=np.float32)

                def saver(tmp: Path, arr=pts):
                    with open(tmp, "wb") as fh:
                        np.save(fh, arr, allow_pickle=False)

                atomic_save(dst / POINTS_DIR / f"{fid}.npy", saver)
                atomic_write_text(dst / LABELS_DIR / f"{fid}.txt", format_labels(boxes.astype(np.float32), names))
                for n in names:
                    if n not in out_classes:
                        out_classes.append(n)
                n_boxes += len(boxes)
                written[split].append(fid)
        if bar is not None:
            bar.close()
        for split, name in OPENPCDET_SPLITS.items():
            atomic_write_text(dst / IMAGESETS_DIR / f"{name}.txt", "".join(f + "\n" for f in written[split]))
        (s_h, s_p), _ = max(sensors_used.items(), key=lambda kv: kv[1]) if sensors_used else \
            ((float(datasets["train"].sensor.height), float(datasets["train"].sensor.pitch_deg)), 0)
        yaml_text = openpcdet_dataset_yaml(out.resolve(), out_classes or ["Vehicle"], frame, s_h, s_p,
                                           source=f"{root.resolve()} at {hk} m")
        atomic_write_text(dst / EXPORT_YAML, yaml_text)
        commands = openpcdet_commands(out, root, hk, frame)
        atomic_write_text(dst / EXPORT_SCRIPT, _create_infos_script(out, commands))
        notes = []
        if frame == "sensor" and any(p for (_, p) in sensors_used):
            notes.append(f"the sensor is pitched {s_p:g} deg: labels are upright boxes about the exact centre "
                         f"in its frame (their tilt by the pitch is dropped), and the road rises with x in this frame, "
                         f"beyond the 6 m z range far ahead; --frame ground avoids both")
        n_empty = sum(len(v) for v in empty.values())
        if n_empty:
            notes.append(f"{n_empty} frame(s) without boxes after the class map were left out "
                         f"(OpenPCDet's info generation cannot read an empty label file); OpenPCDet neither trains "
                         f"nor evaluates on them, and its predictions will lack them (detbench counts no false "
                         f"positives there)")
        for split, name in OPENPCDET_SPLITS.items():
            if not written[split]:
                notes.append(f"ImageSets/{name}.txt lists no frames: "
                             f"the detbench {split} split has no frame with boxes")
        manifest = {
            "format": "openpcdet-custom",
            "written_by": "detbench tools/export_openpcdet.py",
            "source": {"root": str(root.resolve()), "height": hk, "dataset_source": datasets["train"].info.source},
            "frame": frame,
            "frame_description": ("ego ground frame (origin on the road below the LiDAR; m)" if frame == "ground" else
                                  "the LiDAR's own frame (origin at the sensor; m): ground z = sensor z + height "
                                  "(pitch undone)"),
            "sensor": {"height_m": s_h, "pitch_deg": s_p,
                       "per_frame": [{"height_m": h, "pitch_deg": p, "frames": n}
                                     for (h, p), n in sensors_used.items()]},
            "class_map": cmap.spec,
            "classes": out_classes,
            "class_counts": counts,
            "map_class_to_kitti": {c: (c if c in KITTI_EVAL_CLASSES else "Car") for c in out_classes},
            "splits": {OPENPCDET_SPLITS[s]: {"from_detbench_split": s, "frames": len(written[s]),
                                             "frames_without_boxes_left_out": len(empty[s])} for s in OPENPCDET_SPLITS},
            "frames_without_boxes": {OPENPCDET_SPLITS[s]: empty[s] for s in OPENPCDET_SPLITS},
            "boxes": n_boxes,
            "point_cloud_range": openpcdet_point_cloud_range(frame, s_h),
            "files": {"yaml": EXPORT_YAML, "create_infos": EXPORT_SCRIPT, "markdown": EXPORT_MARKDOWN},
            "commands": commands,
            "notes": notes,
            "removed_from_earlier_export": removed,
        }
        atomic_write_text(dst / EXPORT_MARKDOWN, export_markdown(manifest))
        atomic_write_json(dst / EXPORT_MANIFEST, manifest)  # last: marks a finished export
    return manifest


def export_markdown(m: dict) -> str:
    """The manifest of an export as Markdown: what is where, in which frame, and the commands."""
    c = m["commands"]
    lines = [
        "# OpenPCDet custom dataset exported by detbench",
        "",
        f"Source: `{m['source']['root']}`, the {m['source']['height']} m LiDAR. Frame of points and labels: "
        f"**{m['frame']}** - {m['frame_description']}. Sensor: {m['sensor']['height_m']:g} m, pitch "
        f"{m['sensor']['pitch_deg']:g} deg.",
        "",
        "| OpenPCDet split | from detbench split | frames | frames without boxes left out |",
        "|---|---|---:|---:|",
        *[f"| ImageSets/{k}.txt | {v['from_detbench_split']} | {v['frames']} | {v['frames_without_boxes_left_out']} |"
          for k, v in m["splits"].items()],
        "",
        f"Classes (map `{m['class_map']}`): {', '.join(m['classes']) or '(none)'}; {m['boxes']} boxes in all. "
        f"Label lines per source class:",
        "",
        "| source class | kept | dropped | written as |",
        "|---|---:|---:|---|",
        *[f"| {k} | {v['kept']} | {v['dropped']} | {v['as'] or '-'} |" for k, v in sorted(m["class_counts"].items())],
        "",
        "MAP_CLASS_TO_KITTI: " + ", ".join(f"{k} -> {v}" for k, v in m["map_class_to_kitti"].items()) + ".",
        "",
        "## Into OpenPCDet",
        "",
        "```sh",
        "# OpenPCDet's create_custom_infos reads OPENPCDET/data/custom: link it to this folder",
        c["link"],
        c["create_infos"],
        "# (or: sh create_infos.sh OPENPCDET, which does both)",
        "```",
        "",
        f"Then use `{EXPORT_YAML}` as the dataset config (copy it over "
        "tools/cfgs/dataset_configs/custom_dataset.yaml or point the model config's `_BASE_CONFIG_` at it) and set "
        f"`CLASS_NAMES: {m['classes']}` in the model config. (OpenPCDet's create_custom_infos always reads "
        "OPENPCDET/data/custom, hence the link; it writes custom_infos_train.pkl, custom_infos_val.pkl, "
        "custom_dbinfos_train.pkl and gt_database/ into this folder.)",
        "",
        "## Predictions back into detbench",
        "",
        "`tools/test.py` of OpenPCDet writes `result.pkl`; evaluate it the Height3 paper's way with",
        "",
        "```sh",
        c["evaluate_in_detbench"],
        "```",
        "",
    ]
    if m["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in m["notes"]] + [""]
    return "\n".join(lines)


__all__ = [
    "ClassMap", "parse_class_map", "count_classes", "class_count_lines", "CLASS_MAP_PRESETS",
    "DEFAULT_EXPORT_CLASS_MAP", "DEFAULT_IMPORT_CLASS_MAP", "NON_VEHICLE_CLASSES", "KITTI_EVAL_CLASSES",
    "OPENPCDET_SPLITS", "road_surface_z", "level_road_z", "guess_points_frame", "frame_tolerance", "label_bottom_z",
    "export_openpcdet", "export_markdown", "openpcdet_dataset_yaml", "openpcdet_point_cloud_range",
    "openpcdet_commands", "EXPORT_MANIFEST", "EXPORT_YAML", "EXPORT_SCRIPT", "EXPORT_MARKDOWN",
]
