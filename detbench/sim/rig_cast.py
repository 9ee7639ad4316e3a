"""Casting a rig: every sensor of a `Rig` over one scene, the returns merged into one ego-frame cloud.

Each sensor is cast in the frame of its column (origin on the road under it, x along its yaw): the
scene's objects and boxes are moved into that frame, the sensor's roll and pitch turn its rays, and its
points come back to the ego frame. The ego in the scene is the rig's body (hood, body and cabin boxes that
occlude and, without the self-filter, return points) or, without the body, the single-sensor studies'
idealised box, which a sensor mounted within it ignores. Per-box counts are summed over the sensors; each
point keeps the index of the sensor that saw it. A rig of one sensor at the reference point without the
body is cast exactly as that sensor alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from detbench.data.regions import DETECTED_BOTTOM_LIFT
from detbench.sim.raycast import cast_lidar
from detbench.sim.scene_objects import KIND_EGO, SceneObjects, wrap_angle
from detbench.sim.rigs import EgoBody, Rig, RigSensor


@dataclass
class RigCast:
    """Output of `cast_rig`.

    points: (N, 4) float32 x, y, z, intensity in the ego frame, the sensors' returns one after another;
    sensor_index: (N,) int64 index in `rig.sensors` of the sensor of each point;
    point_box: (N,) int64 row of the scene's boxes containing each point (bottom lift applied) or -1;
    counts: (M,) int64 points inside each box, summed over the sensors;
    self_hits: (S,) int64 rays of each sensor whose first hit is the ego (of the rays traced);
    rays_cast: rays traced over all sensors.
    """

    points: np.ndarray
    sensor_index: np.ndarray
    point_box: np.ndarray
    counts: np.ndarray
    self_hits: np.ndarray
    rays_cast: int
    timings: dict = field(default_factory=dict)


def with_ego(scene: SceneObjects, ego: tuple[tuple, tuple, np.ndarray] | None) -> SceneObjects:
    """The scene with its KIND_EGO objects replaced by `ego` ((pose, label, parts) or None: no ego).

    The boxes (vehicles) are the scene's, unchanged."""
    not_ego = scene.kind != KIND_EGO
    keep = np.flatnonzero(not_ego)
    pose, label, part_start = scene.pose[keep], scene.label[keep], [0]
    parts = [scene.parts[scene.part_start[k]:scene.part_start[k + 1]] for k in keep]
    kind, refl, bidx = scene.kind[keep], scene.reflectivity[keep], scene.box_index[keep]
    if ego is not None:
        pose = np.vstack([pose, np.asarray(ego[0], np.float64)[None]])
        label = np.vstack([label, np.asarray(ego[1], np.float64)[None]])
        parts.append(np.asarray(ego[2], np.float64).reshape(-1, 6))
        kind = np.append(kind, np.int32(KIND_EGO)).astype(np.int32)
        refl = np.append(refl, 0.5)
        bidx = np.append(bidx, -1).astype(np.int64)
    for p in parts:
        part_start.append(part_start[-1] + len(p))
    all_parts = np.concatenate(parts, axis=0) if parts else np.zeros((0, 6))
    return SceneObjects(np.ascontiguousarray(pose), np.ascontiguousarray(label), np.ascontiguousarray(all_parts),
                        np.asarray(part_start, np.int64), np.ascontiguousarray(kind), np.ascontiguousarray(refl),
                        np.ascontiguousarray(bidx), scene.boxes)


def body_object(body: EgoBody) -> tuple[tuple, tuple, np.ndarray]:
    """The rig's body as one ego object (pose at the reference point, label box around its parts, parts)."""
    parts = body.parts()
    lo = (parts[:, :3] - parts[:, 3:]).min(axis=0)
    hi = (parts[:, :3] + parts[:, 3:]).max(axis=0)
    lo[2] = 0.0
    c, h = (lo + hi) / 2, (hi - lo) / 2
    return (0.0, 0.0, 0.0), (c[0], c[1], c[2], h[0], h[1], h[2]), parts


