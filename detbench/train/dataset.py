"""`TrainingSet`: frames -> training samples (LiDAR-detected ground truth, augmentation, crop).

Per item, in order:
1. ground truth = the frame's LiDAR-detected vehicles (`detbench.data.regions.lidar_detected`:
   >= 1 point inside the box with its bottom raised 0.05 m), as the paper trains;
2. when training: augmentation (detbench.data.augment) with a generator seeded from
   (seed, epoch, index), pasted vehicles kept clear of every vehicle of the frame;
3. crop points and boxes to the model's point-cloud range and, when the run's `road.drop` says so,
   remove the road points (`detbench.data.road.crop_model_input`: pasted vehicles are in by then, so
   their copied road goes too).

Items are addressed as `ts[(epoch, index)]` (the training loop's batch sampler, `EpochBatches`,
sends the epoch with each index, so persistent DataLoader workers need no epoch state) or as
`ts[index]` for the epoch last given to `set_epoch`. Instances must be picklable (workers
are spawned).
"""
from __future__ import annotations

import errno
import hashlib
import math
import os
from dataclasses import replace
from pathlib import Path
from collections.abc import Iterator, Sequence

import numpy as np
from torch.utils.data import Dataset, Sampler
from torch.utils.data.distributed import DistributedSampler

from detbench.data import Height3Dataset
from detbench.data.augment import AugmentConfig, augment_frame, check_point_cloud_range
from detbench.data.batch import Sample
from detbench.data.frame import Frame, data_key, key_value
from detbench.data.gt_database import GTDatabase, GTSampler, build_or_load_gt_database
from detbench.data.regions import DETECTED_BOTTOM_LIFT, DETECTED_MIN_POINTS, lidar_detected
from detbench.data.road import RoadConfig, crop_model_input
from detbench.train.rng import sample_rng

__all__ = ["EpochBatches", "TrainingSet", "default_database_dir"]


def default_database_dir(root: str | os.PathLike, height: float) -> Path:
    """ROOT/gt_database/<height_key>: where `TrainingSet.from_dataset` keeps the ground-truth database."""
    return Path(root) / "gt_database" / data_key(height)


def cached_database_dir(root: str | os.PathLike, height: float) -> Path:
    """Where the ground-truth database of a dataset that cannot be written goes: the simulated datasets' cache
    (`detbench.sim.dataset.cache_root`), gt_database/<digest of the dataset's path>/<height_key>."""
    from detbench.sim.dataset import cache_root

    digest = hashlib.sha1(str(Path(root).resolve()).encode("utf-8", "surrogateescape")).hexdigest()[:12]
    return cache_root() / "gt_database" / digest / data_key(height)


