"""One height of a detbench dataset written as an OpenPCDet custom folder (tools/export_openpcdet.py).

`export_openpcdet` writes the frames (`export_frames`: points and labels in the ground frame or each
LiDAR's own frame, classes through a class map, frames left without boxes left out, since
OpenPCDet's info generation cannot read an empty label file), ImageSets/train.txt and val.txt, a
custom_dataset.yaml for OpenPCDet (`openpcdet_dataset_yaml`), create_infos.sh and a manifest
(detbench_export.json, and `export_markdown` of it) with the commands into OpenPCDet and back.
What the format requires is in detbench.data.openpcdet's docstring.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from detbench.data.frame import is_rig_key
from detbench.data.layout import IMAGESETS_DIR, LABELS_DIR, POINTS_DIR, POINTS_FRAMES
from detbench.data.openpcdet import (
    DEFAULT_EXPORT_CLASS_MAP, KITTI_EVAL_CLASSES, OPENPCDET_SPLITS, ClassMap, count_classes, parse_class_map,
)
from detbench.data.readers import format_labels
from detbench.data.transforms import boxes_ground_to_sensor, ground_to_sensor
from detbench.utils.atomic import atomic_save, atomic_write_json, atomic_write_text
from detbench.utils.folder_ownership import check_replaceable, FolderKind
from detbench.utils.staged_folders import recover_staged, staged_folder

EXPORT_MANIFEST = "detbench_export.json"
EXPORT_MARKDOWN = "detbench_export.md"
EXPORT_YAML = "custom_dataset.yaml"
EXPORT_SCRIPT = "create_infos.sh"
# what OpenPCDet's create_custom_infos writes into the data folder (removed by --overwrite)
_OPENPCDET_GENERATED = ("custom_infos_train.pkl", "custom_infos_val.pkl", "custom_dbinfos_train.pkl", "gt_database")


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


@dataclass
class ExportedFrames:
    """What writing an export's frames did, per detbench split (train, test)."""

    written: dict[str, list[str]]  # frame ids written and listed in ImageSets
    empty: dict[str, list[str]]  # frame ids left out: no box after the class map
    class_counts: dict  # `count_classes` of every label line read
    classes: list[str]  # the written class names, in order of first appearance
    sensors: dict[tuple[float, float], int]  # (height m, pitch deg) -> frames written with that sensor
    boxes: int  # boxes written

    def main_sensor(self, fallback: tuple[float, float]) -> tuple[float, float]:
        """(height m, pitch deg) of most written frames (the first such on a tie); `fallback` when none was
        written."""
        return max(self.sensors.items(), key=lambda kv: kv[1])[0] if self.sensors else fallback


def _save_points(path: Path, points: np.ndarray) -> None:
    arr = np.ascontiguousarray(points, dtype=np.float32)

    def saver(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.save(fh, arr, allow_pickle=False)

    atomic_save(path, saver)


def export_frames(datasets: dict, dst: Path, cmap: ClassMap, frame: str, progress: bool) -> ExportedFrames:
    """Write every frame of `datasets` ({detbench split: Height3Dataset}) that keeps a box after `cmap` into
    `dst`'s points/ and labels/, in the `frame` ("ground" or "sensor") of each frame's own sensor."""
    (dst / POINTS_DIR).mkdir()
    (dst / LABELS_DIR).mkdir()
    done = ExportedFrames(written={}, empty={}, class_counts={}, classes=[], sensors={}, boxes=0)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(len(d) for d in datasets.values()), desc="export", unit="frame")
    for split, ds in datasets.items():
        done.written[split], done.empty[split] = [], []
        for fid in ds.frame_ids:
            f = ds.load(fid)
            count_classes(f.classes, cmap, done.class_counts)
            keep, names = cmap.apply(f.classes)
            boxes = f.boxes[keep]
            if bar is not None:
                bar.update(1)
            if len(boxes) == 0:
                done.empty[split].append(fid)
                continue
            points, s = f.points, f.sensor
            key = (float(s.height), float(s.pitch_deg))
            done.sensors[key] = done.sensors.get(key, 0) + 1
            if frame == "sensor":
                points = ground_to_sensor(points, s.height, s.pitch_deg)
                boxes = boxes_ground_to_sensor(boxes, s.height, s.pitch_deg)
            _save_points(dst / POINTS_DIR / f"{fid}.npy", points)
            atomic_write_text(dst / LABELS_DIR / f"{fid}.txt", format_labels(boxes.astype(np.float32), names))
            done.classes += [n for n in dict.fromkeys(names) if n not in done.classes]
            done.boxes += len(boxes)
            done.written[split].append(fid)
    if bar is not None:
        bar.close()
    return done


def export_notes(frame: str, done: ExportedFrames, pitch_deg: float) -> list[str]:
    """What a user of the export must know: a pitched sensor's frame, frames left out, an empty split list."""
    notes = []
    if frame == "sensor" and any(p for (_, p) in done.sensors):
        notes.append(f"the sensor is pitched {pitch_deg:g} deg: labels are upright boxes about the exact centre "
                     f"in its frame (their tilt by the pitch is dropped), and the road rises with x in this frame, "
                     f"beyond the 6 m z range far ahead; --frame ground avoids both")
    n_empty = sum(len(v) for v in done.empty.values())
    if n_empty:
        notes.append(f"{n_empty} frame(s) without boxes after the class map were left out "
                     f"(OpenPCDet's info generation cannot read an empty label file); OpenPCDet neither trains "
                     f"nor evaluates on them, and its predictions will lack them (detbench counts no false "
                     f"positives there)")
    for split, name in OPENPCDET_SPLITS.items():
        if not done.written[split]:
            notes.append(f"ImageSets/{name}.txt lists no frames: the detbench {split} split has no frame with boxes")
    return notes


