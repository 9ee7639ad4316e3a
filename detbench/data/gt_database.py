"""Ground-truth sampling: a database of LiDAR-detected vehicles and their points, pasted into frames.

Building (once per training split and height; later calls reuse it):

```
OUT/gt_database.npz    points (T, 4) float32 x, y, z relative to the box centre, intensity;
                       offsets (K + 1,) int64 (object k owns points[offsets[k]:offsets[k+1]]);
                       boxes (K, 7) float32 where the vehicle was; num_points (K,) int64
OUT/gt_database.json   the index: format, version, source, fingerprint of the frames'
                       content (`frames_fingerprint`: the bytes of their files), bottom
                       lift, per-class counts and one record per object
                       {frame_id, class, track_id, num_points}
```

A build first removes the old index, then writes both files atomically, the JSON last, so
a folder without the JSON is an unfinished build and is rebuilt. A database whose
fingerprint no longer matches the frames (the dataset was re-simulated into the same
folder, or labels were edited in place) is rebuilt, never reused. An object's points are
those inside its box with the
bottom raised by `bottom_lift` (DETECTED_BOTTOM_LIFT, the LiDAR-detected rule of
detbench.data.regions), so no road points travel with a pasted vehicle; objects with fewer
such points than DETECTED_MIN_POINTS are not LiDAR-detected and are left out.

Pasting (`GTSampler.sample`): draw vehicles, keep each where it was recorded (the road
layout is shared by all frames), reject any whose bird's-eye-view box overlaps (IoU > 0) a
vehicle of the frame (detected or not) or an already accepted one, delete the frame's
points inside the accepted boxes (enlarged by `remove_extra_width`), and add the vehicles'
points and boxes. As in OpenPCDet, occlusion between pasted and existing vehicles is not
re-simulated.
"""
from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from detbench.config import ConfigError, shipped_defaults, validate
from detbench.data.frame import Frame
from detbench.data.regions import DETECTED_BOTTOM_LIFT, DETECTED_MIN_POINTS, detected_point_index
from detbench.ops import boxes_iou_bev, points_in_boxes
from detbench.utils.atomic import atomic_save, atomic_write_json, read_json
from detbench.utils.untrusted import excerpt

__all__ = [
    "GT_SAMPLING_DEFAULTS", "GTSamplingConfig", "GTDatabase", "GTSampler", "build_gt_database", "load_gt_database",
    "build_or_load_gt_database", "frames_fingerprint",
]

DB_FORMAT = "detbench-gt-database"
DB_VERSION = 1
INDEX_FILE = "gt_database.json"
ARRAYS_FILE = "gt_database.npz"

# configs/default.yaml `augment.gt_sampling:`, each key documented there
GT_SAMPLING_DEFAULTS: dict[str, Any] = shipped_defaults("augment")["gt_sampling"]


@dataclass(frozen=True)
class GTSamplingConfig:
    """Ground-truth sampling settings: the `augment.gt_sampling` section, parsed by `from_dict`
    (names, defaults and units: configs/default.yaml)."""

    enabled: bool
    sample_count: int
    limit_whole_scene: bool
    filter_by_min_points: int
    remove_extra_width: tuple[float, float, float]  # metres
    database_dir: str | None

    @classmethod
    def from_dict(cls, cfg: Mapping | None, where: str = "augment.gt_sampling") -> GTSamplingConfig:
        """Parse the `gt_sampling` section; missing keys take GT_SAMPLING_DEFAULTS."""
        cfg = dict(cfg or {})
        validate(cfg, GT_SAMPLING_DEFAULTS, where=where)
        d = {**GT_SAMPLING_DEFAULTS, **cfg}
        n, mp = d["sample_count"], d["filter_by_min_points"]
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise ConfigError(f"{where}: sample_count must be an integer >= 0, got {excerpt(n)}")
        if not isinstance(mp, int) or isinstance(mp, bool) or mp < 1:
            raise ConfigError(f"{where}: filter_by_min_points must be an integer >= 1, got {excerpt(mp)}")
        try:
            w = tuple(float(v) for v in d["remove_extra_width"])
        except (TypeError, ValueError):
            w = ()
        if len(w) != 3 or not all(math.isfinite(v) and v >= 0 for v in w):
            raise ConfigError(f"{where}: remove_extra_width must be 3 numbers >= 0 (metres added to dx, dy, dz), "
                              f"got {excerpt(d['remove_extra_width'])}")
        db = d["database_dir"]
        return cls(enabled=bool(d["enabled"]), sample_count=n, limit_whole_scene=bool(d["limit_whole_scene"]),
                   filter_by_min_points=mp, remove_extra_width=w,  # type: ignore[arg-type]
                   database_dir=None if db in (None, "") else str(db))


