"""Convert OpenPCDet "custom" folders, one per mounting height, into one detbench dataset.

    python -m detbench.data.convert --src 0.5=/data/h3/0.5m --src 1.0=/data/h3/1.0m \\
        --src 1.8=/data/h3/1.8m --out data/height3 [--pitch 1.8=2.5] [--frames-per-scene 200]

(`python tools/import_openpcdet.py` is the same command.) Each source folder holds
`points/<id>.npy` (or `.bin`), `labels/<id>.txt` (`x y z dx dy dz heading class`) and
`ImageSets/train.txt` + `val.txt` (OpenPCDet's custom layout). The converter

- finds the frame of each folder's points from its road (`--points-frame auto`, the
  default): near z = 0 m they are in the ego ground frame, near z = -height m in the LiDAR's
  own frame; it refuses to guess when the road cannot tell (say it with --points-frame);
- copies (or, with --link, hard-links) the point files unchanged and records their frame;
  the reader moves sensor-frame points to the ground frame on load with the stored height
  and pitch;
- moves the labels of the reference height (the first --src) to the ground frame (by default
  they are in the frame of the points, as OpenPCDet requires; --labels-frame says otherwise),
  checks that their bottoms sit on the road, and that the other heights' labels agree
  within --label-tolerance metres (labels are shared in the detbench layout);
- maps or drops classes with --class-map (default: drop OpenPCDet's non-vehicle classes
  Pedestrian, Cyclist, Person_sitting, DontCare; keep every other name) and prints how many
  label lines of each class it kept and dropped;
- keeps the source's split (ImageSets/train.txt, and val.txt or test.txt as detbench's test
  split; frames in neither are not converted), or re-splits by scene with --resplit; a kept
  split that puts frames of one scene in both splits (the test leaks into training) is
  warned about in one line naming how many scenes it cuts;
- writes no meta files (`has_meta: false`): lanes are derived from the lateral offset with
  --lane-width, track ids are -1, scenes come from --frames-per-scene consecutive ids;
- prints per height the road height it finds in the converted points of the first frame
  (should be close to 0 m) and writes OUT/convert_report.json and .md.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detbench.config import shipped_default
from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.frame import DEFAULT_LANE_WIDTH, Sensor, height_key
from detbench.data.layout import (
    DATASET_FOLDER, FORMAT_NAME, FORMAT_VERSION, INFO_FILE, POINT_EXTS, DatasetInfo, HeightInfo, SceneRule,
    assign_splits, check_frame_id, imageset_path, label_path, points_path,
)
from detbench.data.openpcdet import (
    DEFAULT_IMPORT_CLASS_MAP, ClassMap, class_count_lines, count_classes, frame_tolerance, guess_points_frame,
    label_bottom_z, level_road_z, parse_class_map, road_surface_z,
)
from detbench.data.readers import format_labels, read_imageset, read_labels, read_points
from detbench.data.transforms import boxes_sensor_to_ground, sensor_to_ground
from detbench.utils.atomic import atomic_write_json, atomic_write_text
from detbench.utils.folder_ownership import check_replaceable, write_owner
from detbench.utils.staged_folders import recover_staged, staged_folder

POINTS_FRAME_CHOICES = ("auto", "sensor", "ground")
LABELS_FRAME_CHOICES = ("points", "sensor", "ground")
SAMPLE_FRAMES = 5  # frames per source looked at to find the points' frame and check the labels


def paper_sensor(height: float, pitch_deg: float = 0.0) -> Sensor:
    """The Height3 paper's LiDAR (Table II: 128 x 480, 180 deg HFOV, 150 m, 25 deg VFOV) at `height` m.

    With pitch 0 the 1.8 m sensor gets the table's -15..10 deg field (the downward tilt
    folded into the field); with a pitch the field is the symmetric -12.5..12.5 deg.
    """
    hk = height_key(height)
    vfov = (-15.0, 10.0) if hk == "1.8" and pitch_deg == 0.0 else (-12.5, 12.5)
    return Sensor(height=float(hk), pitch_deg=float(pitch_deg), vfov_deg=vfov, hfov_deg=180.0, channels=128,
                  h_samples=480, max_range=150.0, name=f"h3-{hk}")


def _pairs(items, what: str) -> dict[str, str]:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise ValueError(f"--{what} {it!r}: write HEIGHT=VALUE, e.g. 1.8=/data/h3/1.8m")
        k, v = it.split("=", 1)
        try:
            out[height_key(float(k))] = v
        except ValueError:
            raise ValueError(f"--{what} {it!r}: {k!r} is not a mounting height in metres (e.g. 1.8)") from None
    return out


def _pitches(items) -> dict[str, float]:
    out = {}
    for k, v in _pairs(items, "pitch").items():
        try:
            out[k] = float(v)
        except ValueError:
            raise ValueError(f"--pitch {k}={v}: {v!r} is not a pitch in degrees (e.g. 1.8=2.5)") from None
        if not math.isfinite(out[k]) or abs(out[k]) >= 90:
            raise ValueError(f"--pitch {k}={v}: a pitch is degrees in (-90, 90), positive = down")
    return out


def _points_ext(src: Path) -> str:
    for p in sorted((src / "points").iterdir()):
        if p.is_file() and p.suffix in POINT_EXTS:
            return p.suffix
    raise MissingFileError(f"no point files ({' or '.join(POINT_EXTS)}) directly in points/; OpenPCDet's custom "
                           f"layout keeps points/<id>.npy", path=src / "points")


def _source_split(src: Path) -> tuple[list[str], list[str], str] | None:
    """(train ids, test ids, which files) of the source's ImageSets, or None when it has no train.txt."""
    sets = src / "ImageSets"
    if not (sets / "train.txt").is_file():
        return None
    train = read_imageset(sets / "train.txt", root=src)
    test_name = next((n for n in ("val.txt", "test.txt") if (sets / n).is_file()), None)
    test = read_imageset(sets / test_name, root=src) if test_name else []
    both = sorted(set(train) & set(test))
    if both:
        raise DatasetError(f"{len(both)} frame id(s) are in both train.txt and {test_name} (e.g. {both[0]!r}); a "
                           f"frame belongs to one split - fix the lists, or pass --resplit", path=sets)
    return train, test, f"train.txt + {test_name}" if test_name else "train.txt (no val.txt or test.txt)"


