"""The detbench dataset layout on disk (docs/data-format.md is the user-facing description).

```
ROOT/
  dataset.json                  format, version, heights with their sensors, source, classes, split
  points/<height_key>/<id>.npy  (N, 4) float32 x y z intensity (or KITTI-style <id>.bin); a rig's
                                points under points/<rig name>/, ground frame, all its sensors merged
  sensor_index/<rig name>/<id>.npy  (N,) int16 the rig sensor of each point (rigs only)
  labels/<id>.txt               one vehicle a line: x y z dx dy dz heading class (ground frame)
  meta/<id>.json                per-frame extras: scene, timestamp, ego, track ids, lanes, sensors
  ImageSets/train.txt           frame ids, one a line
  ImageSets/test.txt
```

This module holds the names, the `DatasetInfo` read from dataset.json (validated, with
errors naming the file and key) and the split rule (by scene, never by frame).
"""
from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from detbench.config import shipped_default
from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.frame import DEFAULT_LANE_WIDTH, RIG_NAME, Sensor, height_key, is_rig_key
from detbench.utils.atomic import read_json
from detbench.utils.folder_ownership import FolderKind
from detbench.utils.untrusted import clip, excerpt, outside_folder

FORMAT_NAME = "detbench-height3"
FORMAT_VERSION = 1

INFO_FILE = "dataset.json"
POINTS_DIR = "points"
LABELS_DIR = "labels"
META_DIR = "meta"
IMAGESETS_DIR = "ImageSets"
SPLITS = ("train", "test")
SPLIT_CHOICES = ("train", "test", "all")

POINT_EXTS = (".npy", ".bin")
POINTS_FRAMES = ("ground", "sensor")
DEFAULT_CLASSES = ("car", "suv", "van", "taxi", "truck")

_FRAME_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")
# a frame id with its longest suffix (".json") fits the 255 bytes file systems allow a file name
MAX_FRAME_ID_CHARS = 200


def check_frame_id(frame_id: str, where: str = "") -> str:
    """Frame ids become file names: letters, digits, '_', '-', '.'; no path separators; at most
    MAX_FRAME_ID_CHARS characters."""
    if not isinstance(frame_id, str) or not _FRAME_ID_RE.match(frame_id) or frame_id in (".", ".."):
        raise DatasetError(
            f"invalid frame id {excerpt(frame_id)}: use letters, digits, '_', '-' and '.' only "
            f"(it becomes a file name), e.g. '0003_017'", path=where or None)
    if len(frame_id) > MAX_FRAME_ID_CHARS:
        raise DatasetError(
            f"frame id {excerpt(frame_id)} is longer than {MAX_FRAME_ID_CHARS} characters; it becomes a file "
            f"name, which file systems keep under 255 bytes; shorten it (e.g. '0003_017')", path=where or None)
    return frame_id


def points_path(root: str | os.PathLike, height: float | str, frame_id: str, ext: str = ".npy") -> Path:
    """ROOT/points/<height_key>/<frame_id><ext>."""
    hk = height if isinstance(height, str) else height_key(height)
    return Path(root) / POINTS_DIR / hk / f"{frame_id}{ext}"


def sensor_index_path(root: str | os.PathLike, rig: str, frame_id: str) -> Path:
    """ROOT/sensor_index/<rig name>/<frame_id>.npy: the rig sensor of each point of points/<rig name>/<frame_id>."""
    return Path(root) / "sensor_index" / rig / f"{frame_id}.npy"


def label_path(root: str | os.PathLike, frame_id: str) -> Path:
    """ROOT/labels/<frame_id>.txt (shared by every height)."""
    return Path(root) / LABELS_DIR / f"{frame_id}.txt"


def meta_path(root: str | os.PathLike, frame_id: str) -> Path:
    """ROOT/meta/<frame_id>.json (per-frame extras)."""
    return Path(root) / META_DIR / f"{frame_id}.json"


def imageset_path(root: str | os.PathLike, split: str) -> Path:
    """ROOT/ImageSets/<split>.txt."""
    return Path(root) / IMAGESETS_DIR / f"{split}.txt"


