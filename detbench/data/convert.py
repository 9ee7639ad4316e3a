"""Convert OpenPCDet "custom" folders, one per mounting height, into one detbench dataset.

    python -m detbench.data.convert --src 0.5=/data/h3/0.5m --src 1.0=/data/h3/1.0m \
        --src 1.8=/data/h3/1.8m --out data/height3 [--pitch 1.8=2.5] [--frames-per-scene 200]

Each source folder holds `points/<id>.npy` (or `.bin`), `labels/<id>.txt`
(`x y z dx dy dz heading class`) and optionally `ImageSets/*.txt`, all in that LiDAR's own
frame (OpenPCDet's custom layout). The converter

- copies (or, with --link, hard-links) the point files unchanged and marks them
  `points_frame: "sensor"`; the reader converts them to the ground frame on load with the
  stored height and pitch;
- moves the labels of the reference height (the first --src) to the ground frame (z +
  height, pitch applied to the centre) and checks that the other heights' labels agree
  with them within --label-tolerance metres (labels are shared in the detbench layout);
- writes no meta files (`has_meta: false`): lanes are derived from the lateral offset with
  --lane-width, track ids are -1, scenes come from --frames-per-scene consecutive ids;
- splits by scene (--test-fraction), or keeps the source's ImageSets with --keep-split;
- prints, per height, the road-surface height it finds in the converted points of the
  first frame, a check that height and pitch are right (it should be close to 0 m).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.frame import DEFAULT_LANE_WIDTH, Sensor, height_key
from detbench.data.layout import (
    FORMAT_NAME, FORMAT_VERSION, INFO_FILE, DatasetInfo, HeightInfo, SceneRule, assign_splits, check_frame_id,
    imageset_path, label_path, points_path,
)
from detbench.data.readers import format_labels, read_imageset, read_labels, read_points
from detbench.data.transforms import boxes_sensor_to_ground, sensor_to_ground
from detbench.utils.io import atomic_write_json, atomic_write_text


def paper_sensor(height: float, pitch_deg: float = 0.0) -> Sensor:
    """The Height3 paper's LiDAR (Table II: 128 x 480, 180 deg HFOV, 150 m, 25 deg VFOV) at `height` m.

    With pitch 0 the 1.8 m sensor gets the table's -15..10 deg field (the downward tilt
    folded into the field); with a pitch the field is the symmetric -12.5..12.5 deg.
    """
    hk = height_key(height)
    vfov = (-15.0, 10.0) if hk == "1.8" and pitch_deg == 0.0 else (-12.5, 12.5)
    return Sensor(height=float(hk), pitch_deg=float(pitch_deg), vfov_deg=vfov, hfov_deg=180.0, channels=128,
                  h_samples=480, max_range=150.0, name=f"h3-{hk}")


def road_surface_z(points: np.ndarray) -> float:
    """Estimated road height (m) in ground-frame points: 5th percentile of z for 5 < x < 40 m, |y| < 4 m."""
    p = np.asarray(points)
    sel = p[(p[:, 0] > 5) & (p[:, 0] < 40) & (np.abs(p[:, 1]) < 4)]
    return float(np.percentile(sel[:, 2], 5)) if len(sel) >= 20 else float("nan")


def _pairs(items, what: str) -> dict[str, str]:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"--{what} {it!r}: write HEIGHT=VALUE, e.g. 1.8=/data/h3/1.8m")
        k, v = it.split("=", 1)
        out[height_key(float(k))] = v
    return out


def convert_openpcdet_custom(sources: dict[str, str | os.PathLike], out: str | os.PathLike, *,
                             pitch_deg: dict[str, float] | None = None, labels_frame: str = "sensor",
                             frames_per_scene: int = 200, test_fraction: float = 1 / 3, keep_split: bool = False,
                             lane_width: float | None = None, label_tolerance: float = 0.05, link: bool = False,
                             overwrite: bool = False, progress: bool = True) -> DatasetInfo:
    """Build a detbench dataset at `out` from per-height OpenPCDet custom folders.

    sources: height key ("0.5") -> folder; pitch_deg: height key -> pitch in degrees
    (positive = down; default 0); labels_frame: "sensor" (labels in each LiDAR's frame) or
    "ground". Returns the DatasetInfo written to out/dataset.json. See the module doc.
    """
    if not sources:
        raise ValueError("no sources given; pass --src HEIGHT=FOLDER for each height")
    if labels_frame not in ("sensor", "ground"):
        raise ValueError(f"labels_frame must be 'sensor' or 'ground', got {labels_frame!r}")
    out = Path(out)
    if (out / INFO_FILE).exists() and not overwrite:
        raise FileExistsError(f"{out / INFO_FILE}: a dataset already exists here; choose another --out or "
                              f"pass --overwrite")
    pitch_deg = {height_key(float(k)): float(v) for k, v in (pitch_deg or {}).items()}
    srcs = {height_key(float(k)): Path(v) for k, v in sources.items()}
    sensors = {k: paper_sensor(float(k), pitch_deg.get(k, 0.0)) for k in srcs}
    ref_key = next(iter(srcs))
    exts: dict[str, str] = {}
    for k, src in srcs.items():
        if not (src / "labels").is_dir() or not (src / "points").is_dir():
            raise MissingFileError("expected an OpenPCDet custom folder with points/ and labels/ inside", path=src)
        first = next(iter(sorted((src / "points").iterdir())), None)
        if first is None:
            raise MissingFileError("points/ is empty", path=src / "points")
        exts[k] = first.suffix
    ref_src = srcs[ref_key]
    ids = sorted(p.stem for p in (ref_src / "labels").glob("*.txt"))
    if not ids:
        raise MissingFileError("no label files (*.txt) found", path=ref_src / "labels")
    for fid in ids:
        check_frame_id(fid, str(ref_src / "labels" / f"{fid}.txt"))

    iterator = ids
    if progress:
        from tqdm import tqdm

        iterator = tqdm(ids, desc="convert", unit="frame")
    classes: list[str] = []
    road_z: dict[str, float] = {}
    for k in srcs:
        (out / "points" / k).mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    for fid in iterator:
        ground = {}
        for k, src in srcs.items():
            boxes, names = read_labels(src / "labels" / f"{fid}.txt")
            if labels_frame == "sensor":
                boxes = boxes_sensor_to_ground(boxes, float(k), sensors[k].pitch_deg)
            ground[k] = (boxes, names)
        rb, rn = ground[ref_key]
        for k, (b, n) in ground.items():
            if k == ref_key:
                continue
            if len(b) != len(rb) or (len(b) and (np.abs(b[:, :6] - rb[:, :6]).max() > label_tolerance
                                                 or not np.array_equal(n, rn))):
                raise DatasetError(
                    f"labels at {k} m do not match those at {ref_key} m after moving both to the ground frame "
                    f"(tolerance {label_tolerance} m); check --pitch/--labels-frame, or that both folders hold the "
                    f"same frames", path=srcs[k] / "labels" / f"{fid}.txt")
        for n in rn.tolist():
            if n not in classes:
                classes.append(n)
        atomic_write_text(label_path(out, fid), format_labels(rb, rn))
        for k, src in srcs.items():
            sp = src / "points" / f"{fid}{exts[k]}"
            pts = read_points(sp)  # validates before copying
            dst = points_path(out, k, fid, exts[k])
            if k not in road_z:
                road_z[k] = road_surface_z(sensor_to_ground(pts, float(k), sensors[k].pitch_deg))
            dst.unlink(missing_ok=True)
            if link:
                os.link(sp, dst)
            else:
                shutil.copyfile(sp, dst)

    rule = SceneRule(kind="block", frames_per_scene=frames_per_scene)
    scene_of = rule.scenes(ids)
    if keep_split:
        train = read_imageset(ref_src / "ImageSets" / "train.txt")
        test_name = "test.txt" if (ref_src / "ImageSets" / "test.txt").is_file() else "val.txt"
        test = read_imageset(ref_src / "ImageSets" / test_name)
        known = set(ids)
        missing = [f for f in train + test if f not in known]
        if missing:
            raise DatasetError(f"{len(missing)} listed id(s) have no label file (e.g. {missing[0]!r})",
                               path=ref_src / "ImageSets")
        split = {"rule": "kept", "source": str(ref_src / "ImageSets"), "num_train": len(train), "num_test": len(test)}
    else:
        train, test, split = assign_splits(ids, scene_of, test_fraction)
        split = dict(split, num_train=len(train), num_test=len(test))
    atomic_write_text(imageset_path(out, "train"), "".join(f + "\n" for f in train))
    atomic_write_text(imageset_path(out, "test"), "".join(f + "\n" for f in test))
    heights = {k: HeightInfo(key=k, sensor=sensors[k], points_frame="sensor", points_ext=exts[k]) for k in srcs}
    info = DatasetInfo(heights=heights, classes=classes or ["car"], split=split, has_meta=False,
                       lane_width=DEFAULT_LANE_WIDTH if lane_width is None else float(lane_width),
                       scene_rule=rule, num_frames=len(ids), format=FORMAT_NAME, version=FORMAT_VERSION,
                       source={"kind": "external", "converted_from": {k: str(v) for k, v in srcs.items()},
                               "labels_frame": labels_frame, "road_surface_z_m": road_z})
    atomic_write_json(out / INFO_FILE, info.to_dict())
    return info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m detbench.data.convert", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", action="append", required=True, metavar="HEIGHT=DIR",
                    help="an OpenPCDet custom folder and its mounting height in metres; repeat per height "
                         "(the first one is the label reference)")
    ap.add_argument("--out", required=True, help="output dataset folder")
    ap.add_argument("--pitch", action="append", metavar="HEIGHT=DEG", default=[],
                    help="sensor pitch in degrees, positive = down, for a height (default 0)")
    ap.add_argument("--labels-frame", choices=("sensor", "ground"), default="sensor",
                    help="frame of the source labels: each LiDAR's own frame (default) or the ground frame")
    ap.add_argument("--frames-per-scene", type=int, default=200,
                    help="consecutive frame ids forming one scene (Height3: 200 frames = 100 s at 2 Hz)")
    ap.add_argument("--test-fraction", type=float, default=1 / 3, help="share of scenes in the test split")
    ap.add_argument("--keep-split", action="store_true",
                    help="keep the source's ImageSets/train.txt and test.txt (or val.txt) instead of re-splitting")
    ap.add_argument("--lane-width", type=float, default=None,
                    help="lane width in metres used to derive lanes from y on load (default 3.5)")
    ap.add_argument("--label-tolerance", type=float, default=0.05,
                    help="max difference in metres between the heights' ground-frame labels (default 0.05)")
    ap.add_argument("--link", action="store_true", help="hard-link point files instead of copying them")
    ap.add_argument("--overwrite", action="store_true", help="write into a folder that already holds a dataset")
    args = ap.parse_args(argv)
    info = convert_openpcdet_custom(
        _pairs(args.src, "src"), args.out, pitch_deg={k: float(v) for k, v in _pairs(args.pitch, "pitch").items()},
        labels_frame=args.labels_frame, frames_per_scene=args.frames_per_scene, test_fraction=args.test_fraction,
        keep_split=args.keep_split, lane_width=args.lane_width, label_tolerance=args.label_tolerance,
        link=args.link, overwrite=args.overwrite)
    for k, z in info.source["road_surface_z_m"].items():
        if not np.isfinite(z):
            print(f"{k} m: too few points in front of the car to find the road surface (check by eye)")
            continue
        flag = "ok" if abs(z) < 0.15 else "CHECK --pitch / the height: the road should be near 0 m"
        print(f"{k} m: road surface at z = {z:+.2f} m in the converted points ({flag})")
    print(f"{args.out}: {info.num_frames} frames, heights {list(info.heights)}, "
          f"{info.split.get('num_train')} train / {info.split.get('num_test')} test")
    return 0


if __name__ == "__main__":
    sys.exit(main())