@dataclass
class GTDatabase:
    """K vehicles with their points. See the module doc for the arrays' layout."""

    points: np.ndarray  # (T, 4) float32, xyz relative to the box centre, intensity
    offsets: np.ndarray  # (K + 1,) int64
    boxes: np.ndarray  # (K, 7) float32
    num_points: np.ndarray  # (K,) int64
    classes: list[str]
    frame_ids: list[str]
    track_ids: np.ndarray  # (K,) int64
    info: dict  # the JSON index without the per-object records

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    def object_points(self, k: int) -> np.ndarray:
        """(n_k, 4) float32 points of object `k` in the frame where it was recorded."""
        p = self.points[self.offsets[k]:self.offsets[k + 1]].copy()
        p[:, :3] += self.boxes[k, :3]
        return p


def _frame_ids(frames: Sequence[Frame]) -> list[str]:
    ids = getattr(frames, "frame_ids", None)
    if ids is not None:
        return [str(i) for i in ids]
    return [frames[i].frame_id for i in range(len(frames))]


def frames_fingerprint(frames: Sequence[Frame]) -> str:
    """SHA-1 of the content of `frames`, in order: for a dataset on disk (anything with
    `frame_files(frame_id)` and `info_file`, e.g. Height3Dataset) the bytes of dataset.json and of
    every frame's label, meta and points files; for a list of Frames their ids, points, boxes,
    classes and track ids. A dataset re-simulated or edited in place gets another fingerprint."""
    h = hashlib.sha1()
    files = getattr(frames, "frame_files", None)
    if files is not None:
        _hash_file(h, frames.info_file)
    for i, fid in enumerate(_frame_ids(frames)):
        h.update(fid.encode("utf-8") + b"\n")
        if files is not None:
            for path in files(fid):
                _hash_file(h, path)
        else:
            f = frames[i]
            for arr in (f.points, f.boxes, np.asarray(f.classes, dtype=str), f.track_ids):
                h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _hash_file(h, path: Path) -> None:
    """Feed a file's size and bytes to `h` (a missing file hashes as absent; reading it will say so)."""
    if not Path(path).is_file():
        h.update(b"<absent>")
        return
    with open(path, "rb") as fh:
        h.update(str(os.fstat(fh.fileno()).st_size).encode() + b":")
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)


def _write_npz(arrays: dict[str, np.ndarray]):
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return write


