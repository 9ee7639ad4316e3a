"""What a training command does around the loop (tools/train.py): the config overrides its options make,
the frames read once before training so a bad file stops the run before it starts, the boxes that size
the anchors, the evaluation after each epoch, and the summary files of the run."""
from __future__ import annotations

import hashlib
import json
import os
import sys
from contextlib import contextmanager
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from detbench.data import Height3Dataset
from detbench.data.frame import key_label, key_value
from detbench.data.gt_database import frames_fingerprint
from detbench.data.layout import same_scenes, scene_identity
from detbench.data.regions import RANGE_NAMES
from detbench.data.validate import check_frames
from detbench.eval.evaluate import evaluate_predictions
from detbench.train.dataset import TrainingSet
from detbench.train import inference
from detbench.train.loop import TrainResult
from detbench.train.run_layout import RUN_FOLDER
from detbench.utils.atomic import atomic_write_json, atomic_write_text
from detbench.utils.folder_locks import claim_folder

__all__ = ["check_training_frames", "claim_run_folder", "collect_train_boxes", "eval_frames", "make_eval_fn",
           "option_overrides", "training_data_info", "write_summary"]


def option_overrides(overrides, *, epochs: int | None = None, batch_size: int | None = None,
                     workers: int | None = None, data: str | None = None) -> list[str]:
    """`overrides` (KEY=VALUE) followed by the ones the command's shortcut options stand for."""
    out = list(overrides)
    for value, key in ((epochs, "train.epochs"), (batch_size, "train.batch_size"), (workers, "train.workers")):
        if value is not None:
            out.append(f"{key}={value}")
    if data:
        out.append(f"data.root={Path(data).resolve()}")
    return out


@contextmanager
def claim_run_folder(out: Path) -> Iterator[None]:
    """Hold the run folder `out` for the block (`detbench.utils.folder_locks.claim_folder`): it must be new, empty or a
    training run's (`RUN_FOLDER`), else `FolderNotReplaceable` names it; it is locked, so a second run on it is
    refused (`FolderInUse`, naming the holder's pid and host), and a lock left by a killed run is taken over
    with a note. Under torchrun only rank 0 holds it (the others write nothing there)."""
    if int(os.environ.get("RANK", "0") or 0) != 0:
        yield
        return
    with claim_folder(out, RUN_FOLDER, "a training run", notes=lambda n: print(f"note: {n}", file=sys.stderr)):
        yield


def collect_train_boxes(train_set: TrainingSet, limit: int = 400) -> np.ndarray:
    """LiDAR-detected boxes of up to `limit` evenly spaced training frames (for anchor sizes)."""
    n = len(train_set)
    idx = np.unique(np.linspace(0, n - 1, num=min(n, limit)).astype(int)) if n else []
    boxes = [train_set.get(int(i), 0, augment=False).gt_boxes for i in idx]
    return np.concatenate(boxes) if boxes else np.zeros((0, 7), np.float32)


def training_data_info(root: Path, height: float, train_set: TrainingSet) -> dict:
    """What a checkpoint records of its training data and `--resume` compares: the source folder, the height and
    the content fingerprint of the training frames (`frames_fingerprint`; the ground-truth database's, already
    computed when it has one), so a dataset re-simulated or edited in place is told from the one trained on."""
    db = train_set.sampler.db if train_set.sampler is not None else None
    sha1 = (db.info.get("frames_sha1") if db is not None else None) or frames_fingerprint(train_set.frames)
    info = {"source": str(root), "height": key_value(height), "frames_sha1": str(sha1)}
    return {**info, **dataset_identity(root, train_set.frames)}


def dataset_identity(root: Path, frames) -> dict:
    """What an evaluation of a checkpoint compares with the data it is given (`training_data_warnings`): the
    digest of the dataset's dataset.json (its source, seed and split; another after a re-simulation or a
    re-split), what draws its scenes (`dataset_scenes`: the simulator preset, calibration, seed and overrides of
    its `source`, JSON; empty for data that are not simulated) and the ids of the training frames, one string
    of lines (one value however many frames)."""
    digest, source = _read_dataset_info(Path(root) / "dataset.json")
    ids = getattr(frames, "frame_ids", None)
    return {"dataset_sha1": digest, "dataset_scenes": json.dumps(scene_identity(source)) if source else "",
            "train_frames": "\n".join(str(i) for i in (ids if ids is not None else []))}


def _read_dataset_info(info_file: Path) -> tuple[str | None, dict | None]:
    """The SHA-1 of a dataset.json and its `source`, from one read; None for what is missing or unreadable."""
    try:
        data = info_file.read_bytes()
    except OSError:
        return None, None
    try:
        source = json.loads(data).get("source")
    except (ValueError, AttributeError):
        source = None
    return hashlib.sha1(data).hexdigest(), source if isinstance(source, dict) else None


