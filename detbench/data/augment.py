"""Training-time augmentation of one frame: ground-truth sampling, flip, rotation, scaling, crop.

Every random choice comes from the `numpy.random.Generator` passed in, so a frame's
augmentation is a pure function of (frame, config, generator seed); the training set seeds
the generator from (seed, epoch, frame index) so a resumed run replays it exactly.

Order (OpenPCDet's): ground-truth sampling, flip across the x axis, rotation about z,
scaling, then the crop to the model's point-cloud range.

Config: the `augment` section (names follow OpenPCDet's DATA_AUGMENTOR entries; angles in
degrees at this edge, radians inside) with the sub-sections random_world_flip {enabled,
probability}, random_world_rotation {enabled, world_rot_angle_deg}, random_world_scaling
{enabled, world_scale_range} and gt_sampling (detbench.data.gt_database). Its defaults,
units and meanings are written once, in configs/default.yaml (AUGMENT_DEFAULTS is that
section).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from detbench.config import ConfigError, shipped_defaults, validate
from detbench.data.gt_database import GTSampler, GTSamplingConfig
from detbench.ops import normalize_heading
from detbench.utils.untrusted import excerpt

__all__ = [
    "AUGMENT_DEFAULTS", "AugmentConfig", "flip_x", "rotate_z", "scale_world", "random_flip_x",
    "random_rotation", "random_scaling", "crop_to_range", "augment_frame", "check_point_cloud_range",
]

AUGMENT_DEFAULTS: dict[str, Any] = shipped_defaults("augment")  # configs/default.yaml `augment:`


def _pair(value, name: str, where: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {name} must be a [low, high] pair of numbers, got {excerpt(value)}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ConfigError(f"{where}: {name} must be finite with low <= high, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class AugmentConfig:
    """Which augmentations run and their ranges (radians and unitless factors).

    Built by `from_dict` from the `augment` section (defaults: configs/default.yaml).
    """

    flip: bool
    flip_probability: float
    rotation: bool
    rotation_range: tuple[float, float]  # radians
    scaling: bool
    scale_range: tuple[float, float]
    gt_sampling: GTSamplingConfig

    @classmethod
    def none(cls) -> AugmentConfig:
        """Every augmentation off (the other settings at their defaults)."""
        cfg = cls.from_dict({})
        return replace(cfg, flip=False, rotation=False, scaling=False,
                       gt_sampling=replace(cfg.gt_sampling, enabled=False))

    @classmethod
    def from_dict(cls, cfg: Mapping | None, where: str = "augment") -> AugmentConfig:
        """Parse the `augment` config section (see the module doc); missing keys take the defaults.

        Raises ConfigError naming `where` and the closest known key for unknown keys and for
        out-of-range values.
        """
        cfg = dict(cfg or {})
        validate(cfg, AUGMENT_DEFAULTS, where=where)

        def section(name: str) -> dict:
            merged = dict(AUGMENT_DEFAULTS[name])
            merged.update(cfg.get(name) or {})
            return merged

        flip, rot, scl = section("random_world_flip"), section("random_world_rotation"), section("random_world_scaling")
        p = float(flip["probability"])
        if not 0.0 <= p <= 1.0:
            raise ConfigError(f"{where}: random_world_flip.probability must be in [0, 1], got {p}")
        lo_deg, hi_deg = _pair(rot["world_rot_angle_deg"], "random_world_rotation.world_rot_angle_deg", where)
        s_lo, s_hi = _pair(scl["world_scale_range"], "random_world_scaling.world_scale_range", where)
        if s_lo <= 0:
            raise ConfigError(f"{where}: random_world_scaling.world_scale_range must be positive, got [{s_lo}, {s_hi}]")
        return cls(flip=bool(flip["enabled"]), flip_probability=p,
                   rotation=bool(rot["enabled"]), rotation_range=(math.radians(lo_deg), math.radians(hi_deg)),
                   scaling=bool(scl["enabled"]), scale_range=(s_lo, s_hi),
                   gt_sampling=GTSamplingConfig.from_dict(section("gt_sampling"), where=f"{where}.gt_sampling"))


# ----------------------------------------------------------------------------------------
# deterministic transforms: (points (N, >=3), boxes (M, 7)) -> new arrays, inputs untouched
# ----------------------------------------------------------------------------------------
def flip_x(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror across the x axis (the x-z plane): y -> -y, heading -> -heading (wrapped to [-pi, pi))."""
    points = points.copy()
    boxes = boxes.copy()
    points[:, 1] = -points[:, 1]
    boxes[:, 1] = -boxes[:, 1]
    boxes[:, 6] = normalize_heading(-boxes[:, 6])  # wrapped in the boxes' own dtype: flip twice = identity
    return points, boxes


