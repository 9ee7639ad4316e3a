"""Sensor frame <-> ego ground frame.

Sensor frame: origin at the LiDAR, axes of the LiDAR (x along its optical axis, y left, z up
of the sensor). The sensor is pitched by `pitch_deg` about +y (positive pitches it down,
as in `Sensor.pitch_deg`) and mounted `height` metres above the road, right above the
ground-frame origin. A ground-frame point is

    p_ground = R_y(pitch) @ p_sensor + (0, 0, height)

with R_y(a) = [[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]], so the sensor's +x axis
points to (cos a, 0, -sin a): below the horizon for a > 0.
"""
from __future__ import annotations

import math

import numpy as np

from detbench.utils.angles import fix_huge


def _rot_y(pitch_deg: float) -> np.ndarray:
    a = math.radians(float(pitch_deg))
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=np.float64)


def sensor_to_ground(points: np.ndarray, height: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Points (N, >=3) in the sensor frame -> same shape and dtype in the ego ground frame.

    Columns past the third (intensity, ...) are copied unchanged. `height` in metres,
    `pitch_deg` in degrees (positive = pitched down). Computed in float64, returned in the
    input dtype.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got shape {pts.shape}")
    out = pts.copy()
    xyz = pts[:, :3].astype(np.float64) @ _rot_y(pitch_deg).T
    xyz[:, 2] += float(height)
    out[:, :3] = xyz.astype(pts.dtype, copy=False)
    return out


def ground_to_sensor(points: np.ndarray, height: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Inverse of `sensor_to_ground`: points (N, >=3) in the ground frame -> the sensor frame."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got shape {pts.shape}")
    out = pts.copy()
    xyz = pts[:, :3].astype(np.float64)
    xyz[:, 2] -= float(height)
    xyz = xyz @ _rot_y(pitch_deg)  # R^T applied to row vectors
    out[:, :3] = xyz.astype(pts.dtype, copy=False)
    return out


def boxes_sensor_to_ground(boxes: np.ndarray, height: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Boxes (M, 7) labelled in the sensor frame -> the ground frame.

    The centre is transformed exactly; sizes and heading are kept. A box tilted by the
    sensor's pitch cannot be represented as an upright box, so for pitch != 0 this is the
    upright box about the exact centre (heading error none, tilt dropped); for the paper's
    2.5 degree pitch the tilt of a vehicle label is below the label's own noise.
    """
    b = np.asarray(boxes)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"boxes must be (M, 7), got shape {b.shape}")
    out = b.copy()
    out[:, :3] = sensor_to_ground(b[:, :3], height, pitch_deg)
    return out


def boxes_ground_to_sensor(boxes: np.ndarray, height: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Inverse of `boxes_sensor_to_ground`: boxes (M, 7) in the ground frame -> the sensor frame.

    The centre is transformed exactly; sizes and heading are kept, so for pitch != 0 the
    result is the upright box about the exact centre (the box's tilt by the pitch is dropped).
    """
    b = np.asarray(boxes)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"boxes must be (M, 7), got shape {b.shape}")
    out = b.copy()
    out[:, :3] = ground_to_sensor(b[:, :3], height, pitch_deg)
    return out


def wrap_heading(heading: np.ndarray) -> np.ndarray:
    """Angles (radians, any shape) wrapped into [-pi, pi), float64; huge angles exactly (detbench.utils.angles)."""
    h = np.asarray(heading, dtype=np.float64)
    return fix_huge(h, (h + np.pi) % (2 * np.pi) - np.pi)
