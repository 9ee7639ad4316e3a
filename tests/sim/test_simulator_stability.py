"""The simulator at the extremes of mounting: heights 0.2-3.0 m, pitches -10..+10 degrees.

Every frame must be valid: no point below the road (z >= 0 exactly without range noise; with
range noise sigma a ground return moves along its ray, so it may lie below the road by at most
5 sigma x the sine of the steepest ray's depression), none beyond the sensor's range, every point on one of
the configured rings (sensor-frame elevation within 1e-6 rad of a channel, pitch undone) and
inside the horizontal field of view, and the frame's sensor record says the height and pitch.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from detbench.ops import points_in_boxes
from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config

HEIGHTS = (0.2, 0.5, 1.0, 1.8, 2.4, 3.0)  # metres
PITCHES = (-10.0, -5.0, 0.0, 5.0, 10.0)  # degrees; positive tilts the sensor down
NOISE = 0.02  # metres, for the noisy variants


def _lidars():
    grid = [lidar_preset(h, pitch_deg=p, channels=32, h_samples=180) for h in HEIGHTS for p in PITCHES]
    noisy = [lidar_preset(h, pitch_deg=p, channels=32, h_samples=180, range_noise_m=NOISE, dropout=0.1)
             for h, p in ((0.2, 10.0), (3.0, -10.0), (1.8, 2.5))]
    return grid + noisy


def sensor_angles(points: np.ndarray, height: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth (radians) of ground-frame points in the sensor frame (pitch undone)."""
    p = points[:, :3].astype(np.float64) - np.array([0.0, 0.0, height])
    a = math.radians(pitch_deg)
    c, s = math.cos(a), math.sin(a)
    xs = c * p[:, 0] - s * p[:, 2]
    zs = s * p[:, 0] + c * p[:, 2]
    return np.arctan2(zs, np.hypot(xs, p[:, 1])), np.arctan2(p[:, 1], xs)


@pytest.fixture(scope="module")
def frames():
    lidars = _lidars()
    steps = list(HighwaySimulator(load_sim_config(), 5).run(2, lidars, frames_per_scene=2))
    return lidars, steps


def test_every_height_and_pitch_gives_valid_frames(frames):
    lidars, steps = frames
    for step in steps:
        assert len(step) == len(lidars)
        for f, lidar in zip(step, lidars):
            tag = f"height {lidar.height} m, pitch {lidar.pitch_deg} deg, noise {lidar.range_noise_m} m"
            f.check()
            assert f.sensor.height == lidar.height and f.sensor.pitch_deg == lidar.pitch_deg, tag
            pts = f.points
            assert len(pts) > 500 and np.isfinite(pts).all(), tag
            # no point below the road
            steepest = -float(lidar.ray_directions()[..., 2].min())  # sine of the steepest ray's depression
            floor = 0.0 if lidar.range_noise_m == 0 else -5 * lidar.range_noise_m * steepest
            assert pts[:, 2].min() >= floor, (tag, float(pts[:, 2].min()))
            # none beyond the range (float32 points: one float32 step at 150 m is 1.5e-5 m)
            rng = np.linalg.norm(pts[:, :3].astype(np.float64) - [0.0, 0.0, lidar.height], axis=1)
            assert rng.max() <= lidar.max_range + 1e-4, (tag, float(rng.max()))
            # on the configured rings, inside the field of view
            el, az = sensor_angles(pts, lidar.height, lidar.pitch_deg)
            rings = lidar.elevations()
            ring = np.abs(el[:, None] - rings[None]).argmin(1)
            assert np.abs(el - rings[ring]).max() < 1e-6, tag
            assert np.abs(az).max() <= math.radians(lidar.hfov_deg) / 2 + 1e-6, tag
            # the lowest ring points below the horizon at every one of these mountings and sees the road
            assert (ring == 0).any() and (pts[ring == 0, 2] <= 1e-3).any(), tag
            if lidar.range_noise_m == 0:
                # a noise-free ground return lies exactly on the road, at h / tan(depression) from the sensor
                ground = pts[:, 2] == 0.0
                assert ground.sum() > 100, tag
                d = np.hypot(pts[ground, 0], pts[ground, 1])
                depression = -np.arctan2(pts[ground, 2] - lidar.height, d)
                np.testing.assert_allclose(d, lidar.height / np.tan(depression), rtol=1e-6, err_msg=tag)
            # hit counts follow the LiDAR-detected rule on the points
            counts, _ = points_in_boxes(pts, f.boxes, bottom_lift=0.05)
            assert np.array_equal(counts, f.hit_counts), tag


def test_pitch_moves_the_rings_as_configured(frames):
    """Same height, pitch -10 / 0 / +10: the ground returns of the lowest ring straight ahead lie at
    h / tan(-(lower fov limit) + pitch), the pitch tilting the sensor down when positive."""
    lidars, steps = frames
    f_by = {(lidar.height, lidar.pitch_deg): f for lidar, f in zip(lidars, steps[0]) if lidar.range_noise_m == 0}
    checked = 0
    for h in (0.2, 1.8, 3.0):
        for p in (-10.0, 0.0, 10.0):
            f = f_by[(h, p)]
            el, az = sensor_angles(f.points, h, p)
            low = (np.abs(el - math.radians(-12.5)) < 1e-6) & (np.abs(az) < math.radians(1.0)) & (f.points[:, 2] == 0)
            if not low.any():  # a vehicle right ahead hides the road there
                continue
            checked += 1
            # the ray of sensor elevation -12.5 deg and azimuth az, turned by the pitch, meets the road at x
            e, a, c, sn = math.radians(-12.5), az[low], math.cos(math.radians(p)), math.sin(math.radians(p))
            dx = c * math.cos(e) * np.cos(a) + sn * math.sin(e)
            dz = -sn * math.cos(e) * np.cos(a) + c * math.sin(e)
            np.testing.assert_allclose(f.points[low, 0], h * dx / -dz, rtol=1e-5, err_msg=f"h {h} pitch {p}")
            # straight ahead that is h / tan(12.5 deg + pitch): positive pitch brings the ring closer
            assert abs(float(np.median(f.points[low, 0])) - h / math.tan(math.radians(12.5 + p))) < 0.01 * h / math.tan(
                math.radians(12.5 + p)) + 0.02
    assert checked >= 6