class TrainingSet(Dataset):
    """A torch Dataset of `Sample`s over any sequence of Frames (e.g. a Height3Dataset split).

    Args:
        frames: `len()` and `[i] -> Frame` (Height3Dataset or a list of Frames).
        point_cloud_range: [x_min, y_min, z_min, x_max, y_max, z_max] metres, the model's.
        augment: augmentation config; None or `AugmentConfig.none()` for no augmentation.
        gt_database: required when `augment.gt_sampling.enabled`.
        seed: seeds each sample's augmentation with the epoch and index.
        training: False disables augmentation (evaluation, previews).
        road: the road model; with `road.drop` the road points leave every sample (None: kept).
        min_points / bottom_lift: the LiDAR-detected rule (defaults: DETECTED_MIN_POINTS = 1 point,
            DETECTED_BOTTOM_LIFT = 0.05 m; detbench.data.regions).
    """

    def __init__(self, frames: Sequence[Frame], point_cloud_range: Sequence[float], *,
                 augment: AugmentConfig | None = None, gt_database: GTDatabase | None = None, seed: int = 0,
                 training: bool = True, road: RoadConfig | None = None, min_points: int = DETECTED_MIN_POINTS,
                 bottom_lift: float = DETECTED_BOTTOM_LIFT):
        self.frames = frames
        self.point_cloud_range = check_point_cloud_range(point_cloud_range)
        self.augment = augment or AugmentConfig.none()
        self.sampler = None
        if self.augment.gt_sampling.enabled:
            if gt_database is None:
                raise ValueError("augment.gt_sampling.enabled is true but TrainingSet got no gt_database; pass one "
                                 "(detbench.data.gt_database.build_or_load_gt_database) or use "
                                 "TrainingSet.from_dataset, or set augment.gt_sampling.enabled=false")
            self.sampler = GTSampler(gt_database, self.augment.gt_sampling)
        self.seed = int(seed)
        self.road = road
        self.training = bool(training)
        self.min_points = int(min_points)
        self.bottom_lift = float(bottom_lift)
        self.epoch = 0

    @classmethod
    def from_dataset(cls, root: str | os.PathLike, height: float, point_cloud_range: Sequence[float], *,
                     augment: AugmentConfig | None = None, seed: int = 0, split: str = "train",
                     road: RoadConfig | None = None, database_dir: str | os.PathLike | None = None,
                     progress: bool = True) -> TrainingSet:
        """`Height3Dataset(root, height, split)` with the ground-truth database built (once) if sampling is on.

        The database comes from the *train* split only; it lives in `database_dir`, else
        `augment.gt_sampling.database_dir`, else ROOT/gt_database/<height>, or, when the dataset cannot be
        written (read-only), in the cache (`cached_database_dir`). In a distributed
        run call this inside `main_process_first(info)`.
        """
        augment = augment or AugmentConfig.none()
        frames = Height3Dataset(root, height, split)
        db = None
        if augment.gt_sampling.enabled and split != "test":
            train_frames = frames if split == "train" else Height3Dataset(root, height, "train")
            where = database_dir or augment.gt_sampling.database_dir
            source = {"root": str(Path(root).resolve()), "height": key_value(height), "split": "train"}
            try:
                db = build_or_load_gt_database(train_frames, where or default_database_dir(root, height),
                                               progress=progress, source=source)
            except OSError as e:  # a dataset the user may not write (read-only): the database goes to the cache
                if where is not None or e.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                    raise
                db = build_or_load_gt_database(train_frames, cached_database_dir(root, height), progress=progress,
                                               source=source)
        if db is None and augment.gt_sampling.enabled:
            augment = replace(augment, gt_sampling=replace(augment.gt_sampling, enabled=False))
        return cls(frames, point_cloud_range, augment=augment, gt_database=db, seed=seed, training=split != "test",
                   road=road)

    def __len__(self) -> int:
        return len(self.frames)

    def set_epoch(self, epoch: int) -> None:
        """The epoch whose augmentation `__getitem__` reproduces (call before each pass)."""
        self.epoch = int(epoch)

    def __getitem__(self, key: int | tuple[int, int]) -> Sample:
        """`ts[(epoch, index)]` or `ts[index]` (epoch from `set_epoch`); augmented when `training`."""
        if isinstance(key, tuple):
            epoch, index = key
            return self.get(int(index), int(epoch), augment=self.training)
        return self.get(int(key), self.epoch, augment=self.training)

    def get(self, index: int, epoch: int = 0, augment: bool = True) -> Sample:
        """Sample `index` as seen in `epoch`: (points (N, 4) float32, gt_boxes (M, 7) float32, frame_id)."""
        if not 0 <= index < len(self.frames):
            raise IndexError(f"index {index} out of range for {len(self.frames)} frames")
        frame = self.frames[index]
        points = np.asarray(frame.points, dtype=np.float32)
        all_boxes = np.asarray(frame.boxes, dtype=np.float32).reshape(-1, 7)
        gt = all_boxes[lidar_detected(points, all_boxes, self.min_points, self.bottom_lift)]
        if augment:
            rng = sample_rng(self.seed, epoch, index)
            points, gt = augment_frame(points, gt, rng, self.augment, self.sampler, avoid_boxes=all_boxes)
        points, gt, _ = crop_model_input(points, gt, self.point_cloud_range, self.road)
        return Sample(np.ascontiguousarray(points, dtype=np.float32), np.ascontiguousarray(gt, dtype=np.float32),
                      frame.frame_id)


class EpochBatches(Sampler):
    """Batches of (epoch, index) pairs in the sampler's order for `epoch`, skipping the first `skip` batches.

    The epoch travels with each index, so persistent DataLoader workers augment for the
    right epoch without being re-created; `skip` serves a mid-epoch resume.
    """

    def __init__(self, sampler: DistributedSampler, batch_size: int, drop_last: bool):
        self.sampler, self.batch_size, self.drop_last = sampler, batch_size, drop_last
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.epoch, self.skip = int(epoch), int(skip)
        self.sampler.set_epoch(self.epoch)

    def full_length(self) -> int:
        n = len(self.sampler)
        return n // self.batch_size if self.drop_last else math.ceil(n / self.batch_size)

    def __len__(self) -> int:
        return max(0, self.full_length() - self.skip)

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        order = list(self.sampler)
        for k in range(self.skip, self.full_length()):
            yield [(self.epoch, i) for i in order[k * self.batch_size:(k + 1) * self.batch_size]]
