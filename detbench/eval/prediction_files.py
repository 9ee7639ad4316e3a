"""Prediction files: one `<frame_id>.txt` per frame, a box per line, as tools/eval.py --pred reads them.

A line is `x y z dx dy dz heading score [class]`: metres and radians in the ego ground frame
(docs/evaluation.md), an optional class name that is not read. An empty file is a frame with no
predictions; a frame without a file has none either. `write_predictions` writes a checkpoint's
`Detections` in this format (each file atomically) and `read_prediction_dir` reads a folder back
(float64, so a model's float32 figures come back bit for bit); a malformed line is a ValueError
naming the file and the line. Other tools' layouts (OpenPCDet's result.pkl, KITTI text) are read by
`detbench.eval.external`.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path
from collections.abc import Iterable, Mapping

import numpy as np

from detbench.data.detections import Detections
from detbench.utils.atomic import atomic_write_text
from detbench.utils.cli import UserError
from detbench.utils.untrusted import excerpt

__all__ = ["PREDICTION_SUFFIX", "format_prediction_lines", "parse_prediction_file", "read_prediction_dir",
           "remove_prediction_folder", "write_prediction_folder",
           "write_predictions"]


PREDICTION_SUFFIX = ".txt"


def parse_prediction_file(path: str | Path) -> Detections:
    """Read one prediction file: one box per line, `x y z dx dy dz heading score [class]`.

    Units: metres and radians in the ego ground frame (docs/evaluation.md). Blank lines are
    skipped; an optional ninth field (a class name) is accepted and not used. An empty file
    is a frame with no predictions. A malformed line raises ValueError naming file and line.
    Returns numpy Detections: boxes (M, 7) float64, scores (M,) float64, labels 0.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file; write one box per line as "
                         f"'x y z dx dy dz heading score [class]'") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (8, 9):
            raise ValueError(f"{path}:{lineno}: expected 8 numbers 'x y z dx dy dz heading score' and an "
                             f"optional class name, got {len(fields)} field(s): {excerpt(line.strip())}")
        try:
            values = [float(v) for v in fields[:8]]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: not a number among the first 8 fields "
                             f"'x y z dx dy dz heading score': {excerpt(line.strip())}") from None
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{path}:{lineno}: non-finite value in {excerpt(line.strip())}; every field must "
                             f"be a finite number")
        if min(values[3:6]) < 0:
            raise ValueError(f"{path}:{lineno}: negative box size dx, dy, dz = {values[3:6]} in "
                             f"{excerpt(line.strip())}; sizes are lengths in metres, >= 0")
        rows.append(values)
    arr = np.array(rows, dtype=np.float64).reshape(-1, 8)
    return Detections.from_arrays(np.ascontiguousarray(arr[:, :7]), np.ascontiguousarray(arr[:, 7]))


def read_prediction_dir(pred_dir: str | Path, frame_ids: Iterable[str],
                        other_ids: Iterable[str] = ()) -> tuple[dict[str, Detections], list[str]]:
    """Read `<frame_id>.txt` files of a folder (one per frame; see `parse_prediction_file`).

    frame_ids: ids of the frames being evaluated. other_ids: ids of the same dataset outside
    the evaluated split; their files are skipped (returned in the second list) rather than
    rejected. Any other file (unknown id, other extension) is an error naming the file; hidden
    files (starting with '.') are ignored. Returns ({frame_id: Detections}, skipped ids).
    """
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"{pred_dir}: prediction folder not found; give the folder holding "
                                f"one <frame_id>{PREDICTION_SUFFIX} file per frame")
    wanted = set(frame_ids)
    others = set(other_ids) - wanted
    out: dict[str, Detections] = {}
    skipped: list[str] = []
    for path in sorted(pred_dir.iterdir()):
        if path.name.startswith("."):
            continue
        if not path.is_file() or path.suffix != PREDICTION_SUFFIX:
            raise ValueError(f"{path}: unexpected entry in the prediction folder; it must hold only "
                             f"<frame_id>{PREDICTION_SUFFIX} files")
        fid = path.stem
        if fid in wanted:
            out[fid] = parse_prediction_file(path)
        elif fid in others:
            skipped.append(fid)
        else:
            raise ValueError(f"{path}: unknown frame id {fid!r} (not a frame of the dataset); rename or "
                             f"remove the file")
    return out, skipped


def format_prediction_lines(boxes: np.ndarray, scores: np.ndarray, class_name: str | None = None) -> str:
    """Text of a prediction file for boxes (M, 7) and scores (M,), one box per line."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(boxes) != len(scores):
        raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
    tail = f" {class_name}" if class_name else ""
    return "".join(" ".join(repr(float(v)) for v in (*b, s)) + tail + "\n" for b, s in zip(boxes, scores))


def write_prediction_folder(preds: Mapping[str, Detections | tuple], pred_dir: str | Path) -> None:
    """`write_predictions` into a folder that replaces `pred_dir` whole when complete
    (detbench.utils.staged_folders.staged_folder): no file of an earlier evaluation's predictions stays
    beside these, and an interrupted write leaves the earlier folder as it was."""
    from detbench.utils.staged_folders import staged_folder

    with staged_folder(pred_dir, what="an evaluation's predictions") as staged:
        write_predictions(preds, staged)


def remove_prediction_folder(pred_dir: str | Path) -> None:
    """Remove a prediction folder an earlier evaluation wrote (only `<frame_id>.txt` files, or refused)."""
    pred_dir = Path(pred_dir)
    foreign = [p.name for p in pred_dir.iterdir() if not (p.is_file() and p.name.endswith(PREDICTION_SUFFIX))]
    if foreign:
        raise UserError(f"{pred_dir}: holds {', '.join(sorted(foreign)[:5])}, which an evaluation does not write; "
                        f"move it elsewhere, or choose another --out")
    shutil.rmtree(pred_dir)


def write_predictions(preds: Mapping[str, Detections | tuple], pred_dir: str | Path) -> None:
    """One `<frame_id>.txt` per frame of `preds` ({frame_id: Detections or (boxes, scores)}) in `pred_dir`."""
    for fid, p in preds.items():
        atomic_write_text(Path(pred_dir) / f"{fid}{PREDICTION_SUFFIX}", format_prediction_lines(p[0], p[1]))