# --------------------------------------------------------------------------- dataset.json

@dataclass
class HeightInfo:
    """What dataset.json says about one mounting height."""

    key: str  # "0.5", "1.0", "1.8"
    sensor: Sensor
    points_frame: str = "ground"  # "ground" (ego ground frame) or "sensor" (converted on load)
    points_ext: str = ".npy"  # ".npy" or ".bin"
    bin_columns: int = 4  # float32 values per point in .bin files (first 4 are x y z intensity)
    rig: dict | None = None  # a rig's key (its name): the rig (detbench.sim.rigs.Rig.describe); sensor is its first

    def to_dict(self) -> dict:
        d = {"sensor": self.sensor.to_dict(), "points_frame": self.points_frame,
             "points_ext": self.points_ext, "bin_columns": self.bin_columns}
        if self.rig is not None:
            d["rig"] = self.rig
        return d


@dataclass
class SceneRule:
    """How frame ids map to scenes when no meta file names the scene.

    kind "prefix": the scene is the frame id up to the last `sep` ("0003_017" -> "0003");
    kind "block": frame ids sorted, every `frames_per_scene` consecutive ids are one scene
        (default: configs/default.yaml `data.frames_per_scene`);
    kind "frame": every frame is its own scene (only for data with no time structure).
    """

    kind: str = "prefix"
    sep: str = "_"
    frames_per_scene: int = field(default_factory=lambda: shipped_default("data.frames_per_scene"))

    def to_dict(self) -> dict:
        if self.kind == "prefix":
            return {"kind": "prefix", "sep": self.sep}
        if self.kind == "block":
            return {"kind": "block", "frames_per_scene": self.frames_per_scene}
        return {"kind": self.kind}

    def scenes(self, frame_ids: list[str]) -> dict[str, str]:
        """frame id -> scene id for every id in `frame_ids`."""
        if self.kind == "prefix":
            return {f: (f.rsplit(self.sep, 1)[0] if self.sep in f else f) for f in frame_ids}
        if self.kind == "block":
            order = sorted(frame_ids)
            return {f: f"block{i // self.frames_per_scene:04d}" for i, f in enumerate(order)}
        return {f: f for f in frame_ids}


@dataclass
class DatasetInfo:
    """The parsed, validated content of ROOT/dataset.json."""

    heights: dict[str, HeightInfo]  # by height key, in file order
    source: dict = field(default_factory=dict)
    classes: list[str] = field(default_factory=lambda: list(DEFAULT_CLASSES))
    split: dict = field(default_factory=dict)
    has_meta: bool = True
    lane_width: float = DEFAULT_LANE_WIDTH  # metres, for lanes derived from y without meta
    scene_rule: SceneRule = field(default_factory=SceneRule)
    num_frames: int | None = None
    format: str = FORMAT_NAME
    version: int = FORMAT_VERSION

    def to_dict(self) -> dict:
        return {
            "format": self.format,
            "version": self.version,
            "num_frames": self.num_frames,
            "heights": {k: h.to_dict() for k, h in self.heights.items()},
            "classes": list(self.classes),
            "has_meta": self.has_meta,
            "lane_width": self.lane_width,
            "scene_rule": self.scene_rule.to_dict(),
            "split": self.split,
            "source": self.source,
        }

    def height(self, height: float | str, path: str | os.PathLike = "") -> HeightInfo:
        """The HeightInfo of `height` (metres or key); unknown heights list the available ones."""
        try:
            key = height if isinstance(height, str) and height in self.heights else height_key(float(height))
        except (TypeError, ValueError) as e:
            raise DatasetError(f"height {height!r} is not a mounting height ({e}); give one of the dataset's "
                               f"heights: {', '.join(self.heights) or '(none)'} (metres)", path=path or None) from None
        if key not in self.heights:
            raise DatasetError(
                f"no height {key} m in this dataset; available heights: "
                f"{', '.join(self.heights) or '(none)'} (pick one of them, or simulate {key} m "
                f"with tools/simulate.py --heights {key})", path=path or None)
        return self.heights[key]