def _inside_ego(scene: SceneObjects, x: float, y: float, z: float) -> bool:
    """True when (x, y, z) lies within a part of a KIND_EGO object of the scene."""
    for k in np.flatnonzero(scene.kind == KIND_EGO):
        c, s = math.cos(scene.pose[k, 2]), math.sin(scene.pose[k, 2])
        rx, ry = x - scene.pose[k, 0], y - scene.pose[k, 1]
        lx, ly = c * rx + s * ry, -s * rx + c * ry
        for p in scene.parts[scene.part_start[k]:scene.part_start[k + 1]]:
            if abs(lx - p[0]) <= p[3] and abs(ly - p[1]) <= p[4] and abs(z - p[2]) <= p[5]:
                return True
    return False


def to_sensor_frame(scene: SceneObjects, sensor: RigSensor) -> SceneObjects:
    """The scene moved into the frame of the sensor's column (origin under it, x along its yaw)."""
    if sensor.x == 0.0 and sensor.y == 0.0 and sensor.yaw_deg == 0.0:
        return scene
    yaw = math.radians(sensor.yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    pose = scene.pose.copy()
    dx, dy = scene.pose[:, 0] - sensor.x, scene.pose[:, 1] - sensor.y
    pose[:, 0], pose[:, 1] = c * dx + s * dy, -s * dx + c * dy
    pose[:, 2] = wrap_angle(scene.pose[:, 2] - yaw)
    boxes = scene.boxes.copy()
    if len(boxes):
        b = scene.boxes.astype(np.float64)
        bx, by = b[:, 0] - sensor.x, b[:, 1] - sensor.y
        boxes[:, 0], boxes[:, 1] = c * bx + s * by, -s * bx + c * by
        boxes[:, 6] = wrap_angle(b[:, 6] - yaw)
    return SceneObjects(pose, scene.label, scene.parts, scene.part_start, scene.kind, scene.reflectivity,
                        scene.box_index, boxes)


def to_ego_frame(points: np.ndarray, sensor: RigSensor) -> np.ndarray:
    """(N, 4) float32 points of a sensor's column frame in the ego frame."""
    if sensor.x == 0.0 and sensor.y == 0.0 and sensor.yaw_deg == 0.0:
        return points
    yaw = math.radians(sensor.yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    p = points.astype(np.float64)
    out = points.copy()
    out[:, 0] = sensor.x + c * p[:, 0] - s * p[:, 1]
    out[:, 1] = sensor.y + s * p[:, 0] + c * p[:, 1]
    return out


def rig_scene(rig: Rig, scene: SceneObjects, sensor: RigSensor) -> SceneObjects:
    """The scene one sensor of the rig sees: the rig's body as the ego, or the idealised ego box unless the
    sensor is mounted within it."""
    if rig.ego_body:
        return with_ego(scene, body_object(rig.body))
    if _inside_ego(scene, sensor.x, sensor.y, float(sensor.lidar.height)):
        return with_ego(scene, None)
    return scene


def cast_rig(rig: Rig, scene: SceneObjects, keys: list[int], with_points: bool = True,
             bottom_lift: float = DETECTED_BOTTOM_LIFT, ground_reflectivity: float = 0.3,
             timings: dict | None = None) -> RigCast:
    """Cast every sensor of `rig` over `scene` (ego frame, with the idealised ego box) and merge the returns.

    keys: one 64-bit noise key per sensor. See the module doc.
    """
    pts, sidx, pbox, self_hits = [], [], [], []
    counts = np.zeros(len(scene.boxes), np.int64)
    rays = 0
    keep_ego = rig.ego_body and not rig.self_filter
    for i, (sensor, key) in enumerate(zip(rig.sensors, keys)):
        local = to_sensor_frame(rig_scene(rig, scene, sensor), sensor)
        res = cast_lidar(sensor.lidar, local, key=key, with_points=with_points, bottom_lift=bottom_lift,
                         ground_reflectivity=ground_reflectivity, timings=timings, roll_deg=sensor.roll_deg,
                         keep_ego=keep_ego)
        counts += res.counts
        rays += res.rays_cast
        self_hits.append(res.self_hits)
        pts.append(to_ego_frame(res.points, sensor))
        sidx.append(np.full(len(res.points), i, np.int64))
        pbox.append(res.point_box)
    return RigCast(np.concatenate(pts).astype(np.float32, copy=False), np.concatenate(sidx), np.concatenate(pbox),
                   counts, np.asarray(self_hits, np.int64), rays, timings if timings is not None else {})


__all__ = ["RigCast", "cast_rig", "with_ego", "body_object", "to_sensor_frame", "to_ego_frame", "rig_scene"]
