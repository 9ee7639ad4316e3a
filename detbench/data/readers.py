"""Readers and formatters of the per-frame files, each validating what it reads.

- points: `.npy` (N, 4) float32 or KITTI-style `.bin` (raw little-endian float32, `columns`
  values a point, the first four x y z intensity);
- labels: text, one vehicle a line `x y z dx dy dz heading class` (metres, radians);
- meta: JSON side file with scene id, timestamp, ego state, track ids, lanes, sensors.

Every problem raises `DatasetError` naming the file (and the 1-based line for labels),
what is wrong and how to fix it; content is quoted as a short, escaped excerpt. Each reader takes
`root`, the folder the user named (default: the folder the file is in), and refuses a file that is
a link to somewhere outside it.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from detbench.data.errors import DatasetError, MissingFileError
from detbench.data.frame import BOX_DIM, POINT_DIM, Sensor
from detbench.data.layout import check_frame_id
from detbench.data.transforms import wrap_heading
from detbench.utils.untrusted import MAX_DEPTH, clip, excerpt, outside_folder, structure_problem

LABEL_COLUMNS = ("x", "y", "z", "dx", "dy", "dz", "heading", "class")


def check_inside(path: Path, root: str | os.PathLike | None) -> None:
    """DatasetError when `path` is a link (or lies under one) leading outside `root` (default: its folder)."""
    root = path.parent if root is None else root
    target = outside_folder(path, root)
    if target is not None:
        raise DatasetError(f"a link to {target}, outside {root}; detbench reads only the files inside the folder "
                           f"it is given (a link out of it could expose any file); copy the file into the folder",
                           path=path)


def _npy_data_problem(path: Path) -> str | None:
    """What is wrong with a .npy file's header against its size (a header claiming more data than the file
    holds would make numpy allocate it all), or None."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                           (2, 0): np.lib.format.read_array_header_2_0}.get(version)
            if read_header is None:
                return f".npy format version {version[0]}.{version[1]} is not read; save with np.save"
            shape, _, dtype = read_header(fh)
            data_bytes = os.fstat(fh.fileno()).st_size - fh.tell()
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as e:
        return f"cannot read as .npy ({clip(e)}); the file is truncated or not a numpy file; re-create it"
    if dtype.hasobject:
        return None  # np.load(allow_pickle=False) refuses it
    need = math.prod(shape) * dtype.itemsize
    if need != data_bytes:
        return (f"the header says shape {excerpt(shape)} of {dtype.str} ({need:,} bytes) but the file holds "
                f"{data_bytes:,} bytes of data; it is truncated or damaged; re-create it")
    return None


# --------------------------------------------------------------------------- points

