"""`DatasetWriter`: stream frames (one per height, same traffic) into the detbench layout.

```python
with DatasetWriter(root, heights=[0.5, 1.0, 1.8], source={"simulator": cfg, "seed": 0}) as w:
    for frames in sim.run(n, lidars):
        w.add(frames)          # points per height, shared labels, meta side file
# leaving the block writes ImageSets/train.txt, test.txt (split by scene) and dataset.json
```

Every file is written atomically (detbench.utils.atomic); the folder's owner file
(`detbench.utils.folder_ownership.OWNER_FILE`) is written first and dataset.json last, so a folder without
dataset.json is an unfinished dataset, readers say so, and `overwrite` may replace it: the
owner file proves it a dataset (the names points/ and labels/ alone do not: OpenPCDet uses
them too). A new or empty folder is written in place; an existing dataset (replaced only with
`overwrite=True`) is replaced whole: the new one is built beside it and swapped in when
complete, so no file of the old dataset survives and a failed or interrupted write leaves the
old one as it was.
"""
from __future__ import annotations

import os
import warnings
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from detbench.config import shipped_default
from detbench.data.errors import DatasetError
from detbench.data.frame import DEFAULT_LANE_WIDTH, Frame, Sensor, data_key, height_key, is_rig_key
from detbench.data.layout import (
    DATASET_FOLDER, DEFAULT_CLASSES, FORMAT_NAME, FORMAT_VERSION, INFO_FILE, POINT_EXTS, DatasetInfo, HeightInfo,
    SceneRule, assign_splits, check_frame_id, imageset_path, label_path, meta_path, points_path, sensor_index_path,
)
from detbench.data.readers import format_labels, meta_dict
from detbench.data.regions import check_range_name, in_range
from detbench.utils.atomic import atomic_save, atomic_write_json, atomic_write_text
from detbench.utils.folder_ownership import check_replaceable, folder_owner, write_owner
from detbench.utils.staged_folders import recover_staged, staged_folder


def _save_npy(arr: np.ndarray):
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.save(fh, arr, allow_pickle=False)
    return write


def _save_bin(arr: np.ndarray):
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            fh.write(np.ascontiguousarray(arr, dtype="<f4").tobytes())
    return write