def _sample(ids: list[str], n: int = SAMPLE_FRAMES) -> list[str]:
    if len(ids) <= n:
        return list(ids)
    return [ids[round(i * (len(ids) - 1) / (n - 1))] for i in range(n)]


def _resolve_points_frame(k: str, src: Path, ext: str, sample: list[str], pitch: float, given: str,
                          checks: bool) -> tuple[str, dict]:
    """The frame of source `k`'s points: `given`, or found from the road of `sample` frames."""
    road = [level_road_z(read_points(src / "points" / f"{fid}{ext}", root=src), pitch) for fid in sample]
    guess, why = guess_points_frame(road, float(k))
    record = {"road_z_m": [round(v, 3) for v in road], "evidence": why}
    if given == "auto":
        if guess is None:
            raise DatasetError(
                f"cannot tell the frame of the {k} m points from the road: {why}. Say it with --points-frame sensor "
                f"(the LiDAR's own frame: road near -{k} m) or --points-frame ground (road near 0 m)",
                path=src / "points")
        return guess, dict(record, frame=guess, how="found from the road")
    if checks and guess is not None and guess != given:
        raise DatasetError(
            f"--points-frame {given}, but the road of the {k} m points says {guess} frame ({why}); fix the flag "
            f"(or leave it out to use what the road says), or pass --no-frame-check to convert anyway",
            path=src / "points")
    return given, dict(record, frame=given, how="given (--points-frame)")