def _training_source(data_info: dict) -> dict | None:
    """What drew the training data's scenes: recorded in the checkpoint (`dataset_scenes`), or, for a checkpoint
    that predates the record, the `source` of the training dataset's dataset.json when that file is still the one
    trained on (same digest)."""
    recorded = data_info.get("dataset_scenes")
    if isinstance(recorded, str) and recorded:
        try:
            return json.loads(recorded)
        except ValueError:
            return None
    where, was = data_info.get("source"), data_info.get("dataset_sha1")
    if not where or not was:
        return None
    digest, source = _read_dataset_info(Path(str(where)) / "dataset.json")
    return source if digest == was else None


def training_data_warnings(data_info: dict, root: Path, split: str, split_ids: list[str]) -> list[str]:
    """Warnings for an evaluation on `split` of the dataset `root` (frame ids `split_ids`) of a checkpoint that
    records `data_info` (`training_data_info`): the dataset was re-simulated, re-split or edited since the
    training, and (for a split other than train or all) frames it was trained on are among those evaluated.
    None for a checkpoint that records neither, and none for a simulated dataset whose scenes another simulator
    seed, preset or calibration drew than the training data's (a held-out world: its frame ids name other
    scenes, `detbench.data.layout.same_scenes`)."""
    now, source = _read_dataset_info(Path(root) / "dataset.json")
    if same_scenes(_training_source(data_info), source) is False:
        return []
    out = []
    was = data_info.get("dataset_sha1")
    if was and now and was != now:
        out.append(f"{root} is not the dataset this checkpoint was trained on: its dataset.json changed since "
                   f"(re-simulated, re-split or edited); the figures describe the data as it is now")
    listed = data_info.get("train_frames")
    trained = set(listed.split("\n")) - {""} if isinstance(listed, str) else set()
    if split not in ("train", "all") and trained:
        both = sorted(trained.intersection(split_ids))
        if both:
            out.append(f"{len(both)} of the {len(split_ids)} frames of the {split} split were training frames of "
                       f"this checkpoint (e.g. {', '.join(both[:3])}): the dataset was re-split since, so these "
                       f"figures are not a held-out test; evaluate on the data the model was trained with, or "
                       f"train again")
    return out


def check_training_frames(frames) -> None:
    """Read every training frame once now (about 1 ms a frame), so a bad file stops the run before it trains
    instead of when the data loader reaches it mid-epoch."""
    check_frames(frames, fix=f"a training frame cannot be read: fix or re-create the file (python tools/validate.py "
                             f"{frames.root} lists every problem), or remove its id from "
                             f"{frames.root / 'ImageSets' / 'train.txt'}")


def eval_frames(root: Path, height: float, ecfg):
    """The frames evaluated after each epoch, each read once now, so a bad file stops the run before it trains."""
    test_set = Height3Dataset(root, height, ecfg.split)
    n = len(test_set)
    if ecfg.max_frames and ecfg.max_frames < n:
        return [test_set[int(i)] for i in np.linspace(0, n - 1, ecfg.max_frames).astype(int)]
    check_frames(test_set)
    return test_set


def make_eval_fn(frames, ecfg, point_cloud_range, device, batch_size: int, road=None):
    """`eval_fn(model, epoch)` for the training loop: recall and AP@R40 of all vehicles per range, on the
    input the model trains on (`road`: the run's RoadConfig)."""
    def eval_fn(m, epoch):
        preds = inference.predict_frames(m, frames, point_cloud_range, device=device, batch_size=batch_size,
                                         progress=False, road=road)
        rep = evaluate_predictions(frames, preds, iou_threshold=ecfg.iou_threshold,
                                   score_threshold=ecfg.score_threshold, extras=False, progress=False)
        res = {}
        for r in RANGE_NAMES:
            cell = rep["results"][r]["all"]
            res[f"ap_r40_{r}"] = cell["ap_r40"] if cell["ap_r40"] is not None else float("nan")
            res[f"recall_{r}"] = cell["recall"] if cell["recall"] is not None else float("nan")
        return res

    return eval_fn


def write_summary(out: Path, model_name: str, height: float, preset: str, root: Path, result: TrainResult,
                  seconds: float, init: dict | None = None, frames_sha1: str | None = None) -> None:
    """OUT/train_summary.json and .md of a run of `model_name` at `height` metres with `preset` (`frames_sha1`:
    the training frames' content fingerprint, from `training_data_info`)."""
    last = result.history[-1] if result.history else {}
    summary = {"model": model_name, "height": key_value(height), "preset": preset, "data": str(root),
               "frames_sha1": frames_sha1,
               "epochs_completed": result.epochs_completed, "global_step": result.global_step,
               "interrupted": result.interrupted, "train_seconds": round(seconds, 1),
               "checkpoint": str(result.last_checkpoint) if result.last_checkpoint else None,
               "init_from": init, "last_epoch": last}
    atomic_write_json(out / "train_summary.json", summary)
    lines = [f"# Training summary: {model_name} at {key_label(height)} ({preset} preset)", "",
             "| item | value |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in summary.items() if k != "last_epoch"]
    lines += [f"| last epoch: {k} | {v:.4g} |" if isinstance(v, float) else f"| last epoch: {k} | {v} |"
              for k, v in last.items()]
    atomic_write_text(out / "train_summary.md", "\n".join(lines) + "\n")