def _need(d: dict, key: str, typ, path: Path, where: str):
    if key not in d:
        raise DatasetError(f"missing key {where}{key!r}; see docs/data-format.md for the schema", path=path)
    val = d[key]
    if not isinstance(val, typ) or (typ is not bool and isinstance(val, bool)):
        raise DatasetError(f"key {where}{key!r} must be {getattr(typ, '__name__', typ)}, got "
                           f"{type(val).__name__} {excerpt(val)}", path=path)
    return val


def parse_info(d: dict, path: str | os.PathLike = INFO_FILE) -> DatasetInfo:
    """Validate a dataset.json dict and build a DatasetInfo (errors name `path` and the key)."""
    path = Path(path)
    if not isinstance(d, dict):
        raise DatasetError("dataset.json must hold a JSON object", path=path)
    fmt = d.get("format", FORMAT_NAME)
    if fmt != FORMAT_NAME:
        raise DatasetError(f"format {excerpt(fmt)} is not {FORMAT_NAME!r}; convert the data first "
                           f"(python -m detbench.data.convert --help)", path=path)
    version = d.get("version", FORMAT_VERSION)
    if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
        raise DatasetError(f"format version {excerpt(version)} is not supported (this detbench reads "
                           f"version 1..{FORMAT_VERSION}); upgrade detbench or re-create the dataset", path=path)
    raw_heights = _need(d, "heights", dict, path, "")
    if not raw_heights:
        raise DatasetError("'heights' is empty; list at least one height, e.g. {\"1.8\": {\"sensor\": {...}}}",
                           path=path)
    heights: dict[str, HeightInfo] = {}
    for key, h in raw_heights.items():
        where = f"heights.{key}."
        rig = h.get("rig") if isinstance(h, dict) else None
        if is_rig_key(key):
            if not RIG_NAME.fullmatch(key) or not isinstance(rig, dict):
                raise DatasetError(f"height key {excerpt(key)} is not a positive number of metres (e.g. \"1.8\") nor a "
                                   f"rig name with a 'rig' object (docs/rigs.md)", path=path)
        else:
            try:
                canon = height_key(float(key))
            except ValueError:
                canon = None
            if canon is None:
                raise DatasetError(f"height key {excerpt(key)} is not a positive number of metres (e.g. \"1.8\")",
                                   path=path)
            if canon != key:
                raise DatasetError(f"height key {excerpt(key)} must be written {canon!r} (the folder name under "
                                   f"points/)", path=path)
        if not isinstance(h, dict):
            raise DatasetError(f"heights.{key} must be an object with at least a 'sensor'", path=path)
        sensor_d = _need(h, "sensor", dict, path, where)
        try:
            sensor = Sensor.from_dict(sensor_d)
        except (TypeError, ValueError) as e:
            raise DatasetError(f"{where}sensor is invalid: {clip(e)}", path=path) from None
        if rig is None and abs(float(sensor.height) - float(key)) > 1e-6:
            raise DatasetError(f"{where}sensor.height is {sensor.height} but the key says {key} m; make them agree",
                               path=path)
        if rig is not None and h.get("points_frame", "ground") != "ground":
            raise DatasetError(f"{where}points_frame must be 'ground' for a rig (its sensors' points are merged in "
                               f"the ego frame)", path=path)
        pf = h.get("points_frame", "ground")
        if pf not in POINTS_FRAMES:
            raise DatasetError(f"{where}points_frame is {excerpt(pf)}; use one of {', '.join(POINTS_FRAMES)}",
                               path=path)
        ext = h.get("points_ext", ".npy")
        if ext not in POINT_EXTS:
            raise DatasetError(f"{where}points_ext is {excerpt(ext)}; use one of {', '.join(POINT_EXTS)}", path=path)
        cols = h.get("bin_columns", 4)
        if not isinstance(cols, int) or isinstance(cols, bool) or cols < 4:
            raise DatasetError(f"{where}bin_columns is {excerpt(cols)}; it must be an integer >= 4 "
                               f"(x y z intensity, then any extra columns)", path=path)
        heights[key] = HeightInfo(key=key, sensor=sensor, points_frame=pf, points_ext=ext, bin_columns=cols, rig=rig)
    classes = d.get("classes", list(DEFAULT_CLASSES))
    if not isinstance(classes, list) or not all(isinstance(c, str) and c and " " not in c for c in classes):
        raise DatasetError("'classes' must be a list of class names without spaces", path=path)
    lane_width = d.get("lane_width", DEFAULT_LANE_WIDTH)
    if not isinstance(lane_width, (int, float)) or isinstance(lane_width, bool) or not lane_width > 0 \
            or not math.isfinite(lane_width):
        raise DatasetError(f"'lane_width' must be a positive number of metres, got {excerpt(lane_width)}", path=path)
    has_meta = d.get("has_meta", True)
    if not isinstance(has_meta, bool):
        raise DatasetError(f"'has_meta' must be true or false, got {excerpt(has_meta)}", path=path)
    sr = d.get("scene_rule", {"kind": "prefix", "sep": "_"})
    if not isinstance(sr, dict) or sr.get("kind") not in ("prefix", "block", "frame"):
        raise DatasetError("'scene_rule' must be {\"kind\": \"prefix\", \"sep\": \"_\"}, "
                           "{\"kind\": \"block\", \"frames_per_scene\": 200} or {\"kind\": \"frame\"}", path=path)
    rule = SceneRule(kind=sr["kind"])
    if rule.kind == "prefix":
        rule.sep = sr.get("sep", "_")
        if not isinstance(rule.sep, str) or not rule.sep:
            raise DatasetError("'scene_rule.sep' must be a non-empty string", path=path)
    elif rule.kind == "block":
        fps = sr.get("frames_per_scene")
        if not isinstance(fps, int) or isinstance(fps, bool) or fps < 1:
            raise DatasetError(f"'scene_rule.frames_per_scene' must be a positive integer, got {excerpt(fps)}",
                               path=path)
        rule.frames_per_scene = fps
    source = d.get("source", {})
    split = d.get("split", {})
    if not isinstance(source, dict) or not isinstance(split, dict):
        raise DatasetError("'source' and 'split' must be JSON objects", path=path)
    num_frames = d.get("num_frames")
    return DatasetInfo(heights=heights, source=source, classes=list(classes), split=split, has_meta=has_meta,
                       lane_width=float(lane_width), scene_rule=rule, num_frames=num_frames,
                       format=fmt, version=version)