def _check_label_bottoms(k: str, src: Path, sample: list[str], labels_frame: str, pitch: float, checks: bool
                         ) -> dict:
    """The boxes of `sample`, moved to the ground frame, must stand on the road (bottom near 0 m)."""
    bottoms = []
    for fid in sample:
        boxes, _ = read_labels(src / "labels" / f"{fid}.txt", root=src)
        if labels_frame == "sensor":
            boxes = boxes_sensor_to_ground(boxes, float(k), pitch)
        bottoms.extend(label_bottom_z(boxes).tolist())
    if len(bottoms) < 3:
        return {"boxes": len(bottoms), "median_bottom_z_m": None,
                "evidence": "fewer than 3 boxes ahead in the sampled frames: not checked"}
    med = float(np.median(bottoms))
    rec = {"boxes": len(bottoms), "median_bottom_z_m": round(med, 3)}
    h = float(k)
    tol = frame_tolerance(h)
    if abs(med) <= tol or not checks:
        return rec
    if labels_frame == "sensor" and abs(med - h) <= tol:
        fix = "they look already in the ground frame: pass --labels-frame ground"
    elif labels_frame == "ground" and abs(med + h) <= tol:
        fix = "they look in the LiDAR's own frame: pass --labels-frame sensor"
    else:
        fix = "check --labels-frame, the height and --pitch"
    how = "as --labels-frame sensor says" if labels_frame == "sensor" else "taken as ground-frame labels"
    raise DatasetError(
        f"the boxes of the {k} m labels ({how}) stand at z = {med:+.2f} m (median bottom of {len(bottoms)} boxes "
        f"ahead in {len(sample)} sampled frames), not on the road at 0 m; {fix} (or --no-frame-check to convert "
        f"anyway)", path=src / "labels")


def _check_settings(points_frame: str, labels_frame: str, frames_per_scene, test_fraction, lane_width,
                    label_tolerance) -> None:
    """ValueError naming the flag for a setting out of its range."""
    if points_frame not in POINTS_FRAME_CHOICES:
        raise ValueError(f"points_frame must be one of {', '.join(POINTS_FRAME_CHOICES)}, got {points_frame!r}")
    if labels_frame not in LABELS_FRAME_CHOICES:
        raise ValueError(f"labels_frame must be one of {', '.join(LABELS_FRAME_CHOICES)}, got {labels_frame!r}")
    if isinstance(frames_per_scene, bool) or not isinstance(frames_per_scene, (int, np.integer)) \
            or frames_per_scene < 1:
        raise ValueError(f"--frames-per-scene {frames_per_scene}: must be an integer >= 1 (consecutive frame ids "
                         f"forming one scene; Height3: 200)")
    if not 0.0 <= float(test_fraction) < 1.0:
        raise ValueError(f"--test-fraction {test_fraction}: must be in [0, 1) (the share of scenes in test)")
    if lane_width is not None and not (math.isfinite(float(lane_width)) and float(lane_width) > 0):
        raise ValueError(f"--lane-width {lane_width}: must be a positive number of metres (default 3.5)")
    if not (math.isfinite(float(label_tolerance)) and float(label_tolerance) >= 0):
        raise ValueError(f"--label-tolerance {label_tolerance}: must be a number of metres >= 0 (default 0.05)")


@dataclass(frozen=True)
class Source:
    """One height's OpenPCDet custom folder as the conversion reads it."""

    key: str  # height key, "1.8"
    folder: Path
    sensor: Sensor  # the paper's LiDAR at this height and --pitch
    ext: str  # suffix of its point files, ".npy" or ".bin"


def _open_sources(sources: dict, out: Path, pitch_deg: dict | None, overwrite: bool) -> dict[str, Source]:
    """The sources by height key, in the order given (the first is the label reference), after checking that
    `out` may be written (not a source, replaceable) and that every --pitch has its --src."""
    pitch = {height_key(float(k)): float(v) for k, v in (pitch_deg or {}).items()}
    folders = {height_key(float(k)): Path(v) for k, v in sources.items()}
    for k, src in folders.items():  # a replaced --out is removed whole: it must not hold a source
        if out.exists() and src.exists() and (out.resolve() == src.resolve() or out.resolve() in src.resolve().parents):
            raise ValueError(f"--out {out} holds the source folder {src} (--src {k}=...); choose another --out")
    recover_staged(out)
    check_replaceable(out, overwrite, DATASET_FOLDER)
    unknown = sorted(set(pitch) - set(folders))
    if unknown:
        raise ValueError(f"--pitch for height(s) {unknown} without a --src of that height")
    sensors = {k: paper_sensor(float(k), pitch.get(k, 0.0)) for k in folders}
    out_sources = {}
    for k, src in folders.items():
        if not (src / "labels").is_dir() or not (src / "points").is_dir():
            raise MissingFileError("expected an OpenPCDet custom folder with points/ and labels/ inside", path=src)
        out_sources[k] = Source(k, src, sensors[k], _points_ext(src))
    return out_sources