def build_gt_database(frames: Sequence[Frame], out_dir: str | os.PathLike, source: Mapping | None = None,
                      bottom_lift: float = DETECTED_BOTTOM_LIFT, progress: bool = True) -> GTDatabase:
    """Collect every LiDAR-detected vehicle of `frames` with its points and write the database.

    Args:
        frames: the training split (e.g. `Height3Dataset(root, height, "train")`); never the test split.
        out_dir: folder for gt_database.npz and gt_database.json (created).
        source: provenance stored in the index and compared on reuse, e.g.
            {"root": "/data/h3", "height": 1.8, "split": "train"}.
        bottom_lift: metres; object points are those inside the box with its bottom raised this much.
        progress: show a tqdm bar.
    Returns:
        The database (also on disk).
    """
    from tqdm import tqdm

    out_dir = Path(out_dir)
    (out_dir / INDEX_FILE).unlink(missing_ok=True)  # an interrupted rebuild must not pass for the old database
    pts, boxes, npts, classes, fids, tids = [], [], [], [], [], []
    for i in tqdm(range(len(frames)), desc="gt database", unit="frame", disable=not progress, leave=False):
        f = frames[i]
        if f.boxes.shape[0] == 0:
            continue
        counts, index = detected_point_index(f.points, f.boxes, bottom_lift)
        order = np.argsort(index, kind="stable")
        sorted_index = index[order]
        starts = np.searchsorted(sorted_index, np.arange(f.boxes.shape[0]), side="left")
        for k in np.flatnonzero(counts >= DETECTED_MIN_POINTS):
            sel = order[starts[k]:starts[k] + counts[k]]
            p = f.points[sel].astype(np.float32, copy=True)
            p[:, :3] -= f.boxes[k, :3]
            pts.append(p)
            boxes.append(f.boxes[k].astype(np.float32))
            npts.append(int(counts[k]))
            classes.append(str(f.classes[k]))
            fids.append(f.frame_id)
            tids.append(int(f.track_ids[k]) if len(f.track_ids) else -1)
    num_points = np.asarray(npts, dtype=np.int64)
    offsets = np.zeros(len(npts) + 1, dtype=np.int64)
    np.cumsum(num_points, out=offsets[1:])
    arrays = {
        "points": np.concatenate(pts, axis=0) if pts else np.zeros((0, 4), np.float32),
        "offsets": offsets,
        "boxes": np.stack(boxes, axis=0) if boxes else np.zeros((0, 7), np.float32),
        "num_points": num_points,
        "track_ids": np.asarray(tids, dtype=np.int64),
    }
    per_class: dict[str, int] = {}
    for c in classes:
        per_class[c] = per_class.get(c, 0) + 1
    info = {
        "format": DB_FORMAT,
        "version": DB_VERSION,
        "source": dict(source or {}),
        "frames_sha1": frames_fingerprint(frames),
        "num_frames": len(frames),
        "bottom_lift": float(bottom_lift),
        "num_objects": len(npts),
        "num_points": int(offsets[-1]),
        "per_class": per_class,
        "arrays": ARRAYS_FILE,
        "units": "points: metres relative to the box centre (x, y, z), intensity in [0, 1]; boxes: metres, radians",
    }
    atomic_save(out_dir / ARRAYS_FILE, _write_npz(arrays))
    records = [{"frame_id": f, "class": c, "track_id": t, "num_points": n}
               for f, c, t, n in zip(fids, classes, tids, npts)]
    atomic_write_json(out_dir / INDEX_FILE, {**info, "objects": records})
    return GTDatabase(arrays["points"], offsets, arrays["boxes"], num_points, classes, fids,
                      arrays["track_ids"], info)


def load_gt_database(out_dir: str | os.PathLike) -> GTDatabase:
    """Read a database written by `build_gt_database`; errors name the file and the fix."""
    out_dir = Path(out_dir)
    index_path = out_dir / INDEX_FILE
    fix = "delete the folder and let training rebuild it (or call build_gt_database)"
    index = read_json(index_path)
    if not isinstance(index, dict) or index.get("format") != DB_FORMAT:
        raise ValueError(f"{index_path}: not a detbench ground-truth database index (format != {DB_FORMAT!r}); {fix}")
    if index.get("version") != DB_VERSION:
        raise ValueError(f"{index_path}: database version {excerpt(index.get('version'))}, "
                         f"this code reads {DB_VERSION}; {fix}")
    arrays_path = out_dir / ARRAYS_FILE
    try:
        with np.load(arrays_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("points", "offsets", "boxes", "num_points", "track_ids")}
    except FileNotFoundError:
        raise FileNotFoundError(f"{arrays_path}: missing (the index {index_path} refers to it); {fix}") from None
    except Exception as e:  # zip/format errors of a damaged file
        raise ValueError(f"{arrays_path}: unreadable ({type(e).__name__}: {e}); {fix}") from None
    records = index.get("objects", [])
    k = arrays["boxes"].shape[0]
    if (len(records) != k or arrays["offsets"].shape != (k + 1,) or arrays["num_points"].shape != (k,)
            or arrays["points"].ndim != 2 or arrays["points"].shape[1] != 4
            or int(arrays["offsets"][-1]) != arrays["points"].shape[0]):
        raise ValueError(f"{out_dir}: {INDEX_FILE} and {ARRAYS_FILE} disagree on the number of objects "
                         f"or points; {fix}")
    info = {key: v for key, v in index.items() if key != "objects"}
    return GTDatabase(arrays["points"].astype(np.float32, copy=False), arrays["offsets"].astype(np.int64),
                      arrays["boxes"].astype(np.float32, copy=False), arrays["num_points"].astype(np.int64),
                      [str(r["class"]) for r in records], [str(r["frame_id"]) for r in records],
                      arrays["track_ids"].astype(np.int64), info)


def _same_source(stored, source: Mapping | None) -> bool:
    """The database's recorded source is `source` but for the dataset's path: the frames' content fingerprint
    decides whether they are the same frames, so a dataset moved or copied (or read-only elsewhere) reuses it."""
    if not isinstance(stored, Mapping):
        return False
    return {k: v for k, v in stored.items() if k != "root"} == {k: v for k, v in dict(source or {}).items()
                                                               if k != "root"}