def is_openpcdet_custom_folder(root: str | os.PathLike) -> bool:
    """True for a folder in OpenPCDet's custom layout: point files directly in points/ (not in
    points/<height>/ as detbench keeps them) and a labels/ folder."""
    root = Path(root)
    pts = root / POINTS_DIR
    if not (pts.is_dir() and (root / LABELS_DIR).is_dir()):
        return False
    return any(p.suffix in POINT_EXTS and p.is_file() for p in pts.iterdir())


def openpcdet_folder_hint(root: str | os.PathLike) -> str:
    """What to tell a user who gives a detbench tool an OpenPCDet custom folder: the command converting it."""
    root = Path(root)
    msg = (f"{root} is an OpenPCDet custom folder (points/<id>.npy and labels/<id>.txt of one LiDAR), not a "
           f"detbench dataset; convert it first: python -m detbench.data.convert --src HEIGHT={root} "
           f"--out {root.resolve().parent / (root.resolve().name + '_detbench')} "
           f"(HEIGHT: that LiDAR's mounting height in metres, e.g. 1.8; "
           f"one --src per height), then give the tool the --out folder")
    manifest = root / "detbench_export.json"
    if manifest.is_file():
        try:
            src = read_json(manifest).get("source", {})
            msg += (f". This folder was exported by detbench from {src['root']} ({src['height']} m): give that "
                    f"dataset to detbench's tools instead")
        except (ValueError, KeyError, TypeError, AttributeError):
            pass
    return msg


