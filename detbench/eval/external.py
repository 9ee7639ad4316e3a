"""Predictions written by other tools (OpenPCDet first) and a check that they are in the right frame.

Accepted by `load_predictions` (what `tools/eval.py --pred` reads):

- **OpenPCDet's `result.pkl`** (written by its tools/test.py): a list with one dict per frame
  holding `frame_id`, `boxes_lidar` (M, 7) or (M, 9) (x y z dx dy dz heading [vx vy]),
  `score` (M,) and `name` (M,). A pickle can run code when it is loaded, so it is read with a
  restricted unpickler that admits plain containers (list, dict, tuple, str, numbers),
  numpy arrays, dtypes and numpy scalars and refuses every other object type; still, open
  only result files you or your own tools wrote.
- **a folder of per-frame text files** `<frame_id>.txt`, each in one of these layouts
  (found from the first line; every line of a file must share it):
  - `detbench`: `x y z dx dy dz heading score [class]` (docs/evaluation.md, section 7);
  - `openpcdet-custom`: OpenPCDet's custom label line with the score appended,
    `x y z dx dy dz heading class score`;
  - `kitti`: OpenPCDet's KITTI text layout (`class truncated occluded alpha x1 y1 x2 y2 h w l
    x y z rotation_y score`) in the calibration-free camera frame OpenPCDet's
    `kitti_utils.transform_annotations_to_kitti_format` uses for datasets without camera
    calibration (the custom dataset's evaluation): camera (x, y, z) = (-y, -(z - dz/2), x) of
    the LiDAR box, rotation_y = -heading - pi/2. Files made with a real KITTI camera
    calibration are not this layout and are not supported.

Boxes are in metres and radians, OpenPCDet's unified box (the same as detbench's). With
`pred_frame="sensor"` they are moved from the LiDAR's own frame to the ground frame with
each frame's sensor height and pitch from the dataset. Classes: by default every class but
OpenPCDet's / KITTI's non-vehicle ones (Pedestrian, Cyclist, Person_sitting, DontCare) is
kept; a prediction without a class is kept.

`vertical_offset_check` compares the predictions with the ground truth in bird's-eye view:
predictions in the wrong frame sit a constant height (the mounting height) above or below
the vehicles, which 3D IoU turns into AP 0 without a word. When the median height offset of
the BEV matches exceeds a few decimetres it says so, with the flag that likely fixes it.
"""
from __future__ import annotations

import importlib
import io
import math
import pickle
import struct
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from detbench.config import shipped_default
from detbench.data.openpcdet import NON_VEHICLE_CLASSES
from detbench.data.transforms import boxes_sensor_to_ground, ground_to_sensor, wrap_heading
from detbench.data.detections import Detections
from detbench.eval.prediction_files import PREDICTION_SUFFIX
from detbench.utils.untrusted import clip, excerpt, outside_folder, structure_problem

PRED_FRAMES = ("ground", "sensor")
TEXT_LAYOUTS = {
    "detbench": "x y z dx dy dz heading score [class]",
    "openpcdet-custom": "x y z dx dy dz heading class score",
    "kitti": "class truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y score (camera frame without "
             "calibration)",
}
PICKLE_WARNING = ("a pickle can run code when loaded; detbench reads result.pkl with a restricted unpickler that "
                  "admits only plain containers, numbers, strings and numpy arrays, but open only result files you "
                  "or your own tools wrote")
# what a result.pkl of n bytes may allocate for its arrays: 8 n + 1 MiB (see _RestrictedUnpickler)
PICKLE_BYTES_PER_FILE_BYTE = 8
PICKLE_BYTES_FLOOR = 1 << 20

# frame-mismatch check
OFFSET_THRESHOLD_M = 0.3  # |median dz| above this is reported
MATCH_DISTANCE_M = 1.5  # BEV centre distance of a prediction matched to a vehicle
MIN_MATCHES = 5


class ExternalPredictions(NamedTuple):
    """Predictions of one frame as read: boxes (M, 7) float64, scores (M,) float64, class names (M,) str ('' = none)."""

    boxes: np.ndarray
    scores: np.ndarray
    names: np.ndarray


# --------------------------------------------------------------------------- result.pkl