def build_or_load_gt_database(frames: Sequence[Frame], out_dir: str | os.PathLike, source: Mapping | None = None,
                              bottom_lift: float = DETECTED_BOTTOM_LIFT, progress: bool = True) -> GTDatabase:
    """Load the database in `out_dir` if it was built from the same frames (content), source (but for the
    dataset's path: a moved dataset keeps its database) and lift; else (re)build it.

    In a distributed run, call it on rank 0 first (`detbench.train.distributed.main_process_first`).
    """
    index_path = Path(out_dir) / INDEX_FILE
    if index_path.is_file():
        try:
            db = load_gt_database(out_dir)
        except (ValueError, FileNotFoundError):
            db = None
        if (db is not None and db.info.get("frames_sha1") == frames_fingerprint(frames)
                and _same_source(db.info.get("source"), source)
                and db.info.get("bottom_lift") == float(bottom_lift)):
            return db
        if progress:
            from tqdm import tqdm

            tqdm.write(f"{out_dir}: the ground-truth database is stale (the training frames, their source or "
                       f"the bottom lift changed since it was built); rebuilding it")
    return build_gt_database(frames, out_dir, source=source, bottom_lift=bottom_lift, progress=progress)


class GTSampler:
    """Paste database vehicles into frames (see the module doc). Stateless apart from the database."""

    def __init__(self, db: GTDatabase, cfg: GTSamplingConfig):
        self.db = db
        self.cfg = cfg
        self.pool = np.flatnonzero(db.num_points >= cfg.filter_by_min_points)
        if cfg.enabled and cfg.sample_count > 0 and self.pool.size == 0:
            src = db.info.get("source", {})
            raise ValueError(f"ground-truth database ({src or 'in memory'}) has no vehicle with >= "
                             f"{cfg.filter_by_min_points} points; lower augment.gt_sampling.filter_by_min_points "
                             f"or disable augment.gt_sampling")

    def sample(self, points: np.ndarray, gt_boxes: np.ndarray, rng: np.random.Generator,
               avoid_boxes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """Paste vehicles into one frame.

        Args:
            points: (N, 4) float32 frame points.
            gt_boxes: (M, 7) training ground truth of the frame.
            rng: source of the random draws.
            avoid_boxes: (K, 7) all vehicles of the frame, detected or not (default `gt_boxes`).
        Returns:
            (points (N', 4) float32 with points inside pasted boxes replaced by the vehicles'
            points, gt_boxes (M + A, 7) float32 with the A pasted boxes appended, A).
        """
        gt_boxes = np.asarray(gt_boxes, dtype=np.float32).reshape(-1, 7)
        n_draw = self.cfg.sample_count - (gt_boxes.shape[0] if self.cfg.limit_whole_scene else 0)
        n_draw = min(n_draw, self.pool.size)
        if n_draw <= 0:
            return points, gt_boxes, 0
        picks = self.pool[rng.choice(self.pool.size, size=n_draw, replace=False)]
        cand = self.db.boxes[picks]
        existing = gt_boxes if avoid_boxes is None else np.concatenate(
            [gt_boxes, np.asarray(avoid_boxes, dtype=np.float32).reshape(-1, 7)], axis=0)
        if existing.shape[0]:
            free = ~(np.asarray(boxes_iou_bev(cand, existing)) > 0).any(axis=1)
        else:
            free = np.ones(n_draw, dtype=bool)
        overlap = np.asarray(boxes_iou_bev(cand, cand)) > 0
        accepted: list[int] = []
        for i in np.flatnonzero(free):
            if not overlap[i, accepted].any():
                accepted.append(int(i))
        if not accepted:
            return points, gt_boxes, 0
        keep = picks[accepted]
        new_boxes = self.db.boxes[keep]
        grown = new_boxes.copy()
        grown[:, 3:6] += np.asarray(self.cfg.remove_extra_width, dtype=np.float32)
        _, inside = points_in_boxes(points, grown)
        new_points = [points[np.asarray(inside) < 0]] + [self.db.object_points(int(k)) for k in keep]
        out_points = np.concatenate(new_points, axis=0).astype(np.float32, copy=False)
        return out_points, np.concatenate([gt_boxes, new_boxes], axis=0), len(accepted)