def read_info(root: str | os.PathLike) -> DatasetInfo:
    """Read and validate ROOT/dataset.json."""
    root = Path(root)
    if not root.is_dir():
        raise MissingFileError("dataset folder not found; check the path (create one with tools/simulate.py "
                               "--out ROOT, or convert data with python -m detbench.data.convert)", path=root)
    path = root / INFO_FILE
    if not path.is_file():
        if is_openpcdet_custom_folder(root):
            raise MissingFileError(f"dataset.json not found: {openpcdet_folder_hint(root)}", path=path)
        hint = ("a writer did not finish (re-run it)" if (root / POINTS_DIR).is_dir()
                else "this is not a detbench dataset (create one with tools/simulate.py, or convert "
                     "OpenPCDet-style data with python -m detbench.data.convert)")
        raise MissingFileError(f"dataset.json not found: {hint}", path=path)
    target = outside_folder(path, root)
    if target is not None:
        raise DatasetError(f"a link to {target}, outside {root}; detbench reads only the files inside the folder "
                           f"it is given (a link out of it could expose any file); copy the file into the folder",
                           path=path)
    try:
        d = read_json(path)
    except ValueError as e:
        raise DatasetError(str(e).split(": ", 1)[-1], path=path) from None
    return parse_info(d, path)


# --------------------------------------------------------------------------- split by scene