def _labelled_ids(ref: Source) -> list[str]:
    """The frame ids of the reference height's label files, sorted and checked."""
    labelled = sorted(p.stem for p in (ref.folder / "labels").glob("*.txt"))
    if not labelled:
        raise MissingFileError("no label files (*.txt) found", path=ref.folder / "labels")
    for fid in labelled:
        check_frame_id(fid, str(ref.folder / "labels" / f"{fid}.txt"))
    return labelled


@dataclass
class FrameChoice:
    """The frames a conversion converts and the source's own split of them (None: the split is made by scene)."""

    ids: list[str]
    kept: tuple[list[str], list[str], str] | None  # (train ids, test ids, the split files read)
    notes: list[str]


def choose_frames(ref: Source, labelled: list[str], keep_split: bool) -> FrameChoice:
    """With `keep_split`, the frames the reference source's ImageSets list (every labelled frame when it has
    no train.txt); otherwise every labelled frame."""
    notes: list[str] = []
    kept = _source_split(ref.folder) if keep_split else None
    if keep_split and kept is None:
        notes.append(f"{ref.folder / 'ImageSets' / 'train.txt'} not found: the split is re-made by scene")
    if kept is None:
        return FrameChoice(labelled, None, notes)
    train, test, split_files = kept
    known = set(labelled)
    missing = [f for f in train + test if f not in known]
    if missing:
        raise DatasetError(f"{len(missing)} listed id(s) have no label file (e.g. {missing[0]!r}); fix the lists "
                           f"or pass --resplit", path=ref.folder / "ImageSets")
    ids = sorted(train + test)
    left = len(labelled) - len(ids)
    if left:
        notes.append(f"{left} labelled frame(s) are in neither split list ({split_files}) and were not "
                     f"converted (pass --resplit to use every labelled frame)")
    return FrameChoice(ids, kept, notes)


@dataclass(frozen=True)
class SourceFrames:
    """The frames of one source's points and labels: `record` (dataset.json's source.frames entry: the frame,
    how it was found, the road and box-bottom evidence) and the labels' frame."""

    record: dict
    labels_frame: str

    @property
    def points_frame(self) -> str:
        return self.record["frame"]


def resolve_frames(srcs: dict[str, Source], sample: list[str], points_frame: str, labels_frame: str,
                   checks: bool) -> dict[str, SourceFrames]:
    """Each source's points frame and labels frame, found or checked on the `sample` frames before anything is
    written (DatasetError naming the flag when the road or the boxes contradict them)."""
    out = {}
    for k, src in srcs.items():
        for fid in sample:
            if not (src.folder / "points" / f"{fid}{src.ext}").is_file():
                raise MissingFileError(f"points of frame {fid!r} not found (the folders must hold the same frames)",
                                       path=src.folder / "points" / f"{fid}{src.ext}")
        pf, rec = _resolve_points_frame(k, src.folder, src.ext, sample, src.sensor.pitch_deg, points_frame, checks)
        lf = pf if labels_frame == "points" else labels_frame
        rec["labels"] = dict(frame=lf, **_check_label_bottoms(k, src.folder, sample, lf, src.sensor.pitch_deg, checks))
        out[k] = SourceFrames(rec, lf)
    return out