_NUMPY_GLOBALS = {
    ("numpy", "ndarray"): ("numpy", "ndarray"),
    ("numpy", "dtype"): ("numpy", "dtype"),
    **{(f"numpy.{core}.multiarray", n): ("multiarray", n) for core in ("core", "_core") for n in ("_reconstruct",
                                                                                                  "scalar")},
    **{(f"numpy.{core}.numeric", "_frombuffer"): ("numeric", "_frombuffer") for core in ("core", "_core")},
}


def _numpy_global(where: str, name: str):
    if where == "numpy":
        return getattr(np, name)
    for base in ("numpy._core", "numpy.core"):
        try:
            return getattr(importlib.import_module(f"{base}.{where}"), name)
        except (ImportError, AttributeError):
            continue
    raise pickle.UnpicklingError(f"numpy has no {where}.{name}")


_NUMPY_CALLS = {name: _numpy_global(where, name) for where, name in
                (("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer"))}


class _Refused(pickle.UnpicklingError):
    """An object type the restricted unpickler does not admit, or arrays beyond what the file can hold."""


def _count(shape) -> int:
    """Elements of an array of `shape` (an int or a tuple of ints), in Python ints (no overflow)."""
    if type(shape) is int:
        shape = (shape,)
    if type(shape) is not tuple or any(type(d) is not int or d < 0 for d in shape):
        raise pickle.UnpicklingError(f"an array shape is {excerpt(shape)}, not a tuple of sizes")
    return math.prod(shape)


class _RestrictedUnpickler(pickle._Unpickler):
    """Admits plain containers, numbers, strings and numpy arrays / dtypes / scalars; nothing else.

    Arrays may together take at most `budget` bytes: their data is in the file, so a result file of n
    bytes holds at most n bytes of numbers (8 n for arrays of objects, a pointer for each element of at
    least one byte); a file asking for more lies about its arrays and is refused before they are
    allocated. Python's own unpickler (pickle._Unpickler) runs the file, as its memo is a dict: the C
    unpickler grows a list to any index a 7-byte file names.
    """

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, file, budget: int):
        super().__init__(file)
        self.budget = budget
        self.granted = 0
        self.numpy = {"ndarray": self._ndarray, "_reconstruct": self._reconstruct, "scalar": self._scalar,
                      "_frombuffer": self._frombuffer}  # one object each: _reconstruct knows its ndarray by identity

    def _grant(self, count: int, dtype) -> None:
        nbytes = count * np.dtype(dtype).itemsize
        if self.granted + nbytes > self.budget:
            raise _Refused(f"it asks for arrays of {nbytes + self.granted:,} bytes, more than its size on disk "
                           f"allows ({self.budget:,} bytes at most); it is damaged or was made to exhaust memory")
        self.granted += nbytes

    def _ndarray(self, shape, dtype=float, *args, **kwargs):
        self._grant(_count(shape), dtype)
        return np.ndarray(shape, dtype, *args, **kwargs)

    def _reconstruct(self, subtype, shape, dtype):
        if subtype is not self.numpy["ndarray"]:
            raise _Refused(f"it rebuilds an array of type {excerpt(subtype)}; only numpy arrays are read")
        self._grant(_count(shape), dtype)
        return _NUMPY_CALLS["_reconstruct"](np.ndarray, shape, dtype)

    def _scalar(self, dtype, *args):
        self._grant(1, dtype)
        return _NUMPY_CALLS["scalar"](dtype, *args)

    def _frombuffer(self, buf, dtype, shape, order):
        self._grant(_count(shape), dtype)
        return _NUMPY_CALLS["_frombuffer"](buf, dtype, shape, order)

    def find_class(self, module: str, name: str):
        if (module, name) == ("collections", "OrderedDict"):
            import collections

            return collections.OrderedDict
        target = _NUMPY_GLOBALS.get((module, name))
        if target is None:
            raise _Refused(
                f"it holds an object of type {excerpt(f'{module}.{name}')}; only plain containers and numpy "
                f"arrays are read (a pickle can run code, so other types are refused)")
        if target == ("numpy", "dtype"):
            return np.dtype
        return self.numpy[target[1]]

    def load_build(self):
        state, inst = self.stack[-1], self.stack[-2]
        if isinstance(inst, np.ndarray):  # (version,) shape, dtype, is_fortran, raw data: the array is reallocated
            if not isinstance(state, tuple) or len(state) not in (4, 5) or not isinstance(state[-3], np.dtype):
                raise pickle.UnpicklingError(f"an array's state is {excerpt(state)}, not numpy's")
            self._grant(_count(state[-4]), state[-3])
        elif not isinstance(inst, np.dtype):
            raise _Refused(f"it sets the state of {excerpt(inst)}; only numpy arrays and dtypes have one")
        pickle._Unpickler.load_build(self)

    dispatch[pickle.BUILD[0]] = load_build