def rotate_z(points: np.ndarray, boxes: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the world by `angle` radians counter-clockwise about +z (points and box centres; heading += angle)."""
    c, s = math.cos(angle), math.sin(angle)
    points = points.copy()
    boxes = boxes.copy()
    for arr in (points, boxes):
        x = arr[:, 0].astype(np.float64)
        y = arr[:, 1].astype(np.float64)
        arr[:, 0] = c * x - s * y
        arr[:, 1] = s * x + c * y
    # add in float64, then wrap in the boxes' dtype so float32 headings stay in float32's [-pi, pi)
    boxes[:, 6] = normalize_heading((boxes[:, 6].astype(np.float64) + angle).astype(boxes.dtype))
    return points, boxes


def scale_world(points: np.ndarray, boxes: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale the world about the origin by `factor` (> 0): point xyz, box centres and sizes; heading unchanged.

    The origin is on the road, so a box standing on the road (z = dz / 2) still does.
    """
    if not factor > 0:
        raise ValueError(f"scale factor must be positive, got {factor}")
    points = points.copy()
    boxes = boxes.copy()
    points[:, :3] *= factor
    boxes[:, :6] *= factor
    return points, boxes


def random_flip_x(points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator,
                  probability: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """`flip_x` with probability `probability` (one draw from `rng`)."""
    if rng.random() < probability:
        return flip_x(points, boxes)
    return points, boxes


def random_rotation(points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator,
                    angle_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """`rotate_z` by an angle drawn uniformly from `angle_range` (radians)."""
    return rotate_z(points, boxes, float(rng.uniform(angle_range[0], angle_range[1])))


def random_scaling(points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator,
                   scale_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """`scale_world` by a factor drawn uniformly from `scale_range`."""
    return scale_world(points, boxes, float(rng.uniform(scale_range[0], scale_range[1])))


def check_point_cloud_range(point_cloud_range: Sequence[float], where: str = "point_cloud_range") -> np.ndarray:
    """Validate [x_min, y_min, z_min, x_max, y_max, z_max] (metres) and return it as float64 (6,)."""
    try:
        r = np.asarray(point_cloud_range, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: must be 6 numbers [x_min, y_min, z_min, x_max, y_max, z_max] in metres, "
                          f"got {excerpt(point_cloud_range)}") from None
    if r.shape != (6,) or not np.isfinite(r).all() or (r[3:] <= r[:3]).any():
        raise ConfigError(f"{where}: must be 6 finite numbers [x_min, y_min, z_min, x_max, y_max, z_max] in metres "
                          f"with each max > min, got {list(np.asarray(point_cloud_range).reshape(-1))}")
    return r


def crop_to_range(points: np.ndarray, boxes: np.ndarray, point_cloud_range: Sequence[float]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep points inside the range and boxes whose BEV centre is inside it.

    Args:
        points: (N, >=3) x, y, z, ... metres.
        boxes: (M, 7).
        point_cloud_range: [x_min, y_min, z_min, x_max, y_max, z_max] metres; half-open
            [min, max) on each axis, as voxelizers index it.
    Returns:
        (points (N', C), boxes (M', 7), keep (M,) bool mask of the kept boxes).
    """
    r = check_point_cloud_range(point_cloud_range)
    p = points[:, :3]
    pmask = ((p >= r[:3]) & (p < r[3:])).all(axis=1)
    c = boxes[:, :2]
    bmask = ((c >= r[:2]) & (c < r[3:5])).all(axis=1)
    return points[pmask], boxes[bmask], bmask


def augment_frame(points: np.ndarray, gt_boxes: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig,
                  sampler: GTSampler | None = None, avoid_boxes: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Apply the configured augmentations, in OpenPCDet's order, to one frame.

    Args:
        points: (N, 4) float32 x, y, z, intensity.
        gt_boxes: (M, 7) float32 training ground truth (the LiDAR-detected vehicles).
        rng: the only source of randomness.
        cfg: which augmentations run.
        sampler: the ground-truth sampler; required when `cfg.gt_sampling.enabled`.
        avoid_boxes: (K, 7) every vehicle of the frame (detected or not); pasted vehicles
            must not overlap any of them. Defaults to `gt_boxes`.
    Returns:
        (points (N', 4) float32, gt_boxes (M', 7) float32), M' >= M (pasted boxes appended).
    """
    points = np.asarray(points, dtype=np.float32)
    gt_boxes = np.asarray(gt_boxes, dtype=np.float32).reshape(-1, 7)
    if cfg.gt_sampling.enabled:
        if sampler is None:
            raise ValueError("augment.gt_sampling.enabled is true but no ground-truth database was given; "
                             "build one with detbench.data.gt_database.build_or_load_gt_database or set "
                             "augment.gt_sampling.enabled=false")
        points, gt_boxes, _ = sampler.sample(points, gt_boxes, rng, avoid_boxes=avoid_boxes)
    if cfg.flip:
        points, gt_boxes = random_flip_x(points, gt_boxes, rng, cfg.flip_probability)
    if cfg.rotation:
        points, gt_boxes = random_rotation(points, gt_boxes, rng, cfg.rotation_range)
    if cfg.scaling:
        points, gt_boxes = random_scaling(points, gt_boxes, rng, cfg.scale_range)
    return points.astype(np.float32, copy=False), gt_boxes.astype(np.float32, copy=False)