def _ground_labels(src: Source, fid: str, labels_frame: str, cmap: ClassMap, class_counts: dict | None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """One frame's labels of one source after the class map, in the ground frame; the lines are counted into
    `class_counts` when given."""
    boxes, names = read_labels(src.folder / "labels" / f"{fid}.txt", root=src.folder)
    if class_counts is not None:
        count_classes(names.tolist(), cmap, class_counts)
    keep, new_names = cmap.apply(names.tolist())
    boxes, names = boxes[keep], np.asarray(new_names, dtype=str).reshape(-1)
    if labels_frame == "sensor":
        boxes = boxes_sensor_to_ground(boxes, float(src.key), src.sensor.pitch_deg)
    return boxes, names


@dataclass
class CopiedFrames:
    """What copying the frames found: the classes written (in order of first appearance), the label lines per
    source class of the reference height, and each height's road height in its first converted frame (m)."""

    classes: list[str]
    class_counts: dict
    road_z: dict[str, float]


def copy_frames(staged: Path, ids: list[str], srcs: dict[str, Source], frames: dict[str, SourceFrames],
                cmap: ClassMap, label_tolerance: float, link: bool, progress: bool) -> CopiedFrames:
    """Write the reference height's labels (ground frame, after the class map) and copy or hard-link every
    height's point files into `staged`; DatasetError when another height's labels differ by more than
    `label_tolerance` metres."""
    ref_key = next(iter(srcs))
    iterator = ids
    if progress:
        from tqdm import tqdm

        iterator = tqdm(ids, desc="convert", unit="frame")
    copied = CopiedFrames(classes=[], class_counts={}, road_z={})
    for k in srcs:
        (staged / "points" / k).mkdir(parents=True, exist_ok=True)
    (staged / "labels").mkdir(parents=True, exist_ok=True)
    for fid in iterator:
        ground = {k: _ground_labels(src, fid, frames[k].labels_frame, cmap,
                                    copied.class_counts if k == ref_key else None) for k, src in srcs.items()}
        rb, rn = ground[ref_key]
        for k, (b, n) in ground.items():
            if k != ref_key and (len(b) != len(rb) or (len(b) and (np.abs(b[:, :6] - rb[:, :6]).max() > label_tolerance
                                                                   or not np.array_equal(n, rn)))):
                raise DatasetError(
                    f"labels at {k} m do not match those at {ref_key} m after moving both to the ground frame "
                    f"(tolerance {label_tolerance} m); check --pitch/--labels-frame, or that both folders hold the "
                    f"same frames", path=srcs[k].folder / "labels" / f"{fid}.txt")
        copied.classes += [n for n in dict.fromkeys(rn.tolist()) if n not in copied.classes]
        atomic_write_text(label_path(staged, fid), format_labels(rb, rn))
        for k, src in srcs.items():
            sp = src.folder / "points" / f"{fid}{src.ext}"
            pts = read_points(sp, root=src.folder)  # validates before copying
            dst = points_path(staged, k, fid, src.ext)
            if k not in copied.road_z:
                g = pts if frames[k].points_frame == "ground" else sensor_to_ground(pts, float(k), src.sensor.pitch_deg)
                copied.road_z[k] = road_surface_z(g)
            dst.unlink(missing_ok=True)
            if link:
                os.link(sp, dst)
            else:
                shutil.copyfile(sp, dst)
    return copied


def write_split(staged: Path, choice: FrameChoice, ref: Source, rule: SceneRule, test_fraction: float) -> dict:
    """Write ImageSets/train.txt and test.txt: the source's split when kept, else by scene; returns the split's
    description for dataset.json."""
    if choice.kept is not None:
        train, test, split_files = choice.kept
        split = {"rule": "kept", "source": str(ref.folder / "ImageSets"), "files": split_files,
                 "num_train": len(train), "num_test": len(test)}
    else:
        train, test, split = assign_splits(choice.ids, rule.scenes(choice.ids), test_fraction)
        split = dict(split, num_train=len(train), num_test=len(test))
    atomic_write_text(imageset_path(staged, "train"), "".join(f + "\n" for f in train))
    atomic_write_text(imageset_path(staged, "test"), "".join(f + "\n" for f in test))
    return split


def split_scene_warning(choice: FrameChoice, rule: SceneRule) -> str | None:
    """One line when the source's kept split puts frames of one scene (scenes by `rule`) in both train and test,
    naming how many scenes and --resplit; None when it keeps every scene whole or the split is made here."""
    if choice.kept is None:
        return None
    train, test, files = choice.kept
    scene_of = rule.scenes(choice.ids)
    shared = {scene_of[f] for f in train} & {scene_of[f] for f in test}
    if not shared:
        return None
    n_scenes = len(set(scene_of.values()))
    how = f"blocks of {rule.frames_per_scene} consecutive frame ids, --frames-per-scene"
    if n_scenes == 1:
        what = (f"all {len(choice.ids)} frames form one scene ({how}), and the source's split ({files}) puts frames "
                f"of it in both train and test")
    else:
        what = (f"the source's split ({files}) puts frames of {len(shared)} of {n_scenes} scenes ({how}) in both "
                f"train and test")
    return (f"{what}: frames of one scene are near-duplicates, so the test leaks into training; pass --resplit to "
            f"split by scene")


def convert_openpcdet_custom(sources: dict[str, str | os.PathLike], out: str | os.PathLike, *,
                             pitch_deg: dict[str, float] | None = None, points_frame: str = "auto",
                             labels_frame: str = "points", class_map: ClassMap | str | list | None = None,
                             frames_per_scene: int | None = None, test_fraction: float | None = None,
                             keep_split: bool = True, lane_width: float | None = None, label_tolerance: float = 0.05,
                             frame_checks: bool = True, link: bool = False, overwrite: bool = False,
                             progress: bool = True) -> DatasetInfo:
    """Build a detbench dataset at `out` from per-height OpenPCDet custom folders.

    sources: height key ("0.5") -> folder; pitch_deg: height key -> pitch in degrees (positive =
    down; default 0); points_frame: "auto" (from the road), "sensor" or "ground"; labels_frame:
    "points" (the frame of the points), "sensor" or "ground"; class_map: see
    `detbench.data.openpcdet.parse_class_map` (default: drop non-vehicle classes); keep_split: keep
    the source's ImageSets (else split by scene: `test_fraction` of the scenes to test, a scene
    being `frames_per_scene` consecutive ids; None takes configs/default.yaml `data:`).
    `frame_checks` False turns the road and box-bottom refusals off. Returns the DatasetInfo written
    to out/dataset.json; its `source` records what was found and done (frames, class counts, split,
    notes, and `warnings`: a kept split with frames of one scene in both splits, `split_scene_warning`).
    See the module doc.
    """
    frames_per_scene = shipped_default("data.frames_per_scene", frames_per_scene)
    test_fraction = shipped_default("data.test_fraction", test_fraction)
    if not sources:
        raise ValueError("no sources given; pass --src HEIGHT=FOLDER for each height")
    _check_settings(points_frame, labels_frame, frames_per_scene, test_fraction, lane_width, label_tolerance)
    cmap = class_map if isinstance(class_map, ClassMap) else parse_class_map(class_map, DEFAULT_IMPORT_CLASS_MAP)
    out = Path(out)
    srcs = _open_sources(sources, out, pitch_deg, overwrite)
    ref = next(iter(srcs.values()))
    choice = choose_frames(ref, _labelled_ids(ref), keep_split)
    frames = resolve_frames(srcs, _sample(choice.ids), points_frame, labels_frame, frame_checks)
    rule = SceneRule(kind="block", frames_per_scene=frames_per_scene)
    warning = split_scene_warning(choice, rule)

    # the new dataset is built beside `out` and swapped in whole when complete: a conversion that fails
    # or is killed leaves `out` as it was (see detbench.utils.staged_folders.staged_folder)
    recheck = lambda: check_replaceable(out, overwrite, DATASET_FOLDER)  # noqa: E731 - again under out's lock
    with staged_folder(out, what="a conversion", check=recheck) as staged:
        write_owner(staged, DATASET_FOLDER)
        copied = copy_frames(staged, choice.ids, srcs, frames, cmap, label_tolerance, link, progress)
        split = write_split(staged, choice, ref, rule, test_fraction)
        heights = {k: HeightInfo(key=k, sensor=src.sensor, points_frame=frames[k].points_frame, points_ext=src.ext)
                   for k, src in srcs.items()}
        info = DatasetInfo(heights=heights, classes=copied.classes or ["car"], split=split, has_meta=False,
                           lane_width=DEFAULT_LANE_WIDTH if lane_width is None else float(lane_width),
                           scene_rule=rule, num_frames=len(choice.ids), format=FORMAT_NAME, version=FORMAT_VERSION,
                           source={"kind": "external",
                                   "converted_from": {k: str(src.folder) for k, src in srcs.items()},
                                   "format": "openpcdet-custom", "frames": {k: f.record for k, f in frames.items()},
                                   "labels_frame": {k: f.labels_frame for k, f in frames.items()},
                                   "class_map": cmap.spec, "class_counts": copied.class_counts,
                                   "road_surface_z_m": copied.road_z, "notes": choice.notes,
                                   "warnings": [] if warning is None else [warning]})
        atomic_write_json(staged / "convert_report.json", {"out": str(out), "num_frames": info.num_frames,
                                                        "split": info.split, **info.source})
        atomic_write_text(staged / "convert_report.md", convert_report_markdown(info, out))
        atomic_write_json(staged / INFO_FILE, info.to_dict())  # last: marks a finished dataset
    return info


def convert_report_markdown(info: DatasetInfo, out: str | os.PathLike) -> str:
    """Markdown of what a conversion found and did (the same facts as dataset.json's `source`)."""
    s = info.source
    lines = [f"# OpenPCDet custom folders converted to {out}", "",
             f"{info.num_frames} frames; split {info.split.get('rule')}: {info.split.get('num_train')} train / "
             f"{info.split.get('num_test')} test.", "",
             "| height | source | points frame | how | labels frame | road in converted points |",
             "|---|---|---|---|---|---:|"]
    for k in info.heights:
        f = s["frames"][k]
        z = s["road_surface_z_m"].get(k)
        zt = "n/a" if z is None or not np.isfinite(z) else f"{z:+.2f} m"
        lines.append(f"| {k} m | `{s['converted_from'][k]}` | {f['frame']} | {f['how']}: {f['evidence']} | "
                     f"{s['labels_frame'][k]} | {zt} |")
    lines += ["", f"Classes (map `{s['class_map']}`), label lines of the reference height:", "",
              "| source class | kept | dropped | as |", "|---|---:|---:|---|"]
    for name, c in sorted(s["class_counts"].items()):
        lines.append(f"| {name} | {c['kept']} | {c['dropped']} | {c['as'] or '-'} |")
    if s.get("warnings"):
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in s["warnings"]]
    if s.get("notes"):
        lines += ["", "Notes:", ""] + [f"- {n}" for n in s["notes"]]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m detbench.data.convert", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  python -m detbench.data.convert --src 1.8=/data/h3/1.8m --out data/h3_1.8\n"
               "  python -m detbench.data.convert --src 0.5=/data/h3/0.5m --src 1.8=/data/h3/1.8m --pitch 1.8=2.5 \\\n"
               "      --out data/height3 --frames-per-scene 200\n"
               "  python -m detbench.data.convert --src 1.8=/data/mine --out data/mine --points-frame ground \\\n"
               "      --class-map 'Vehicle=car,*=-'\n"
               "Writes OUT/dataset.json (with what was found in its 'source'), OUT/convert_report.json and .md.\n"
               "Then: python -m detbench.data.validate OUT; python tools/analyze.py --data OUT")
    ap.add_argument("--src", action="append", required=True, metavar="HEIGHT=DIR",
                    help="an OpenPCDet custom folder and its LiDAR's mounting height in metres; repeat per height "
                         "(the first one is the label reference)")
    ap.add_argument("--out", required=True, help="output dataset folder")
    ap.add_argument("--pitch", action="append", metavar="HEIGHT=DEG", default=[],
                    help="sensor pitch in degrees, positive = down, for a height (default 0)")
    ap.add_argument("--points-frame", choices=POINTS_FRAME_CHOICES, default="auto",
                    help="frame of the source points: 'auto' (default) finds it from the road (near 0 m: ground "
                         "frame; near -HEIGHT m: the LiDAR's own frame) and stops when it cannot tell; 'sensor' or "
                         "'ground' say it")
    ap.add_argument("--labels-frame", choices=LABELS_FRAME_CHOICES, default="points",
                    help="frame of the source labels: 'points' (default: the frame of the points, as OpenPCDet "
                         "requires), 'sensor' (each LiDAR's own frame) or 'ground'; checked by the boxes standing "
                         "on the road")
    ap.add_argument("--class-map", action="append", default=None, metavar="SPEC",
                    help="rename or drop classes: comma-separated SRC=DST (SRC a class, case-insensitive, or '*' for "
                         "every other; DST a name, '-' to drop, '*' to keep), or a preset: vehicles-only (default: "
                         "drop Pedestrian, Cyclist, Person_sitting, DontCare; keep the rest), keep, vehicle (all -> "
                         "Vehicle). Repeat to combine: --class-map vehicles-only --class-map Vehicle=car. The lines "
                         "kept and dropped per class are printed")
    ap.add_argument("--frames-per-scene", type=int, default=shipped_default("data.frames_per_scene"),
                    help="consecutive frame ids forming one scene (default %(default)s; Height3: 200 frames = 100 s "
                         "at 2 Hz)")
    ap.add_argument("--resplit", action="store_true",
                    help="split by scene (--test-fraction) instead of keeping the source's ImageSets/train.txt and "
                         "val.txt (or test.txt), which is the default")
    ap.add_argument("--keep-split", action="store_true",
                    help="keep the source's split (the default; kept for older commands)")
    ap.add_argument("--test-fraction", type=float, default=shipped_default("data.test_fraction"),
                    help="with --resplit: share of scenes in test (default %(default).4g)")
    ap.add_argument("--lane-width", type=float, default=None,
                    help="lane width in metres used to derive lanes from y on load (default 3.5)")
    ap.add_argument("--label-tolerance", type=float, default=0.05,
                    help="max difference in metres between the heights' ground-frame labels (default 0.05)")
    ap.add_argument("--no-frame-check", action="store_true",
                    help="convert even when the road or the boxes' bottoms contradict --points-frame/--labels-frame")
    ap.add_argument("--link", action="store_true", help="hard-link point files instead of copying them")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace a dataset already in --out (the new one is built beside it and swapped in when "
                         "complete, so a failed or interrupted run leaves the old one)")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    from detbench.utils.cli import UserError

    args = build_parser().parse_args(argv)
    if args.resplit and args.keep_split:
        raise UserError("--resplit and --keep-split contradict each other; give one")
    try:
        info = convert_openpcdet_custom(
            _pairs(args.src, "src"), args.out,
            pitch_deg=_pitches(args.pitch),
            points_frame=args.points_frame, labels_frame=args.labels_frame, class_map=args.class_map,
            frames_per_scene=args.frames_per_scene, test_fraction=args.test_fraction, keep_split=not args.resplit,
            lane_width=args.lane_width, label_tolerance=args.label_tolerance, frame_checks=not args.no_frame_check,
            link=args.link, overwrite=args.overwrite, progress=not args.no_progress)
    except (DatasetError, FileNotFoundError, FileExistsError, ValueError, OSError) as e:
        raise UserError(str(e)) from None
    src = info.source
    for k in info.heights:
        f = src["frames"][k]
        print(f"{k} m: points in the {f['frame']} frame ({f['how']}: {f['evidence']}); labels in the "
              f"{src['labels_frame'][k]} frame")
    for k, z in src["road_surface_z_m"].items():
        if not np.isfinite(z):
            print(f"{k} m: too few points in front of the car to find the road surface (check by eye)")
            continue
        flag = "ok" if abs(z) < 0.15 else "CHECK --pitch / the height: the road should be near 0 m"
        print(f"{k} m: road surface at z = {z:+.2f} m in the converted points ({flag})")
    print(f"classes (map {src['class_map']}):")
    for line in class_count_lines(src["class_counts"]):
        print("  " + line)
    for n in src["notes"]:
        print("note: " + n)
    for w in src["warnings"]:
        print("warning: " + w, file=sys.stderr)
    out = Path(args.out)
    print(f"{args.out}: {info.num_frames} frames, heights {list(info.heights)}, "
          f"{info.split.get('num_train')} train / {info.split.get('num_test')} test "
          f"(split {info.split.get('rule')}); report: {out / 'convert_report.md'}")
    return 0


if __name__ == "__main__":
    from detbench.utils.cli import run_main

    sys.exit(run_main(main))