def load_result_pkl(path: str | Path):
    """The object in an OpenPCDet result.pkl, read with the restricted unpickler. ValueError naming the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: result file not found; give the result.pkl OpenPCDet's tools/test.py "
                                f"wrote (output/.../eval/.../result.pkl)") from None
    budget = PICKLE_BYTES_PER_FILE_BYTE * len(data) + PICKLE_BYTES_FLOOR
    try:
        obj = _RestrictedUnpickler(io.BytesIO(data), budget).load()
    except _Refused as e:
        raise ValueError(f"{path}: not read: {e}") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
            UnicodeDecodeError, OverflowError, RecursionError, MemoryError, struct.error) as e:
        raise ValueError(f"{path}: not a readable pickle ({type(e).__name__}: {clip(e)}); is it OpenPCDet's "
                         f"result.pkl, complete?") from None
    problem = structure_problem(obj, max_values=len(data) + PICKLE_BYTES_FLOOR)
    if problem:
        raise ValueError(f"{path}: not read: {problem}; OpenPCDet's result.pkl is a flat list of per-frame dicts")
    return obj


def _frame_id(value, where: str) -> str:
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode("utf-8", "replace")
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool) and abs(int(value)) < 10 ** 18:
        value = str(int(value))
    if not isinstance(value, (str, np.str_)):
        raise ValueError(f"{where}: frame_id is {excerpt(value)}, not a frame id string")
    return str(value)


def _checked(boxes, scores, names, where: str) -> ExternalPredictions:
    try:
        b = np.asarray(boxes, dtype=np.float64)
        s = np.asarray(scores, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{where}: boxes_lidar and score must be numeric arrays") from None
    if b.size == 0:
        b = b.reshape(0, 7)
    if b.ndim != 2 or b.shape[1] < 7:
        raise ValueError(f"{where}: boxes_lidar has shape {b.shape}, expected (M, 7) x y z dx dy dz heading "
                         f"(or (M, 9) with velocities)")
    b = np.ascontiguousarray(b[:, :7])
    if len(s) != len(b):
        raise ValueError(f"{where}: {len(b)} boxes but {len(s)} scores")
    raw = None if names is None else np.asarray(names, dtype=object).reshape(-1)
    if raw is None or (len(raw) == 0 and len(b) == 0):
        n = np.full(len(b), "", dtype=object).astype(str)
    else:
        bad = next((v for v in raw if not isinstance(v, (str, bytes))), None)
        if bad is not None:
            raise ValueError(f"{where}: name holds {excerpt(bad)}, not a class name string")
        n = np.asarray([v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v) for v in raw], dtype=str)
        if len(n) != len(b):
            raise ValueError(f"{where}: {len(b)} boxes but {len(n)} names")
    if not (np.isfinite(b).all() and np.isfinite(s).all()):
        raise ValueError(f"{where}: non-finite box or score values")
    if len(b) and b[:, 3:6].min() < 0:
        raise ValueError(f"{where}: a negative box size (dx, dy, dz are lengths in metres)")
    return ExternalPredictions(b, s, n)


def predictions_from_result_pkl(path: str | Path) -> dict[str, ExternalPredictions]:
    """{frame_id: ExternalPredictions} of OpenPCDet's result.pkl (module doc); ValueError naming file and entry."""
    path = Path(path)
    data = load_result_pkl(path)
    if not isinstance(data, (list, tuple)):
        raise ValueError(f"{path}: holds a {type(data).__name__}, not OpenPCDet's list of per-frame dicts "
                         f"(frame_id, boxes_lidar, score, name)")
    out: dict[str, ExternalPredictions] = {}
    for i, d in enumerate(data):
        where = f"{path}: entry {i}"
        if not isinstance(d, dict):
            raise ValueError(f"{where} is {excerpt(d)}, not a dict with frame_id, boxes_lidar, score, name")
        missing = [k for k in ("frame_id", "boxes_lidar", "score") if k not in d]
        if missing:
            raise ValueError(f"{where} has no {', '.join(missing)} (keys: {excerpt(list(d))}); is this the "
                             f"result.pkl of OpenPCDet's tools/test.py?")
        fid = _frame_id(d["frame_id"], where)
        if fid in out:
            raise ValueError(f"{where}: frame {excerpt(fid)} appears twice")
        out[fid] = _checked(d["boxes_lidar"], d["score"], d.get("name"), f"{where} (frame {excerpt(fid)})")
    return out