def split_scenes(scene_ids: list[str], test_fraction: float | None = None) -> tuple[list[str], list[str]]:
    """Deterministic split of scenes into (train, test), never cutting a scene.

    Scenes are taken in sorted order; n_test = round(S * test_fraction) (at least 1 when the
    fraction is positive, at most S - 1) scenes evenly spread over that order go to test:
    positions floor((i + 1) * S / n_test) - 1 for i < n_test (with 1/3 that is every third
    scene). The rule needs no seed, so adding frames to a scene never moves it across splits.
    A single scene cannot be split this way: it is returned as train only (see
    `assign_splits` for the time-block rule used then). `test_fraction` None: configs/default.yaml
    `data.test_fraction`.
    """
    test_fraction = shipped_default("data.test_fraction", test_fraction)
    if not 0.0 <= test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    scenes = sorted(set(scene_ids))
    s = len(scenes)
    if s < 2 or test_fraction == 0.0:
        return scenes, []
    n_test = min(max(1, round(s * test_fraction)), s - 1)
    test_pos = {(i + 1) * s // n_test - 1 for i in range(n_test)}
    train = [sc for i, sc in enumerate(scenes) if i not in test_pos]
    test = [sc for i, sc in enumerate(scenes) if i in test_pos]
    return train, test


def assign_splits(frame_ids: list[str], scene_of: dict[str, str], test_fraction: float | None = None
                  ) -> tuple[list[str], list[str], dict]:
    """Split frames by scene: returns (train_ids, test_ids, rule_description).

    Frame order is kept. With two or more scenes the split follows `split_scenes`. With a
    single scene and test_fraction > 0 a UserWarning is issued and the scene is cut in time
    instead: its last ceil(n * test_fraction) frames (in id order) go to test, the rest to
    train, so the two splits only touch at one boundary. The returned rule says which
    case applied. `test_fraction` None: configs/default.yaml `data.test_fraction`.
    """
    test_fraction = shipped_default("data.test_fraction", test_fraction)
    scenes = [scene_of[f] for f in frame_ids]
    train_sc, test_sc = split_scenes(scenes, test_fraction)
    if len(train_sc) == 1 and not test_sc and test_fraction > 0 and len(frame_ids) >= 2:
        warnings.warn(
            f"the dataset has a single scene ({train_sc[0]!r}); it cannot be split by scene, so its "
            f"last {test_fraction:.0%} of frames form the test split (a time-block split; frames near the "
            f"boundary are nearly identical). Simulate several scenes for an honest split.", UserWarning,
            stacklevel=3)
        order = sorted(frame_ids)
        n_test = max(1, math.ceil(len(order) * test_fraction))
        n_test = min(n_test, len(order) - 1)
        test_set = set(order[len(order) - n_test:])
        train = [f for f in frame_ids if f not in test_set]
        test = [f for f in frame_ids if f in test_set]
        rule = {"rule": "time-block", "reason": "single scene", "test_fraction": test_fraction,
                "train_scenes": train_sc, "test_scenes": train_sc}
        return train, test, rule
    test_set = set(test_sc)
    train = [f for f in frame_ids if scene_of[f] not in test_set]
    test = [f for f in frame_ids if scene_of[f] in test_set]
    rule = {"rule": "by-scene", "description": "scenes in sorted order; n_test = round(S * test_fraction) "
                                               "scenes evenly spread (positions floor((i+1)*S/n_test)-1) go to test",
            "test_fraction": test_fraction, "train_scenes": train_sc, "test_scenes": test_sc}
    return train, test, rule


# what a dataset folder may hold: the layout, the side files written into it by detbench (the ground-truth
# database, the simulator's and the converter's reports) and temporary files of atomic writes
DATASET_ENTRIES = (INFO_FILE, POINTS_DIR, LABELS_DIR, META_DIR, IMAGESETS_DIR, "gt_database", "simulate_run.json",
                   "simulate_run.md", "convert_report.json", "convert_report.md")


# a dataset folder as a writer replaces it (`detbench.utils.folder_ownership.check_replaceable`): whole, with the user's
# own files refused, and an unfinished one (no dataset.json) replaceable too when its owner file says it is
# a dataset (an OpenPCDet folder has the same points/, labels/ and ImageSets/)
DATASET_FOLDER = FolderKind(name="a dataset", marker=INFO_FILE, entries=DATASET_ENTRIES, foreign="part of a dataset",
                            unfinished="an unfinished dataset", key="dataset")


# The simulator calibration a dataset was made with, from its dataset.json `source` (the data layer reads it;
# the simulator writes it).
PREVIOUS_CALIBRATION = "v1"  # what a config or dataset.json without a `calibration` key was made with


def calibration_id(label: str) -> str:
    """The calibration id of a label: its first word ("v2"). Some datasets carry the id followed by a note in
    parentheses ("v2 (...)"); they read as the bare id, so every dataset of one calibration compares equal."""
    text = str(label).strip()
    return text.split(" (", 1)[0].strip() or text


def sim_calibration(info: dict) -> str:
    """The simulator calibration a config or a dataset.json `source` was made with: its
    `calibration` (or its config's) as a bare id (`calibration_id`), and "v1" when neither says,
    since a simulator config without the key is calibration v1's."""
    if not isinstance(info, dict):
        return PREVIOUS_CALIBRATION
    if info.get("calibration"):
        return calibration_id(info["calibration"])
    cfg = info.get("config")
    if isinstance(cfg, dict) and cfg.get("calibration"):
        return calibration_id(cfg["calibration"])
    return PREVIOUS_CALIBRATION


_SCENE_IDENTITY = ("kind", "preset", "calibration", "seed", "overrides")  # what draws a simulated dataset's scenes


def scene_identity(source: dict) -> dict:
    """What draws a simulated dataset's scenes, from its dataset.json `source`: simulator preset, calibration,
    seed and overrides (and the kind of source)."""
    return {k: source.get(k) for k in _SCENE_IDENTITY}


def same_scenes(source: dict | None, other: dict | None) -> bool | None:
    """Whether two datasets' frames with one id hold one scene, from their dataset.json `source`: True for two
    simulations with the same simulator preset, calibration, seed and overrides (detbench.sim seeds each scene by
    (seed, scene), so frame 0001_000 is one traffic state in both however each is split); False for two
    simulations that differ in any of them (their ids name other scenes); None when either is not simulated or
    does not say (real data: ids alone cannot tell)."""
    a, b = source or {}, other or {}
    if a.get("kind") != "simulator" or b.get("kind") != "simulator":
        return None
    return scene_identity(a) == scene_identity(b)
