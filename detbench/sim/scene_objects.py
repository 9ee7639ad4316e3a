"""The objects of one time step as the ray caster reads them, and how to build them.

Everything is in the ego ground frame: x forward, y left, z up, metres. An object (a vehicle, an occluder
such as a barrier, or the ego) has a yaw pose (x, y, heading), a label box and one or more parts, both
axis-aligned boxes in the object's own frame (origin on the road under the pose, x along its heading).
`pack_scene` packs per-object lists into the flat arrays `detbench.sim.raycast.cast_lidar` reads;
`make_scene` builds a scene from explicit objects for tests and experiments.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from detbench.sim.vehicles import label_box_local

KIND_VEHICLE = 0
KIND_OCCLUDER = 1
KIND_EGO = 2

TWO_PI = 2.0 * math.pi


@dataclass
class SceneObjects:
    """Objects of one time step in the ego ground frame (see module doc).

    pose: (K, 3) float64 x, y (metres), heading (radians);
    label: (K, 6) float64 label box in the object frame: cx, cy, cz, hx, hy, hz (half sizes);
    parts: (P, 6) float64 parts in their object's frame, same layout;
    part_start: (K + 1,) int64, object k owns parts[part_start[k]:part_start[k + 1]];
    kind: (K,) int32 KIND_VEHICLE / KIND_OCCLUDER / KIND_EGO;
    reflectivity: (K,) float64 in [0, 1];
    box_index: (K,) int64 row of the object in `boxes` (vehicles) or -1;
    boxes: (M, 7) float32 the vehicles' label boxes x, y, z, dx, dy, dz, heading.
    """

    pose: np.ndarray
    label: np.ndarray
    parts: np.ndarray
    part_start: np.ndarray
    kind: np.ndarray
    reflectivity: np.ndarray
    box_index: np.ndarray
    boxes: np.ndarray

    @property
    def num_objects(self) -> int:
        return int(self.pose.shape[0])


def wrap_angle(a):
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + math.pi) % TWO_PI - math.pi


def boxes_from_objects(pose: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(K, 7) float32 label boxes in the ego frame from object poses (K, 3) and local labels (K, 6)."""
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    out = np.empty((pose.shape[0], 7), dtype=np.float64)
    out[:, 0] = pose[:, 0] + c * label[:, 0] - s * label[:, 1]
    out[:, 1] = pose[:, 1] + s * label[:, 0] + c * label[:, 1]
    out[:, 2] = label[:, 2]
    out[:, 3:6] = 2.0 * label[:, 3:6]
    out[:, 6] = wrap_angle(pose[:, 2])
    return out.astype(np.float32)


def make_scene(vehicles=(), occluders=(), ego: tuple[float, float, float] | None = None) -> SceneObjects:
    """A scene from explicit objects, for tests and experiments (ego ground frame, metres/radians).

    vehicles: iterable of (parts (P, 6), x, y, heading) or (parts, x, y, heading, reflectivity):
      parts in the vehicle frame (see detbench.sim.vehicles); the label box is their tight box
      from z = 0 (use `detbench.sim.vehicles.label_box_local` rules, no margin);
    occluders: iterable of boxes (x, y, z, dx, dy, dz, heading) that block rays and give
      points but are never counted (barriers, walls);
    ego: optional (length, width, height) of the ego body, placed behind the sensor
      (x in [-length, 0), centred on y = 0): it blocks rays and gives no points.
    """
    poses, labels, part_list, kinds, refl, bidx = [], [], [], [], [], []
    nveh = 0
    for v in vehicles:
        parts, x, y, hd = v[:4]
        parts = np.asarray(parts, dtype=np.float64).reshape(-1, 6)
        lb = label_box_local(parts, 0.0)
        poses.append((x, y, hd))
        labels.append((lb[0], lb[1], lb[2], lb[3] / 2, lb[4] / 2, lb[5] / 2))
        part_list.append(parts)
        kinds.append(KIND_VEHICLE)
        refl.append(float(v[4]) if len(v) > 4 else 0.7)
        bidx.append(nveh)
        nveh += 1
    for o in occluders:
        x, y, z, dx, dy, dz, hd = (float(u) for u in o)
        loc = np.array([[0.0, 0.0, z, dx / 2, dy / 2, dz / 2]])
        poses.append((x, y, hd))
        labels.append(tuple(loc[0]))
        part_list.append(loc)
        kinds.append(KIND_OCCLUDER)
        refl.append(0.5)
        bidx.append(-1)
    if ego is not None:
        L, W, H = ego
        loc = np.array([[0.0, 0.0, H / 2, L / 2, W / 2, H / 2]])
        poses.append((-L / 2 - 0.05, 0.0, 0.0))
        labels.append(tuple(loc[0]))
        part_list.append(loc)
        kinds.append(KIND_EGO)
        refl.append(0.0)
        bidx.append(-1)
    return pack_scene(poses, labels, part_list, kinds, refl, bidx)


def pack_scene(poses, labels, part_list, kinds, refl, box_index) -> SceneObjects:
    """SceneObjects from per-object lists (see `SceneObjects` for the layouts)."""
    K = len(poses)
    pose = np.asarray(poses, dtype=np.float64).reshape(K, 3)
    label = np.asarray(labels, dtype=np.float64).reshape(K, 6)
    sizes = np.array([len(p) for p in part_list], dtype=np.int64)
    part_start = np.zeros(K + 1, dtype=np.int64)
    np.cumsum(sizes, out=part_start[1:])
    parts = np.concatenate(part_list, axis=0).astype(np.float64) if K else np.zeros((0, 6))
    kind = np.asarray(kinds, dtype=np.int32).reshape(K)
    box_index = np.asarray(box_index, dtype=np.int64).reshape(K)
    veh = box_index >= 0
    order = np.argsort(box_index[veh], kind="stable")
    boxes = boxes_from_objects(pose[veh][order], label[veh][order]) if veh.any() else np.zeros((0, 7), np.float32)
    return SceneObjects(pose, label, np.ascontiguousarray(parts), part_start, kind,
                        np.asarray(refl, dtype=np.float64).reshape(K), box_index, boxes)


__all__ = ["SceneObjects", "make_scene", "pack_scene", "boxes_from_objects", "wrap_angle",
           "KIND_VEHICLE", "KIND_OCCLUDER", "KIND_EGO"]