def read_points(path: str | os.PathLike, columns: int = POINT_DIM, *, root: str | os.PathLike | None = None
                ) -> np.ndarray:
    """Read one point cloud: `.npy` or `.bin` -> (N, 4) float32 x, y, z, intensity.

    `.npy` must hold a 2-D float32 array with 4 columns. `.bin` is a raw little-endian float32
    file with `columns` values a point (KITTI: 4); only the first four are kept. Points are
    checked to be finite and plausible (coordinates within MAX_POINT_COORD metres, no
    subnormal floats); a .bin file that holds float64 or big-endian values is named as such,
    with a conversion that keeps the values; the .npy header must describe the data the file
    holds. Raises MissingFileError / DatasetError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError("points file not found; re-create the frame or remove its id from ImageSets",
                               path=path)
    check_inside(path, root)
    ext = path.suffix.lower()
    if ext == ".npy":
        if path.stat().st_size == 0:
            raise DatasetError("the file is empty (0 bytes), as an interrupted copy or a full disk leaves it; "
                               "copy or re-create it", path=path)
        problem = _npy_data_problem(path)
        if problem:
            raise DatasetError(problem, path=path)
        try:
            arr = np.load(path, allow_pickle=False)
        except ValueError as e:
            raise DatasetError(f"cannot read as .npy ({clip(e)}); save points with np.save(path, "
                               f"points.astype(np.float32))", path=path) from None
        except (OSError, EOFError) as e:
            raise DatasetError(f"cannot read as .npy ({clip(e)}); the file is truncated or not a numpy file; "
                               f"re-create it", path=path) from None
        if arr.ndim != 2 or arr.shape[1] != POINT_DIM:
            raise DatasetError(f"points array has shape {arr.shape}, expected (N, {POINT_DIM}) "
                               f"(x, y, z, intensity); save a 2-D array with 4 columns", path=path)
        if arr.dtype != np.float32:
            raise DatasetError(f"points array has dtype {arr.dtype}, expected float32; save "
                               f"points.astype(np.float32)", path=path)
    elif ext == ".bin":
        if columns < POINT_DIM:
            raise ValueError(f"columns must be >= {POINT_DIM}, got {columns}")
        size = path.stat().st_size
        if size % (4 * columns):
            raise DatasetError(f"file size {size} bytes is not a multiple of {4 * columns} "
                               f"({columns} float32 values a point); the file is truncated or has "
                               f"another column count (set bin_columns in dataset.json)", path=path)
        full = np.fromfile(path, dtype="<f4").reshape(-1, columns)
        if _implausible_rows(full).size:
            _refuse_misread_bin(path, columns, size)
        arr = np.ascontiguousarray(full[:, :POINT_DIM]) if columns != POINT_DIM else full
        arr = arr.astype(np.float32, copy=False)
    else:
        raise DatasetError(f"unknown points extension {ext!r}; use .npy or .bin", path=path)
    finite = np.isfinite(arr)
    if not finite.all():
        bad_rows = np.flatnonzero(~finite.all(axis=1))
        raise DatasetError(f"{bad_rows.size} point(s) have NaN or inf values (first at row {int(bad_rows[0])}); "
                           f"drop them (points[np.isfinite(points).all(1)]) and save again", path=path)
    bad_rows = _implausible_rows(arr)
    if bad_rows.size:
        raise DatasetError(f"{bad_rows.size} point(s) have implausible values (first at row {int(bad_rows[0])}: "
                           f"{_row_text(arr[bad_rows[0]])}; a coordinate beyond {MAX_POINT_COORD:g} m or a "
                           f"subnormal float): the points were not written as float32 metres; re-create the file "
                           f"from the source data", path=path)
    return arr


# a coordinate no LiDAR measures (metres); beyond it, the bytes were read with the wrong dtype or byte order
MAX_POINT_COORD = 1e4
_F32_TINY = float(np.finfo(np.float32).tiny)


def _implausible_rows(arr: np.ndarray) -> np.ndarray:
    """Rows of (N, C) points holding NaN / inf, a coordinate beyond MAX_POINT_COORD, or a subnormal value:
    what float64 values or big-endian floats read as little-endian float32 give, and measured points do not."""
    with np.errstate(all="ignore"):
        a = np.asarray(arr, dtype=np.float64)
        mag = np.abs(a)
        bad = ~np.isfinite(a) | ((mag > 0) & (mag < _F32_TINY))
        bad[:, :3] |= mag[:, :3] > MAX_POINT_COORD
    return np.flatnonzero(bad.any(axis=1))


def _row_text(row: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(v):.3g}" for v in row[:POINT_DIM]) + ")"


def _refuse_misread_bin(path: Path, columns: int, size: int) -> None:
    """A .bin file whose little-endian float32 reading holds implausible values: DatasetError naming what the
    bytes are when another reading (big-endian float32, float64) gives plausible points, with a conversion
    that keeps the values; else with the non-finite rows' fix when those are the only problem; else naming the
    implausible values. Returns when the file reads as measured points after all (never: called on a problem)."""
    q = str(path).replace("'", "\\'")
    readings = [(">f4", "big-endian float32", f"np.fromfile('{q}', '>f4').astype('<f4').tofile('{q}')")]
    if size % (8 * columns) == 0:
        readings.append(("<f8", "float64", f"np.fromfile('{q}', '<f8').astype('<f4').tofile('{q}')"))
    for dtype, what, fix in readings:
        other = np.fromfile(path, dtype=dtype).reshape(-1, columns)
        if other.size and not _implausible_rows(other).size:
            raise DatasetError(f"the bytes are {what} values ({other.shape[0]} points of {columns} values, all "
                               f"plausible), not the little-endian float32 a .bin file holds: read as float32 they "
                               f"give NaN, inf or implausible values; convert the file (the values kept) with "
                               f"{fix}", path=path)
    full = np.fromfile(path, dtype="<f4").reshape(-1, columns)
    if not np.isfinite(full).all() and not _implausible_rows(np.where(np.isfinite(full), full, 0.0)).size:
        return  # only NaN / inf rows: the caller names them
    bad = _implausible_rows(full)
    raise DatasetError(f"{bad.size} of {full.shape[0]} point(s) read as little-endian float32 with {columns} values "
                       f"a point have NaN, inf or implausible values (first at row {int(bad[0])}: "
                       f"{_row_text(full[bad[0]])}), and no other dtype or byte order fits either: check how the "
                       f"file was written (float32, little-endian, bin_columns in dataset.json) and re-create it",
                       path=path)


# --------------------------------------------------------------------------- labels

def _parse_label_line(s: str, path, lineno: int, known: set | None) -> tuple[list[float], str]:
    """One stripped, non-comment label line -> (7 values, class name); DatasetError naming file and line."""
    parts = s.split()
    if len(parts) != len(LABEL_COLUMNS):
        raise DatasetError(f"{len(parts)} columns, expected {len(LABEL_COLUMNS)}: "
                           f"{' '.join(LABEL_COLUMNS)} (got {excerpt(s)})", path=path, line=lineno)
    vals = []
    for col, tok in zip(LABEL_COLUMNS[:7], parts[:7]):
        try:
            v = float(tok)
        except ValueError:
            raise DatasetError(f"column {col!r} is {excerpt(tok)}, not a number; write a decimal number "
                               f"(metres or radians)", path=path, line=lineno) from None
        if not math.isfinite(v):
            raise DatasetError(f"column {col!r} is {clip(tok, 40)}; label values must be finite", path=path,
                               line=lineno)
        vals.append(v)
    for col, v in zip(("dx", "dy", "dz"), vals[3:6]):
        if not v > 0:
            raise DatasetError(f"size {col} is {v:g}; box sizes must be > 0 metres (dx length, dy width, dz "
                               f"height): a box without volume holds no point, so the vehicle would count as "
                               f"one the LiDAR missed", path=path, line=lineno)
    name = parts[7]
    try:
        float(name)
        is_number = True
    except ValueError:
        is_number = False
    if is_number:
        raise DatasetError(f"class is {excerpt(name)}, a number; the 8th column is the class name "
                           f"(e.g. car); check the column order x y z dx dy dz heading class",
                           path=path, line=lineno)
    if known is not None and name not in known:
        raise DatasetError(f"class {excerpt(name)} is not in the dataset's classes {excerpt(sorted(known))}; add it to "
                           f"'classes' in dataset.json or fix the label", path=path, line=lineno)
    return vals, name


def _label_lines(text: str):
    """(line number, stripped text) of the lines holding a label (blank and '#' lines skipped)."""
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield lineno, s


def label_problems(text: str, path: str | os.PathLike = "<labels>", classes=None) -> list[DatasetError]:
    """Every malformed line of label text (not just the first), each a DatasetError naming file and line."""
    known = None if classes is None else set(classes)
    problems = []
    for lineno, s in _label_lines(text):
        try:
            _parse_label_line(s, path, lineno, known)
        except DatasetError as e:
            problems.append(e)
    return problems


def parse_labels(text: str, path: str | os.PathLike = "<labels>", classes=None) -> tuple[np.ndarray, np.ndarray]:
    """Parse label text -> (boxes (M, 7) float32, classes (M,) str).

    One vehicle a line: `x y z dx dy dz heading class` (whitespace separated; metres and
    radians; ground frame, z the box centre). Blank lines and lines starting with '#' are
    skipped. Headings beyond +-pi (by more than float32 rounding) are wrapped into
    [-pi, pi). If `classes` is given, every class must
    be one of them. The first malformed line raises DatasetError (`label_problems` lists all).
    """
    rows: list[list[float]] = []
    names: list[str] = []
    known = None if classes is None else set(classes)
    for lineno, s in _label_lines(text):
        vals, name = _parse_label_line(s, path, lineno, known)
        rows.append(vals)
        names.append(name)
    boxes = np.asarray(rows, dtype=np.float64).reshape(-1, BOX_DIM)
    if len(boxes):
        h = boxes[:, 6]
        # wrap only headings beyond +-pi by more than float32 rounding, so labels round-trip bit-exactly
        lim = float(np.float32(math.pi))
        out = (h < -lim) | (h > lim)
        if out.any():
            h[out] = wrap_heading(h[out])
    return boxes.astype(np.float32), np.asarray(names, dtype=str).reshape(-1)


def read_labels(path: str | os.PathLike, classes=None, *, root: str | os.PathLike | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Read ROOT/labels/<id>.txt -> (boxes (M, 7) float32, classes (M,) str); see `parse_labels`."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError("label file not found; every frame id in ImageSets needs labels/<id>.txt "
                               "(an empty file when there are no vehicles)", path=path)
    check_inside(path, root)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError("not UTF-8 text; labels are plain text lines 'x y z dx dy dz heading class'",
                           path=path) from None
    return parse_labels(text, path, classes)


def _fmt(v) -> str:
    return str(v)  # numpy float32 prints the shortest text that reads back to the same float32


def format_labels(boxes: np.ndarray, classes) -> str:
    """Label text for (M, 7) float32 boxes and (M,) class names; reads back bit-exactly."""
    b = np.asarray(boxes, dtype=np.float32).reshape(-1, BOX_DIM)
    names = list(classes)
    if len(names) != len(b):
        raise ValueError(f"{len(names)} class names for {len(b)} boxes")
    lines = []
    for row, name in zip(b, names):
        name = str(name)
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"class name {name!r} must be non-empty without spaces")
        lines.append(" ".join(_fmt(v) for v in row) + " " + name)
    return "\n".join(lines) + ("\n" if lines else "")


# --------------------------------------------------------------------------- meta

def _int_list(d: dict, key: str, m: int, path: Path) -> np.ndarray:
    val = d.get(key)
    if not isinstance(val, list):
        raise DatasetError(f"{key!r} must be a list of {m} integers (one per label line)", path=path)
    if len(val) != m:
        raise DatasetError(f"{key!r} has {len(val)} entries but the label file has {m} boxes; "
                           f"the meta and label files are from different frames - re-create them", path=path)
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in val):
        bad = next(v for v in val if not isinstance(v, int) or isinstance(v, bool))
        raise DatasetError(f"{key!r} holds {excerpt(bad)}; entries must be integers", path=path)
    return np.asarray(val, dtype=np.int64).reshape(-1)


def read_meta(path: str | os.PathLike, frame_id: str, num_boxes: int, *, root: str | os.PathLike | None = None
              ) -> dict:
    """Read ROOT/meta/<id>.json, validated against the frame id and the label count.

    Returns a dict with scene_id (str), timestamp (float, seconds), ego (dict), track_ids
    (M,) int64, lanes (M,) int64 and sensors (dict height key -> Sensor, may be empty).
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError("meta file not found; dataset.json says has_meta is true, so every frame "
                               "needs meta/<id>.json (or set has_meta to false to derive lanes from y)",
                               path=path)
    check_inside(path, root)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        line = getattr(e, "lineno", None)
        raise DatasetError(f"not valid JSON ({clip(getattr(e, 'msg', e))}); re-create the file", path=path,
                           line=line) from None
    except RecursionError:
        raise DatasetError(f"not read: it is nested deeper than {MAX_DEPTH} levels; re-create the file",
                           path=path) from None
    problem = structure_problem(d)
    if problem:
        raise DatasetError(f"not read: {problem}; re-create the file", path=path)
    if not isinstance(d, dict):
        raise DatasetError("meta must be a JSON object", path=path)
    if d.get("frame_id", frame_id) != frame_id:
        raise DatasetError(f"frame_id inside is {excerpt(d.get('frame_id'))} but the file is for {frame_id!r}; "
                           f"the file was renamed or copied - re-create it", path=path)
    scene_id = d.get("scene_id")
    if not isinstance(scene_id, str) or not scene_id:
        raise DatasetError("'scene_id' must be a non-empty string (the split is by scene)", path=path)
    ts = d.get("timestamp", 0.0)
    if not isinstance(ts, (int, float)) or isinstance(ts, bool) or not math.isfinite(ts):
        raise DatasetError(f"'timestamp' must be a finite number of seconds, got {excerpt(ts)}", path=path)
    ego = d.get("ego", {})
    if not isinstance(ego, dict):
        raise DatasetError("'ego' must be a JSON object", path=path)
    sensors = {}
    raw = d.get("sensors", {})
    if not isinstance(raw, dict):
        raise DatasetError("'sensors' must map height keys to sensor objects", path=path)
    for k, sd in raw.items():
        try:
            sensors[k] = Sensor.from_dict(sd)
        except (TypeError, ValueError) as e:
            raise DatasetError(f"sensors.{excerpt(k)} is invalid: {clip(e)}", path=path) from None
    return {
        "scene_id": scene_id,
        "timestamp": float(ts),
        "ego": ego,
        "track_ids": _int_list(d, "track_ids", num_boxes, path),
        "lanes": _int_list(d, "lanes", num_boxes, path),
        "sensors": sensors,
    }