# --------------------------------------------------------------------------- per-frame text

def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _line_layout(fields: list[str]) -> str | None:
    if len(fields) == 16 and not _is_number(fields[0]):
        return "kitti"
    if len(fields) in (8, 9) and _is_number(fields[7]):
        return "detbench"
    if len(fields) == 9 and not _is_number(fields[7]) and _is_number(fields[8]):
        return "openpcdet-custom"
    return None


def _layout_help(fields: list[str]) -> str:
    if len(fields) == 8 and not _is_number(fields[7]):
        return ("this is OpenPCDet's custom label line without a score; predictions need one: write "
                "'x y z dx dy dz heading class score'")
    if len(fields) == 15 and not _is_number(fields[0]):
        return "this is a KITTI line without the score column; predictions need the score as 16th field"
    return "accepted layouts: " + "; ".join(f"{k}: '{v}'" for k, v in TEXT_LAYOUTS.items())


def kitti_camera_to_lidar(values: np.ndarray) -> np.ndarray:
    """(M, 7) h w l x y z rotation_y of OpenPCDet's calibration-free KITTI layout -> LiDAR boxes (M, 7)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1, 7)
    h, w, length, cx, cy, cz, ry = (v[:, i] for i in range(7))
    heading = wrap_heading(-ry - np.pi / 2)
    return np.stack([cz, -cx, -cy + h / 2, length, w, h, heading], axis=1)


def parse_prediction_text(path: str | Path) -> tuple[ExternalPredictions, str | None]:
    """(predictions, layout) of one per-frame text file in any layout of TEXT_LAYOUTS (None for an empty file).

    ValueError naming the file and line on a malformed or mixed line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file; write one box per line") from None
    layout = None
    rows, scores, names = [], [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        this = _line_layout(fields)
        if this is None:
            raise ValueError(f"{path}:{lineno}: expected 8 numbers 'x y z dx dy dz heading score' and an optional "
                             f"class name (or another layout), got {len(fields)} field(s): {excerpt(line.strip())}; "
                             f"{_layout_help(fields)}")
        if layout is None:
            layout = this
        elif this != layout:
            raise ValueError(f"{path}:{lineno}: layout {this} but the file started in layout {layout}; write one "
                             f"layout per file")
        try:
            if layout == "detbench":
                vals = [float(v) for v in fields[:8]]
                box, score, name = vals[:7], vals[7], fields[8] if len(fields) == 9 else ""
            elif layout == "openpcdet-custom":
                box, name, score = [float(v) for v in fields[:7]], fields[7], float(fields[8])
            else:
                cam = [float(v) for v in fields[8:15]]
                box, name, score = kitti_camera_to_lidar(np.array(cam))[0].tolist(), fields[0], float(fields[15])
                float(fields[3])  # alpha must be a number too
        except ValueError:
            raise ValueError(f"{path}:{lineno}: a field that should be a number is not, in {excerpt(line.strip())} "
                             f"(layout {layout}: {TEXT_LAYOUTS[layout]})") from None
        if not all(math.isfinite(v) for v in [*box, score]):
            raise ValueError(f"{path}:{lineno}: non-finite value in {excerpt(line.strip())}")
        if min(box[3:6]) < 0:
            raise ValueError(f"{path}:{lineno}: negative box size in {excerpt(line.strip())}; sizes are lengths in "
                             f"metres")
        rows.append(box)
        scores.append(score)
        names.append(name)
    return ExternalPredictions(np.asarray(rows, dtype=np.float64).reshape(-1, 7), np.asarray(scores, np.float64),
                               np.asarray(names, dtype=str).reshape(-1)), layout


def read_prediction_texts(pred_dir: str | Path) -> tuple[dict[str, ExternalPredictions], dict[str, int]]:
    """({frame_id: predictions}, {layout: number of files}) of a folder of `<frame_id>.txt` files.

    Hidden files are ignored; any other entry than a .txt file, and a link to a file outside the folder, is an
    error naming it.
    """
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"{pred_dir}: prediction folder not found; give the folder holding one "
                                f"<frame_id>{PREDICTION_SUFFIX} file per frame, or OpenPCDet's result.pkl")
    out: dict[str, ExternalPredictions] = {}
    layouts: dict[str, int] = {}
    for path in sorted(pred_dir.iterdir()):
        if path.name.startswith("."):
            continue
        target = outside_folder(path, pred_dir)
        if target is not None:
            raise ValueError(f"{path}: a link to {target}, outside the prediction folder; detbench reads only the "
                             f"files inside the folder it is given (a link out of it could expose any file); copy "
                             f"the predictions into {pred_dir}")
        if not path.is_file() or path.suffix != PREDICTION_SUFFIX:
            hint = "; to read OpenPCDet's result file give --pred the .pkl itself" if path.suffix == ".pkl" else ""
            raise ValueError(f"{path}: unexpected entry in the prediction folder; it must hold only "
                             f"<frame_id>{PREDICTION_SUFFIX} files{hint}")
        preds, layout = parse_prediction_text(path)
        out[path.stem] = preds
        if layout is not None:
            layouts[layout] = layouts.get(layout, 0) + 1
    return out, layouts


