"""Check a whole dataset and list every problem (not just the first).

    python -m detbench.data.validate ROOT [--heights 0.5 1.8 headlights] [--max-errors 50]

Exit status 0 when the dataset is clean, 1 otherwise. Each problem is printed as
``PATH[:LINE]: what is wrong; how to fix it``.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from detbench.data.errors import DatasetError
from detbench.data.frame import data_key, height_or_rig_arg
from detbench.data.dataset import Height3Dataset, check_frame_count, split_ids
from detbench.data.layout import INFO_FILE, LABELS_DIR, read_info, sensor_index_path
from detbench.data.readers import label_problems, read_points
from detbench.data.transforms import sensor_to_ground

# the road check: points 2-40 m away horizontally, the road's height their 5th percentile of z, over up to
# ROAD_FRAMES frames with at least ROAD_MIN_POINTS such points; the declared frame is refused when it puts the
# road more than ROAD_TOLERANCE_M off z = 0 and the other frame puts it at less than half that distance
ROAD_FRAMES = 16
ROAD_MIN_POINTS = 50
ROAD_TOLERANCE_M = 0.2


@dataclass
class ValidationReport:
    """Result of `validate_dataset`: `errors` (messages), `warnings`, and counts."""

    root: str
    num_frames: int = 0
    heights: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # facts worth knowing that are not problems
    truncated: bool = False

    @property
    def ok(self) -> bool:
        return not self.errors

    def to_dict(self) -> dict:
        return {"root": self.root, "ok": self.ok, "num_frames": self.num_frames, "heights": self.heights,
                "errors": self.errors, "warnings": self.warnings, "notes": self.notes, "truncated": self.truncated}


def validate_dataset(root: str | os.PathLike, heights=None, max_errors: int = 50, progress: bool = False
                     ) -> ValidationReport:
    """Read every listed frame at every height and rig (or `heights`: metres or rig names) and collect the problems.

    Checks dataset.json (its num_frames against the ImageSets), ImageSets (duplicates, ids in both
    splits, a scene in both splits, whatever split.rule says, unless the dataset has one scene cut in
    time), every label (every malformed line of it), meta and points file
    (format, dtype and byte order, plausible values, counts), a rig's sensor index of every point
    (`sensor_index_error`), what the points say about the
    frame they are in (`points_frame_problem`: the road's height in the declared frame), and
    warns about label files no split lists. A file's problem is listed once. Stops collecting
    after `max_errors`.
    """
    root = Path(root)
    rep = ValidationReport(root=str(root))
    reported: set[str] = set()  # files already listed (a missing meta file fails the scene check and its frame)

    def err(e: Exception | str, once: bool = True) -> bool:
        where = getattr(e, "path", None)
        if once and where is not None and getattr(e, "line", None) is None and where in reported:
            return False
        reported.add(where)
        rep.errors.append(str(e))
        if len(rep.errors) >= max_errors:
            rep.truncated = True
            return True
        return False

    try:
        info = read_info(root)
    except (DatasetError, FileNotFoundError) as e:
        err(e)
        return rep
    keys = list(info.heights) if heights is None else [data_key(h) for h in heights]
    rep.heights = keys
    try:
        ids = split_ids(root, "all")
    except (DatasetError, FileNotFoundError) as e:
        err(e)
        return rep
    rep.num_frames = len(ids)
    try:
        check_frame_count(root, info, ids)
    except DatasetError as e:
        if err(e):
            return rep
    if not ids:
        rep.warnings.append(f"{root}: ImageSets list no frames")
    listed = set(ids)
    labels_dir = root / LABELS_DIR
    if labels_dir.is_dir():
        orphans = [p for p in labels_dir.glob("*.txt") if p.stem not in listed]
        dropped = (info.split or {}).get("dropped") or {}
        if orphans and len(orphans) == dropped.get("frames"):  # the dataset's own rule left them out
            rep.notes.append(f"{len(orphans)} frame(s) join neither split: {dropped.get('rule')} (dataset.json "
                             f"split.dropped)")
        elif orphans:
            rep.warnings.append(f"{labels_dir}: {len(orphans)} label file(s) are in no split (e.g. {orphans[0].name}); "
                                f"they are ignored")
    datasets = {}
    for k in keys:
        try:
            datasets[k] = Height3Dataset(root, k, "all", check_files=False)
        except (DatasetError, FileNotFoundError, ValueError) as e:
            if err(e):
                return rep
    if not datasets:
        return rep
    any_ds = next(iter(datasets.values()))
    try:
        problem = _shared_scenes(root, info.split.get("rule"), ids, any_ds)
    except (DatasetError, FileNotFoundError) as e:
        problem = e
    if problem is not None and err(problem):
        return rep
    iterator = ids
    if progress:
        from tqdm import tqdm

        iterator = tqdm(ids, desc="validate", unit="frame")
    for fid in iterator:
        for ds in datasets.values():
            e = frame_error(ds, fid)
            if e is None:
                e = sensor_index_error(ds, fid)
                if e is not None and err(e):
                    return rep
                continue
            if any(err(p) for p in _every_line(e, ds.info.classes)):
                return rep
            if isinstance(e, DatasetError) and e.path and Path(e.path).name.startswith(fid) \
                    and Path(e.path).suffix in (".txt", ".json"):
                break  # a shared label/meta problem: reported once, not once per height
    for ds in datasets.values():
        problem = points_frame_problem(ds)
        if problem and err(DatasetError(problem, path=root / INFO_FILE), once=False):
            return rep
    return rep


def _shared_scenes(root: Path, rule, ids: list[str], dataset: Height3Dataset) -> DatasetError | None:
    """The error of a scene with frames in both splits, whatever split.rule says: only a dataset of one scene
    cut in time (rule time-block) has one by design, and a source's split kept on conversion (rule kept) was
    warned about then (`detbench.data.convert.split_scene_warning`)."""
    train_ids = set(split_ids(root, "train"))
    scenes = dataset.scene_ids()
    train_sc = {scenes[f] for f in ids if f in train_ids}
    test_sc = {scenes[f] for f in ids if f not in train_ids}
    both = sorted(train_sc & test_sc)
    if not both or rule == "kept" or (rule == "time-block" and len(train_sc | test_sc) == 1):
        return None
    return DatasetError(f"scene(s) {both[:5]} have frames in both train.txt and test.txt; split by scene (frames "
                        f"of a scene are nearly identical)", path=root / "ImageSets" / "test.txt")


def _road_height(points: np.ndarray) -> float | None:
    """The road's z (metres) under `points`: the 5th percentile of z of the points 2-40 m away horizontally
    (None with fewer than ROAD_MIN_POINTS of them)."""
    d = np.hypot(points[:, 0], points[:, 1])
    z = points[(d >= 2.0) & (d <= 40.0), 2]
    return float(np.percentile(z, 5)) if z.size >= ROAD_MIN_POINTS else None


def points_frame_problem(dataset: Height3Dataset, max_frames: int = ROAD_FRAMES) -> str | None:
    """What the points say about the frame they are in, against dataset.json's `points_frame`: None when the
    road lies at z = 0 in the declared frame (or the frames tell nothing), else the problem and its fix.

    The origin of the ego ground frame is on the road below the sensor, so its road lies at z = 0; in the
    sensor frame the road lies about the mounting height below. Ground-frame points declared `sensor` are
    raised by the height once more on load (and sensor-frame points declared `ground` are left below the
    road), which every count of points in a box then misreads."""
    ids = dataset.frame_ids
    if not ids:
        return None
    picks = sorted({ids[int(i)] for i in np.linspace(0, len(ids) - 1, min(max_frames, len(ids)))})
    declared_z, other_z = [], []
    for fid in picks:
        try:
            sensor = dataset.read_labels(fid)["sensor"]
            raw = read_points(dataset.points_file(fid), dataset.height_info.bin_columns)
        except (DatasetError, FileNotFoundError, ValueError):
            continue  # the frame loop names it
        as_sensor = sensor_to_ground(raw, sensor.height, sensor.pitch_deg)
        declared, other = (raw, as_sensor) if dataset.height_info.points_frame == "ground" else (as_sensor, raw)
        zd, zo = _road_height(declared), _road_height(other)
        if zd is not None and zo is not None:
            declared_z.append(zd)
            other_z.append(zo)
    if not declared_z:
        return None
    zd, zo = float(np.median(declared_z)), float(np.median(other_z))
    if abs(zd) <= ROAD_TOLERANCE_M or abs(zo) >= 0.5 * abs(zd):
        return None
    frame = dataset.height_info.points_frame
    other = "sensor" if frame == "ground" else "ground"
    return (f"heights.{dataset.height_key}.points_frame is {frame!r}, but the points are in the {other} frame: "
            f"read as {frame}-frame points, the road under them lies at z = {zd:+.2f} m in the ego ground frame "
            f"(median of {len(declared_z)} frames; the road lies at z = 0 there), read as {other}-frame points at "
            f"z = {zo:+.2f} m; set heights.{dataset.height_key}.points_frame to {other!r} in dataset.json")


def _every_line(e: Exception, classes) -> list[Exception]:
    """For an error on a line of a label file, every malformed line of that file; else `[e]`."""
    if not (isinstance(e, DatasetError) and e.line is not None and e.path and e.path.endswith(".txt")):
        return [e]
    try:
        text = Path(e.path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return [e]
    return label_problems(text, e.path, classes) or [e]


def sensor_index_error(dataset: Height3Dataset, frame_id: str) -> DatasetError | None:
    """For a rig (dataset.json's heights.<name>.rig), why sensor_index/<rig>/<frame_id>.npy does not give each
    point of the frame one of the rig's sensors, or None (also for a height)."""
    rig = dataset.height_info.rig
    if rig is None:
        return None
    path = sensor_index_path(dataset.root, dataset.height_key, frame_id)
    n_sensors = len(rig.get("sensors") or [])
    fix = f"simulate the rig again (tools/simulate.py --rigs {dataset.height_key})"
    if not path.is_file():
        return DatasetError(f"missing: the rig {dataset.height_key!r} keeps each point's sensor here; {fix}",
                            path=path)
    try:
        index = np.load(path, allow_pickle=False)
        points = read_points(dataset.points_file(frame_id), dataset.height_info.bin_columns)
    except (OSError, ValueError, DatasetError) as e:
        return DatasetError(f"unreadable sensor index ({e}); {fix}", path=path)
    if index.ndim != 1 or index.dtype.kind not in "iu" or len(index) != len(points):
        return DatasetError(f"must be a 1-D integer array of one sensor a point ({len(points)} points), got "
                            f"{index.dtype} of shape {index.shape}; {fix}", path=path)
    if len(index) and (index.min() < 0 or index.max() >= n_sensors):
        return DatasetError(f"sensor indices {int(index.min())}..{int(index.max())} outside the rig's "
                            f"{n_sensors} sensor(s) 0..{n_sensors - 1}; {fix}", path=path)
    return None


def frame_error(dataset: Height3Dataset, frame_id: str) -> Exception | None:
    """Why frame `frame_id` of `dataset` cannot be read (the reader's error naming file and line), or None."""
    try:
        dataset.load(frame_id)
    except (DatasetError, FileNotFoundError, ValueError) as e:
        return e
    return None


def check_frames(dataset: Height3Dataset, frame_ids: Sequence[str] | None = None, fix: str = "") -> None:
    """Read every frame of `dataset` (or `frame_ids`) once; DatasetError naming the first bad file and the count,
    then `fix` (what the user can do) when given.

    For a command about to spend long on them (training reads the training frames in every epoch and
    evaluates the test frames after each).
    """
    ids = dataset.frame_ids if frame_ids is None else list(frame_ids)
    bad = [e for e in (frame_error(dataset, f) for f in ids) if e is not None]
    if bad:
        more = f" (and {len(bad) - 1} more frame(s); list them all with python -m detbench.data.validate " \
               f"{dataset.root})" if len(bad) > 1 else ""
        raise DatasetError(f"{bad[0]}{more}{'; ' + fix if fix else ''}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m detbench.data.validate",
                                 description="Check every file of a detbench dataset and list all problems.")
    ap.add_argument("root", help="dataset folder (holds dataset.json)")
    ap.add_argument("--heights", type=height_or_rig_arg, nargs="+", default=None,
                    help="mounting heights to check, metres, or rigs by name (default: all heights and rigs of the "
                         "dataset)")
    ap.add_argument("--max-errors", type=int, default=50, help="stop after this many problems (default 50)")
    args = ap.parse_args(argv)
    rep = validate_dataset(args.root, args.heights, args.max_errors, progress=True)
    for n in rep.notes:
        print("note:", n)
    for w in rep.warnings:
        print("warning:", w)
    for e in rep.errors:
        print("error:", e)
    more = " (stopped early; fix these and run again)" if rep.truncated else ""
    print(f"{args.root}: {rep.num_frames} frames x {len(rep.heights)} heights checked, "
          f"{len(rep.errors)} problem(s){more}")
    return 0 if rep.ok else 1


if __name__ == "__main__":
    sys.exit(main())