def meta_dict(frame, sensors: dict | None = None) -> dict:
    """The side-file content for a Frame (see read_meta); `sensors` maps height keys to Sensor."""
    return {
        "frame_id": frame.frame_id,
        "scene_id": frame.scene_id,
        "timestamp": float(frame.timestamp),
        "ego": frame.ego,
        "track_ids": [int(v) for v in np.asarray(frame.track_ids).reshape(-1)],
        "lanes": [int(v) for v in np.asarray(frame.lanes).reshape(-1)],
        "sensors": {k: s.to_dict() for k, s in (sensors or {}).items()},
    }


def read_imageset(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> list[str]:
    """Frame ids of ROOT/ImageSets/<split>.txt (one a line; blank lines skipped; duplicates rejected)."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError("split list not found; create ImageSets/train.txt and test.txt with one "
                               "frame id a line (tools/simulate.py writes them)", path=path)
    check_inside(path, root)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError("not UTF-8 text; a split list holds one frame id a line", path=path) from None
    ids: list[str] = []
    seen: dict[str, int] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        try:
            check_frame_id(s)
        except DatasetError as e:
            raise DatasetError(e.reason, path=path, line=lineno) from None
        if s in seen:
            raise DatasetError(f"frame id {excerpt(s)} is listed twice (first at line {seen[s]}); remove the duplicate",
                               path=path, line=lineno)
        seen[s] = lineno
        ids.append(s)
    return ids