# --------------------------------------------------------------------------- loading for the evaluator

@dataclass
class LoadedPredictions:
    """What `load_predictions` hands the evaluator: ground-frame predictions of the evaluated frames."""

    predictions: dict[str, Detections]  # numpy: boxes (M, 7) float64, scores (M,), labels 0
    skipped: list[str]  # frame ids of other splits of the dataset
    info: dict  # for the report: format, layouts, frame, sensors, classes kept/dropped
    notes: list[str] = field(default_factory=list)


def _class_filter(classes: Sequence[str] | None):
    if classes is None:
        drop = {c.lower() for c in NON_VEHICLE_CLASSES}
        return lambda n: n == "" or n.lower() not in drop
    keep = {c.lower() for c in classes}
    return lambda n: n == "" or n.lower() in keep


def load_predictions(path: str | Path, dataset, other_ids: Iterable[str] = (), *, pred_frame: str = "ground",
                     classes: Sequence[str] | None = None) -> LoadedPredictions:
    """Read predictions at `path` (OpenPCDet result.pkl or a folder of per-frame text files) for `dataset`.

    dataset: a `Height3Dataset` (its frame ids, and `read_labels(fid)["sensor"]` for the sensor
    frame). other_ids: ids of the dataset's other splits, skipped (counted) rather than
    rejected; any other unknown id is an error. pred_frame: "ground" or "sensor" (moved to the
    ground frame with each frame's sensor height and pitch). classes: class names to keep
    (case-insensitive); default every class but the non-vehicle ones. Predictions without a
    class are always kept. Raises ValueError / FileNotFoundError with the file and the fix.
    """
    if pred_frame not in PRED_FRAMES:
        raise ValueError(f"pred_frame must be one of {', '.join(PRED_FRAMES)}, got {pred_frame!r}")
    path = Path(path)
    if path.is_file():
        if path.suffix != ".pkl":
            raise ValueError(f"{path}: a prediction file must be OpenPCDet's result.pkl; per-frame text files go in "
                             f"a folder given to --pred")
        raw = predictions_from_result_pkl(path)
        info = {"format": "openpcdet-result.pkl", "pickle": "restricted unpickler (containers and numpy arrays)"}
    else:
        raw, layouts = read_prediction_texts(path)
        info = {"format": "per-frame text", "layouts": layouts}
    wanted = set(dataset.frame_ids)
    others = set(other_ids) - wanted
    unknown = sorted(set(raw) - wanted - others)
    if unknown:
        where = path / f"{unknown[0]}{PREDICTION_SUFFIX}" if path.is_dir() else path
        raise ValueError(f"{where}: unknown frame id {excerpt(unknown[0])} (not a frame of the dataset"
                         f"{f'; {len(unknown)} such ids' if len(unknown) > 1 else ''}); check --data/--height, or "
                         f"rename or remove it")
    skipped = sorted(set(raw) & others)
    keep_name = _class_filter(classes)
    class_counts: dict[str, dict[str, int]] = {}
    sensors: dict[tuple[float, float], int] = {}
    out: dict[str, Detections] = {}
    for fid in sorted(set(raw) & wanted):
        p = raw[fid]
        mask = np.array([keep_name(str(n)) for n in p.names], dtype=bool).reshape(-1)
        for n, k in zip(p.names.tolist(), mask.tolist()):
            c = class_counts.setdefault(n or "(no class)", {"kept": 0, "dropped": 0})
            c["kept" if k else "dropped"] += 1
        boxes, scores = p.boxes[mask], p.scores[mask]
        if pred_frame == "sensor":
            s = dataset.read_labels(fid)["sensor"]
            key = (float(s.height), float(s.pitch_deg))
            sensors[key] = sensors.get(key, 0) + 1
            boxes = boxes_sensor_to_ground(boxes, s.height, s.pitch_deg)
        out[fid] = Detections.from_arrays(np.ascontiguousarray(boxes, dtype=np.float64), np.ascontiguousarray(scores))
    info.update({
        "frame": pred_frame,
        "classes_kept": sorted(classes) if classes is not None else f"all but {', '.join(NON_VEHICLE_CLASSES)}",
        "class_counts": class_counts,
        "files_or_entries": len(raw),
    })
    if pred_frame == "sensor":
        info["moved_to_ground_with"] = [{"height_m": h, "pitch_deg": a, "frames": n} for (h, a), n in sensors.items()]
    notes = []
    dropped = {n: c["dropped"] for n, c in class_counts.items() if c["dropped"]}
    if class_counts:
        notes.append("prediction classes: " + ", ".join(
            f"{n} {c['kept']} kept" + (f" / {c['dropped']} dropped" if c["dropped"] else "")
            for n, c in sorted(class_counts.items())))
    if sum(c["kept"] for c in class_counts.values()) == 0 and dropped:
        notes.append(f"every prediction was dropped by its class ({', '.join(dropped)}); name the classes to keep "
                     f"with --pred-classes")
    if pred_frame == "sensor":
        notes.append("predictions moved from the LiDAR's own frame to the ground frame with "
                     + ", ".join(f"height {h:g} m, pitch {a:g} deg" for (h, a) in sensors))
    return LoadedPredictions(out, skipped, info, notes)