def export_manifest(source: dict, frame: str, sensor: tuple[float, float], cmap: ClassMap, done: ExportedFrames,
                    commands: dict, notes: list[str], removed: list) -> dict:
    """The manifest of an export (detbench_export.json): `source` {root, height, dataset_source}, the frame and
    sensor (height m, pitch deg) written, the classes, splits, files and commands."""
    s_h, s_p = sensor
    return {
        "format": "openpcdet-custom",
        "written_by": "detbench tools/export_openpcdet.py",
        "source": source,
        "frame": frame,
        "frame_description": ("ego ground frame (origin on the road below the LiDAR; m)" if frame == "ground" else
                              "the LiDAR's own frame (origin at the sensor; m): ground z = sensor z + height "
                              "(pitch undone)"),
        "sensor": {"height_m": s_h, "pitch_deg": s_p,
                   "per_frame": [{"height_m": h, "pitch_deg": p, "frames": n} for (h, p), n in done.sensors.items()]},
        "class_map": cmap.spec,
        "classes": done.classes,
        "class_counts": done.class_counts,
        "map_class_to_kitti": {c: (c if c in KITTI_EVAL_CLASSES else "Car") for c in done.classes},
        "splits": {OPENPCDET_SPLITS[s]: {"from_detbench_split": s, "frames": len(done.written[s]),
                                         "frames_without_boxes_left_out": len(done.empty[s])}
                   for s in OPENPCDET_SPLITS},
        "frames_without_boxes": {OPENPCDET_SPLITS[s]: done.empty[s] for s in OPENPCDET_SPLITS},
        "boxes": done.boxes,
        "point_cloud_range": openpcdet_point_cloud_range(frame, s_h),
        "files": {"yaml": EXPORT_YAML, "create_infos": EXPORT_SCRIPT, "markdown": EXPORT_MARKDOWN},
        "commands": commands,
        "notes": notes,
        "removed_from_earlier_export": removed,
    }


def export_openpcdet(root: str | os.PathLike, height: float | str, out: str | os.PathLike, *, frame: str = "ground",
                     class_map: ClassMap | str | Sequence[str] | None = None, overwrite: bool = False,
                     progress: bool = True) -> dict:
    """Write one height (or rig, by name) of the detbench dataset at `root` as an OpenPCDet custom folder at `out`.

    frame: "ground" (detbench's ego ground frame, road at z = 0) or "sensor" (the LiDAR's own
    frame, each frame's stored height and pitch; boxes stay upright, so a pitched sensor's box
    tilt is dropped; a rig, whose sensors merge in the ground frame, has none: ValueError). Points are
    written as `points/<id>.npy` (N, 4) float32, labels as
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
    if frame == "sensor" and datasets["train"].height_info.rig is not None:
        raise ValueError(f"--frame sensor: the rig {hk!r} merges its sensors' points in the ego ground frame, so "
                         f"there is no one sensor frame to write them in; export it with --frame ground")
    removed = check_replaceable(out, overwrite, EXPORT_FOLDER, out="--out")
    recover_staged(out)
    # built beside `out` and swapped in whole when complete: a failed or killed export leaves `out` as it was
    with staged_folder(out, what="an OpenPCDet export",
                       check=lambda: check_replaceable(out, overwrite, EXPORT_FOLDER, out="--out")) as dst:
        done = export_frames(datasets, dst, cmap, frame, progress)
        for split, name in OPENPCDET_SPLITS.items():
            atomic_write_text(dst / IMAGESETS_DIR / f"{name}.txt", "".join(f + "\n" for f in done.written[split]))
        sensor = datasets["train"].sensor
        s_h, s_p = done.main_sensor((float(sensor.height), float(sensor.pitch_deg)))
        atomic_write_text(dst / EXPORT_YAML, openpcdet_dataset_yaml(out.resolve(), done.classes or ["Vehicle"], frame,
                                                                    s_h, s_p, source=f"{root.resolve()} {_at(hk)}"))
        commands = openpcdet_commands(out, root, hk, frame)
        atomic_write_text(dst / EXPORT_SCRIPT, _create_infos_script(out, commands))
        source = {"root": str(root.resolve()), "height": hk, "dataset_source": datasets["train"].info.source}
        manifest = export_manifest(source, frame, (s_h, s_p), cmap, done, commands,
                                   export_notes(frame, done, s_p), removed)
        atomic_write_text(dst / EXPORT_MARKDOWN, export_markdown(manifest))
        atomic_write_json(dst / EXPORT_MANIFEST, manifest)  # last: marks a finished export
    return manifest


def _at(key: str) -> str:
    """"at 1.8 m" for a height's key, "rig headlights" for a rig's."""
    return f"rig {key}" if is_rig_key(key) else f"at {key} m"


def _lidar(key: str) -> str:
    """"the 1.8 m LiDAR" for a height's key, "the rig headlights" for a rig's."""
    return f"the rig {key}" if is_rig_key(key) else f"the {key} m LiDAR"


def export_markdown(m: dict) -> str:
    """The manifest of an export as Markdown: what is where, in which frame, and the commands."""
    c = m["commands"]
    lines = [
        "# OpenPCDet custom dataset exported by detbench",
        "",
        f"Source: `{m['source']['root']}`, {_lidar(m['source']['height'])}. Frame of points and labels: "
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
    "EXPORT_FOLDER", "EXPORT_MANIFEST", "EXPORT_MARKDOWN", "EXPORT_SCRIPT", "EXPORT_YAML", "ExportedFrames",
    "export_frames", "export_manifest", "export_markdown", "export_notes", "export_openpcdet", "openpcdet_commands",
    "openpcdet_dataset_yaml", "openpcdet_point_cloud_range",
]
