"""`Height3Dataset`: the frames of one mounting height and one split, read and validated.

```python
ds = Height3Dataset("data/sim", height=1.8, split="train")
len(ds), ds.frame_ids[:3], ds.heights, ds.sensor
frame = ds[0]            # Frame, points in the ego ground frame, validated
for frame in ds: ...
```
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from collections.abc import Iterator

import numpy as np

from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.frame import Frame, Sensor, height_key, is_rig_key, lanes_from_lateral
from detbench.data.layout import (
    INFO_FILE, SPLIT_CHOICES, DatasetInfo, HeightInfo, imageset_path, label_path, meta_path, points_path,
    read_info,
)
from detbench.data.readers import check_inside, read_imageset, read_labels, read_meta, read_points
from detbench.data.transforms import sensor_to_ground
from detbench.utils.untrusted import excerpt


def split_ids(root: str | os.PathLike, split: str) -> list[str]:
    """Frame ids of `split` ("train", "test" or "all" = both, sorted) under ROOT/ImageSets.

    An id listed in both train.txt and test.txt is an error (the split would leak).
    """
    if split not in SPLIT_CHOICES:
        raise ValueError(f"unknown split {split!r}; use one of {', '.join(SPLIT_CHOICES)}")
    if split != "all":
        return read_imageset(imageset_path(root, split), root=root)
    train = read_imageset(imageset_path(root, "train"), root=root)
    test = read_imageset(imageset_path(root, "test"), root=root)
    both = set(train) & set(test)
    if both:
        first = sorted(both)[0]
        raise DatasetError(f"{len(both)} frame id(s) are in both train.txt and test.txt (e.g. {first!r}); "
                           f"a frame belongs to one split - remove it from one list",
                           path=imageset_path(root, "test"))
    return sorted(train + test)


def check_frame_count(root: Path, info: DatasetInfo, all_ids: list[str]) -> None:
    """DatasetError when dataset.json's `num_frames` is not the frames its ImageSets list (with those its
    `split.dropped` rule left out of both splits): a report would state the wrong count."""
    n = info.num_frames
    if n is None:
        return
    dropped = (info.split.get("dropped") or {}).get("frames", 0) if isinstance(info.split, dict) else 0
    dropped = dropped if isinstance(dropped, int) and not isinstance(dropped, bool) else 0
    want = len(all_ids) + dropped
    if not isinstance(n, int) or isinstance(n, bool) or n != want:
        more = f" and {dropped} frame(s) its split.dropped rule left out" if dropped else ""
        raise DatasetError(f"'num_frames' is {excerpt(n)}, but ImageSets list {len(all_ids)} frame(s){more}; set "
                           f"num_frames to {want} in dataset.json (or re-create the dataset)",
                           path=Path(root) / INFO_FILE)


class Height3Dataset:
    """Frames of one height and split of a dataset in the detbench layout (docs/data-format.md).

    Args:
        root: dataset folder (holds dataset.json).
        height: mounting height in metres (or its key "1.8"), or a rig's name; must be one of `heights`.
        split: "train", "test" or "all".
        lane_width: metres, for datasets without meta files (lanes from the lateral offset);
            default: dataset.json's lane_width (3.5 m).
        check_files: check at construction that every listed frame has its files (cheap
            stat calls); a missing file otherwise surfaces when that frame is read.

    `ds[i]` returns a validated `Frame` (points (N, 4) float32 in the ego ground frame,
    sensor-frame data converted with the stored height and pitch). Any malformed file
    raises `DatasetError` naming the file (and line).
    """

    def __init__(self, root: str | os.PathLike, height: float | str, split: str = "train", *,
                 lane_width: float | None = None, check_files: bool = True):
        self.root = Path(root)
        self.info: DatasetInfo = read_info(self.root)
        self.height_info: HeightInfo = self.info.height(height, self.root / INFO_FILE)
        self.height_key = self.height_info.key
        # metres; a rig's key is its name, and its height that of its first sensor
        self.height = float(self.height_key) if self.height_info.rig is None else float(self.height_info.sensor.height)
        self.split = split
        self.lane_width = float(lane_width) if lane_width is not None else self.info.lane_width
        if not self.lane_width > 0:
            raise ValueError(f"lane_width must be positive metres, got {lane_width}")
        self._ids = split_ids(self.root, split)
        self._scene_of: dict[str, str] | None = None
        if not self.info.has_meta:
            all_ids = split_ids(self.root, "all")
            self._scene_of = self.info.scene_rule.scenes(all_ids)
        if check_files:
            self._check_files()
            if split == "all" or all(imageset_path(self.root, s).is_file() for s in ("train", "test")):
                check_frame_count(self.root, self.info, self._ids if split == "all" else split_ids(self.root, "all"))

    # ------------------------------------------------------------------ properties
    @property
    def frame_ids(self) -> list[str]:
        """Frame ids of this split, in ImageSets order."""
        return list(self._ids)

    @property
    def heights(self) -> list[float | str]:
        """Every mounting height the dataset holds (metres), and its rigs by name."""
        return [k if is_rig_key(k) else float(k) for k in self.info.heights]

    @property
    def info_file(self) -> Path:
        """ROOT/dataset.json."""
        return self.root / INFO_FILE

    @property
    def sensor(self) -> Sensor:
        """The sensor of this height as stored in dataset.json."""
        return self.height_info.sensor

    def __len__(self) -> int:
        return len(self._ids)

    def __getitem__(self, index: int) -> Frame:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"index must be an integer, got {type(index).__name__}; use .load(frame_id) for ids")
        n = len(self._ids)
        i = int(index) + (n if index < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"index {index} out of range for {n} frames ({self.split} split, {self.height_key} m)")
        return self.load(self._ids[i])

    def __iter__(self) -> Iterator[Frame]:
        for fid in self._ids:
            yield self.load(fid)

    def __repr__(self) -> str:
        return (f"Height3Dataset(root={str(self.root)!r}, height={self.height_key}, split={self.split!r}, "
                f"frames={len(self)})")

    # ------------------------------------------------------------------ reading
    def points_file(self, frame_id: str) -> Path:
        return points_path(self.root, self.height_key, frame_id, self.height_info.points_ext)

    def frame_files(self, frame_id: str) -> list[Path]:
        """The files a frame at this height is read from: labels, meta (when the dataset has them), points."""
        files = [label_path(self.root, frame_id)]
        if self.info.has_meta:
            files.append(meta_path(self.root, frame_id))
        return files + [self.points_file(frame_id)]

    def _check_files(self) -> None:
        missing: list[Path] = []
        for fid in self._ids:
            missing.extend(p for p in self.frame_files(fid) if not p.is_file())
        if missing:
            listing = imageset_path(self.root, "train" if self.split == "all" else self.split)
            shown = ", ".join(str(p) for p in missing[:3])
            raise MissingFileError(
                f"{len(missing)} file(s) of frames listed in ImageSets are absent (e.g. {shown}); restore them "
                f"or remove those ids from ImageSets/*.txt", path=missing[0] if len(missing) == 1 else listing)

    def read_labels(self, frame_id: str) -> dict:
        """Labels and extras of a frame without its points: dict with boxes (M, 7) float32, classes (M,) str,
        track_ids (M,) int64, lanes (M,) int64, scene_id, timestamp (s), ego (dict), sensor (Sensor)."""
        boxes, classes = read_labels(label_path(self.root, frame_id), self.info.classes, root=self.root)
        m = len(boxes)
        sensor = self.height_info.sensor
        if self.info.has_meta:
            mpath = meta_path(self.root, frame_id)
            meta = read_meta(mpath, frame_id, m, root=self.root)
            if self.height_key in meta["sensors"]:
                sensor = meta["sensors"][self.height_key]
                if self.height_info.rig is None and height_key(sensor.height) != self.height_key:
                    raise DatasetError(f"sensors.{self.height_key}.height is {sensor.height}; it must be "
                                       f"{self.height_key} m", path=mpath)
            scene_id, ts, ego = meta["scene_id"], meta["timestamp"], meta["ego"]
            track_ids, lanes = meta["track_ids"], meta["lanes"]
        else:
            scene_of = self._scene_of or {}
            scene_id = scene_of.get(frame_id) or self.info.scene_rule.scenes([frame_id])[frame_id]
            ts, ego = 0.0, {}
            track_ids = np.full(m, -1, dtype=np.int64)
            lanes = lanes_from_lateral(boxes[:, 1], self.lane_width) if m else np.zeros(0, dtype=np.int64)
        return {"boxes": boxes, "classes": classes, "track_ids": track_ids, "lanes": lanes, "scene_id": scene_id,
                "timestamp": ts, "ego": ego, "sensor": sensor}

    def load(self, frame_id: str) -> Frame:
        """The validated Frame of `frame_id` at this height."""
        lab = self.read_labels(frame_id)
        ppath = self.points_file(frame_id)
        points = read_points(ppath, self.height_info.bin_columns, root=self.root)
        if self.height_info.points_frame == "sensor":
            s = lab["sensor"]
            points = sensor_to_ground(points, s.height, s.pitch_deg)
        frame = Frame(frame_id=frame_id, scene_id=lab["scene_id"], points=points, boxes=lab["boxes"],
                      classes=lab["classes"], track_ids=lab["track_ids"], lanes=lab["lanes"], sensor=lab["sensor"],
                      ego=lab["ego"], timestamp=lab["timestamp"])
        try:
            frame.check(str(ppath))
        except ValueError as e:
            raise DatasetError(str(e).split(": ", 1)[-1], path=ppath) from None
        return frame

    def scene_ids(self) -> dict[str, str]:
        """frame id -> scene id for this split (reads the meta files when present)."""
        if not self.info.has_meta:
            return {f: self._scene_of[f] for f in self._ids}
        out = {}
        for fid in self._ids:
            path = meta_path(self.root, fid)
            if not path.is_file():
                raise MissingFileError("meta file not found; every frame needs meta/<id>.json when has_meta "
                                       "is true", path=path)
            check_inside(path, self.root)
            try:
                scene = json.loads(path.read_text(encoding="utf-8")).get("scene_id")
            except (json.JSONDecodeError, UnicodeDecodeError, AttributeError, RecursionError):
                scene = None
            if not isinstance(scene, str) or not scene:
                raise DatasetError("no valid 'scene_id' (a non-empty string) in this meta file; re-create it",
                                   path=path)
            out[fid] = scene
        return out


__all__ = ["Height3Dataset", "split_ids"]