# --------------------------------------------------------------------------- frame-mismatch check

def vertical_offset_check(dataset, predictions: dict, *, pred_frame: str = "ground",
                          score_threshold: float | None = None,
                          max_distance: float = MATCH_DISTANCE_M, threshold: float = OFFSET_THRESHOLD_M,
                          min_matches: int = MIN_MATCHES) -> dict:
    """Height offset (m) between predictions and the vehicles they sit on in bird's-eye view.

    dataset: a `Height3Dataset` (`read_labels(fid)` gives each frame's boxes and sensor);
    predictions: {frame_id: (boxes (M, 7), scores (M,))} in the ground frame, as evaluated.
    For every ground-truth box of a frame with predictions, the nearest prediction with score >=
    `score_threshold` (None: the evaluator's, configs/default.yaml) whose BEV centre lies within
    `max_distance` metres is its match, and dz = prediction z - vehicle z. The same matches are also
    scored under the other frame: as if the given numbers were in the other frame than `pred_frame`
    says (with each frame's sensor height and pitch). A likely frame mismatch is reported when, over
    at least `min_matches` matches, |median dz| > `threshold` (a constant offset), or the median
    |dz| exceeds it while the other frame fits within it (a pitched sensor's offset grows with
    distance). Returns a dict: matches, median_dz_m, dz_quartiles_m, median_abs_dz_m, the other
    frame's median_abs residual, the parameters, likely_frame_mismatch and warning (None, or the
    message with the flag that likely fixes it).
    """
    score_threshold = shipped_default("eval.score_threshold", score_threshold)
    other = "sensor" if pred_frame == "ground" else "ground"
    dz: list[float] = []
    alt: list[float] = []
    sensors: set[tuple[float, float]] = set()
    for fid, pred in predictions.items():
        pb, ps = np.asarray(pred[0], dtype=np.float64).reshape(-1, 7), np.asarray(pred[1]).reshape(-1)
        pb = pb[ps >= score_threshold]
        if not len(pb):
            continue
        lab = dataset.read_labels(fid)
        gt = np.asarray(lab["boxes"], dtype=np.float64).reshape(-1, 7)
        if not len(gt):
            continue
        d = np.hypot(pb[:, None, 0] - gt[None, :, 0], pb[:, None, 1] - gt[None, :, 1])  # (P, G)
        j = d.argmin(axis=0)
        ok = d[j, np.arange(len(gt))] <= max_distance
        if not ok.any():
            continue
        p, g = pb[j[ok]], gt[ok]
        s = lab["sensor"]
        sensors.add((float(s.height), float(s.pitch_deg)))
        dz.extend((p[:, 2] - g[:, 2]).tolist())
        if pred_frame == "ground":  # were the numbers in the LiDAR's frame? compare with the vehicles moved there
            alt.extend((p[:, 2] - ground_to_sensor(g[:, :3], s.height, s.pitch_deg)[:, 2]).tolist())
        else:  # were the given numbers (before --pred-frame sensor moved them) already ground-frame?
            alt.extend((ground_to_sensor(p[:, :3], s.height, s.pitch_deg)[:, 2] - g[:, 2]).tolist())
    res = {"matches": len(dz), "median_dz_m": None, "dz_quartiles_m": None, "median_abs_dz_m": None,
           "other_frame": other, "other_frame_median_abs_dz_m": None, "max_bev_distance_m": max_distance,
           "threshold_m": threshold, "min_matches": min_matches, "score_threshold": score_threshold,
           "likely_frame_mismatch": False, "warning": None}
    if not dz:
        return res
    dz_a, alt_a = np.asarray(dz), np.asarray(alt)
    med = float(np.median(dz_a))
    q1, q3 = (float(v) for v in np.percentile(dz_a, [25, 75]))
    mabs, alt_abs = float(np.median(np.abs(dz_a))), float(np.median(np.abs(alt_a)))
    res.update(median_dz_m=round(med, 4), dz_quartiles_m=[round(q1, 4), round(q3, 4)], median_abs_dz_m=round(mabs, 4),
               other_frame_median_abs_dz_m=round(alt_abs, 4))
    other_fits = alt_abs <= threshold
    if len(dz) < min_matches or not (abs(med) > threshold or (mabs > threshold and other_fits)):
        return res
    if abs(med) > threshold:
        off = f"sit {abs(med):.2f} m {'below' if med < 0 else 'above'} the vehicles they cover in bird's-eye view"
    else:
        off = (f"sit at other heights than the vehicles they cover in bird's-eye view ({mabs:.2f} m apart in the "
               f"median, an offset that changes with distance)")
    msg = (f"likely frame mismatch: the predictions {off} (dz = prediction z - vehicle z over {len(dz)} matches "
           f"within {max_distance:g} m: median {med:+.2f} m, middle half {q1:+.2f} to {q3:+.2f} m); 3D IoU counts "
           f"such boxes as misses. ")
    sens = ", ".join(f"{h:g} m" + (f" pitched {a:g} deg" if a else "") for h, a in sorted(sensors))
    if other_fits and pred_frame == "ground":
        msg += (f"Taken as the LiDAR's own frame (sensor at {sens}) they match the vehicles (median |dz| "
                f"{alt_abs:.2f} m): if the model was trained on sensor-frame data (an OpenPCDet export with --frame "
                f"sensor, or the LiDAR's raw frame), pass --pred-frame sensor.")
    elif other_fits:
        msg += (f"They were moved from the LiDAR's frame (sensor at {sens}) by --pred-frame sensor, but as given they "
                f"already match the vehicles (median |dz| {alt_abs:.2f} m): pass --pred-frame ground.")
    else:
        msg += (f"Neither frame fits (as the {other} frame: median |dz| {alt_abs:.2f} m); check the frame of the "
                f"predictions (--pred-frame, now {pred_frame}) and the dataset's sensor ({sens}).")
    res.update(likely_frame_mismatch=True, warning=msg)
    return res


__all__ = [
    "ExternalPredictions", "LoadedPredictions", "load_predictions", "load_result_pkl", "predictions_from_result_pkl",
    "parse_prediction_text", "read_prediction_texts", "kitti_camera_to_lidar", "vertical_offset_check",
    "PRED_FRAMES", "TEXT_LAYOUTS", "PICKLE_WARNING", "OFFSET_THRESHOLD_M", "MATCH_DISTANCE_M", "MIN_MATCHES",
]