class DatasetWriter:
    """Write a multi-height dataset in the detbench layout (docs/data-format.md).

    Args:
        root: output folder (created).
        heights: mounting heights in metres, e.g. [0.5, 1.0, 1.8], or rig names (docs/rigs.md); each
            `add` gets one frame per height (a rig's frame carries its name in `rig`).
        source: provenance stored in dataset.json, e.g. {"kind": "simulator", "preset": "paper",
            "config": {...}, "seed": 0} or {"kind": "external", ...}.
        test_fraction: share of scenes in the test split, in [0, 1) (default: configs/default.yaml
            `data.test_fraction`); see `detbench.data.layout.split_scenes`.
        overwrite: replace a dataset already in `root` (or an unfinished one): the new one is
            built beside it and swapped in whole by `close` (`detbench.utils.folder_ownership.check_replaceable`
            says which folders may be replaced).
        classes: allowed class names (default: car, suv, van, taxi, truck plus any new names
            seen, appended in order of appearance).
        points_ext: ".npy" (default) or ".bin" (KITTI-style raw float32).
        lane_width: metres (default 3.5), stored for readers that must derive lanes from y.
        drop_frames_without: a range name ("small", "moderate", "large") or None (default: keep
            every frame): frames with no vehicle centred in that range are written but join neither
            split, as the paper drops its frames without vehicles. Scenes are split first, so the
            rule never moves a scene to the other split; dataset.json records what was dropped.
    """

    def __init__(self, root: str | os.PathLike, heights: list[float], source: dict,
                 test_fraction: float | None = None, *, overwrite: bool = False, classes: list[str] | None = None,
                 points_ext: str = ".npy", lane_width: float | None = None,
                 drop_frames_without: str | None = None, rigs: dict[str, dict] | None = None):
        self.root = Path(root)
        self.rigs = dict(rigs or {})  # rig name -> its description, stored in dataset.json
        test_fraction = shipped_default("data.test_fraction", test_fraction)
        if not heights:
            raise ValueError("heights is empty; give at least one mounting height in metres")
        self.height_keys = [data_key(h) for h in heights]
        unknown = [k for k in self.height_keys if is_rig_key(k) and k not in self.rigs]
        if unknown:
            raise ValueError(f"rigs {unknown}: give their descriptions in rigs= (detbench.sim.rigs.Rig.describe)")
        if len(set(self.height_keys)) != len(self.height_keys):
            raise ValueError(f"duplicate heights {self.height_keys}")
        if not isinstance(source, dict):
            raise TypeError(f"source must be a dict (provenance for dataset.json), got {type(source).__name__}")
        if not 0.0 <= float(test_fraction) < 1.0:
            raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
        if points_ext not in POINT_EXTS:
            raise ValueError(f"points_ext must be one of {POINT_EXTS}, got {points_ext!r}")
        self.source = dict(source)
        self.test_fraction = float(test_fraction)
        self.drop_frames_without = None if drop_frames_without is None else check_range_name(drop_frames_without)
        self._without: set[str] = set()  # frames with no vehicle in that range
        self.overwrite = overwrite
        self.points_ext = points_ext
        self.lane_width = DEFAULT_LANE_WIDTH if lane_width is None else float(lane_width)
        self._fixed_classes = classes is not None
        self.classes: list[str] = list(classes) if classes is not None else list(DEFAULT_CLASSES)
        self.sensors: dict[str, Sensor] = {}
        self._frame_ids: list[str] = []
        self._scene_of: dict[str, str] = {}
        self._open = False
        self._closed = False
        self._dir = self.root  # where the files go: `root`, or the folder built beside it to replace it
        self._stage: ExitStack | None = None  # holds the staged folder while one replaces `root`

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> DatasetWriter:
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self._abandon(exc_type, exc, tb)

    def _abandon(self, exc_type, exc, tb) -> None:
        """Stop after an error: a replacement removes the folder built beside `root` (the old dataset
        stays); a dataset written in place stays unfinished (no dataset.json, and readers say so)."""
        if self._stage is not None:
            stage, self._stage = self._stage, None
            stage.__exit__(exc_type, exc, tb)

    def open(self) -> DatasetWriter:
        """Create the folders (called by `with`). A new or empty `root` is written in place; a dataset in
        it is replaced only with `overwrite` (FileExistsError otherwise, naming the folder and the fix),
        by a folder built beside it and swapped in by `close`."""
        if self._open:
            return self
        recover_staged(self.root)
        if check_replaceable(self.root, self.overwrite, DATASET_FOLDER, flag="overwrite=True"):
            self._stage = ExitStack()
            self._dir = self._stage.enter_context(staged_folder(
                self.root, what="a dataset writer",
                check=lambda: check_replaceable(self.root, self.overwrite, DATASET_FOLDER, flag="overwrite=True")))
        self._dir.mkdir(parents=True, exist_ok=True)
        if folder_owner(self._dir) is None:
            write_owner(self._dir, DATASET_FOLDER)  # first: even an unfinished dataset is known to be one
        for hk in self.height_keys:
            (self._dir / "points" / hk).mkdir(parents=True, exist_ok=True)
            if is_rig_key(hk):
                sensor_index_path(self._dir, hk, "x").parent.mkdir(parents=True, exist_ok=True)
        for sub in ("labels", "meta", "ImageSets"):
            (self._dir / sub).mkdir(parents=True, exist_ok=True)
        self._open = True
        return self

    # ------------------------------------------------------------------ frames
    @property
    def frame_ids(self) -> list[str]:
        """Ids added so far, in order."""
        return list(self._frame_ids)

    def __len__(self) -> int:
        return len(self._frame_ids)

    def add(self, frames: list[Frame] | Frame) -> None:
        """Write one frame id at every height.

        `frames`: one Frame per height of the writer (any order; matched by sensor height),
        all with the same frame_id, scene_id and labels (boxes, classes, track ids, lanes),
        as the simulator yields them. Points go to points/<h>/<id>, the shared labels to
        labels/<id>.txt, the extras to meta/<id>.json.
        """
        if not self._open:
            self.open()
        if self._closed:
            raise RuntimeError("this DatasetWriter is closed; open a new one")
        if isinstance(frames, Frame):
            frames = [frames]
        frames = list(frames)
        by_key: dict[str, Frame] = {}
        for f in frames:
            if not isinstance(f, Frame):
                raise TypeError(f"add() takes Frame objects, got {type(f).__name__}")
            hk = getattr(f, "rig", "") or height_key(f.sensor.height)
            if hk in by_key:
                raise ValueError(f"frame {f.frame_id}: two frames for height {hk} m")
            by_key[hk] = f
        if set(by_key) != set(self.height_keys):
            raise ValueError(f"frame {frames[0].frame_id if frames else '?'}: got heights {sorted(by_key)}, "
                             f"the writer was opened for {self.height_keys}; pass one frame per height")
        ref = by_key[self.height_keys[0]]
        fid = check_frame_id(ref.frame_id)
        if fid in self._scene_of:
            raise ValueError(f"frame id {fid!r} was already added; frame ids must be unique")
        if not isinstance(ref.scene_id, str) or not ref.scene_id:
            raise ValueError(f"frame {fid}: scene_id must be a non-empty string (the split is by scene)")
        for hk, f in by_key.items():
            f.check(f"frame {fid} at {hk} m")
            if f.frame_id != fid or f.scene_id != ref.scene_id:
                raise ValueError(f"frames of one add() disagree: {f.frame_id}/{f.scene_id} at {hk} m vs "
                                 f"{fid}/{ref.scene_id}; pass the frames of one instant")
            if f is not ref and not (np.array_equal(f.boxes, ref.boxes)
                                     and np.array_equal(np.asarray(f.classes), np.asarray(ref.classes))
                                     and np.array_equal(f.track_ids, ref.track_ids)
                                     and np.array_equal(f.lanes, ref.lanes)):
                raise ValueError(f"frame {fid}: labels at {hk} m differ from those at {self.height_keys[0]} m; "
                                 f"labels are in the ground frame and shared by all heights")
        for name in np.asarray(ref.classes).tolist():
            if name not in self.classes:
                if self._fixed_classes:
                    raise ValueError(f"frame {fid}: class {name!r} is not in classes {self.classes}")
                self.classes.append(str(name))
        for hk in self.height_keys:
            if hk not in self.sensors:
                self.sensors[hk] = by_key[hk].sensor

        for hk in self.height_keys:
            pts = np.ascontiguousarray(by_key[hk].points, dtype=np.float32)
            saver = _save_npy(pts) if self.points_ext == ".npy" else _save_bin(pts)
            atomic_save(points_path(self._dir, hk, fid, self.points_ext), saver)
            if is_rig_key(hk):  # the sensor of each point, beside the rig's points
                index = np.asarray(getattr(by_key[hk], "sensor_index", np.zeros(len(pts))), dtype=np.int16)
                if index.shape != (len(pts),):
                    raise ValueError(f"frame {fid}: rig {hk} has {len(index)} sensor indices for {len(pts)} points")
                atomic_save(sensor_index_path(self._dir, hk, fid), _save_npy(index))
        atomic_write_text(label_path(self._dir, fid), format_labels(ref.boxes, ref.classes))
        sensors = {hk: by_key[hk].sensor for hk in self.height_keys}
        atomic_write_json(meta_path(self._dir, fid), meta_dict(ref, sensors), indent=None)
        self._frame_ids.append(fid)
        self._scene_of[fid] = ref.scene_id
        if self.drop_frames_without is not None and not in_range(ref.boxes, self.drop_frames_without).any():
            self._without.add(fid)

    # ------------------------------------------------------------------ finish
    def _check_files(self) -> None:
        """DatasetError when a file this writer wrote is gone (another process deleted it while the dataset was
        written): such a dataset is never finished, so no later command trusts it."""
        missing = []
        for fid in self._frame_ids:
            paths = [points_path(self._dir, hk, fid, self.points_ext) for hk in self.height_keys]
            missing += [p for p in (*paths, label_path(self._dir, fid), meta_path(self._dir, fid)) if not p.is_file()]
        if missing:
            raise DatasetError(f"{self.root}: {len(missing)} file(s) written for its {len(self._frame_ids)} frames "
                               f"vanished before the dataset was finished (e.g. {missing[0]}): another process "
                               f"deleted them; the dataset is not finished, run the same command again")

    def close(self) -> DatasetInfo:
        """Write ImageSets (split by scene) and dataset.json; returns the DatasetInfo."""
        if self._closed:
            raise RuntimeError("DatasetWriter.close() called twice")
        if not self._open:
            self.open()
        if not self._frame_ids:
            warnings.warn(f"{self.root}: no frames were added; writing an empty dataset", UserWarning,
                          stacklevel=2)
        try:
            train, test, rule = assign_splits(self._frame_ids, self._scene_of, self.test_fraction)
            if self.drop_frames_without is not None:
                rule = dict(rule, dropped={
                    "rule": f"frames with no vehicle in the {self.drop_frames_without} range join neither split",
                    "range": self.drop_frames_without, "frames": len(self._without),
                    "train": sum(f in self._without for f in train), "test": sum(f in self._without for f in test)})
                train = [f for f in train if f not in self._without]
                test = [f for f in test if f not in self._without]
                if self._frame_ids and not train and not test:
                    r = self.drop_frames_without
                    raise DatasetError(f"dropping the frames without a vehicle in the {r} range (--drop-frames-"
                                       f"without {r}) leaves both splits empty: none of the {len(self._frame_ids)} "
                                       f"frames has one; simulate more frames or denser traffic, or drop by a "
                                       f"wider range (moderate, large)")
            self._check_files()
            atomic_write_text(imageset_path(self._dir, "train"), "".join(f + "\n" for f in train))
            atomic_write_text(imageset_path(self._dir, "test"), "".join(f + "\n" for f in test))
            heights = {}
            for hk in self.height_keys:
                sensor = self.sensors.get(hk) or Sensor(height=float(hk))
                heights[hk] = HeightInfo(key=hk, sensor=sensor, points_frame="ground", points_ext=self.points_ext,
                                         rig=self.rigs.get(hk))
            rule = dict(rule, num_train=len(train), num_test=len(test))
            info = DatasetInfo(heights=heights, source=self.source, classes=self.classes, split=rule, has_meta=True,
                               lane_width=self.lane_width, scene_rule=SceneRule("prefix", "_"),
                               num_frames=len(self._frame_ids), format=FORMAT_NAME, version=FORMAT_VERSION)
            atomic_write_json(self._dir / INFO_FILE, info.to_dict())
        except BaseException as e:
            self._abandon(type(e), e, e.__traceback__)
            raise
        if self._stage is not None:  # the complete new dataset replaces the old one whole
            stage, self._stage = self._stage, None
            stage.close()  # the swap; a swap that fails removes the new folder itself
            self._dir = self.root
        self._closed = True
        return info


__all__ = ["DatasetWriter", "DatasetError"]
