"""The near field of a rig: its ground blind zone and its LDR by distance and bearing in front of the ego.

Blind zone (`blind_zones`): every sensor of the rig is cast, noise-free, over a flat empty road with the
rig's ego (its body, or the idealised box without it); from the ground returns, measured from the ego's
outline (the rig file's body: front bumper at x = 0, half width W/2, length L):
- ahead: the nearest ground return in front of the bumper within the car's width (x >= 0, |y| <= W/2), its x;
- front_left / front_right: the nearest ground return ahead of and outside a front corner (x >= 0,
  |y| >= W/2), its distance from that corner;
- left / right: the nearest ground return beside the car (-L <= x <= 0, |y| >= W/2), its distance from
  the car's side.
None where no ray reaches the ground there. The blind zone is a property of the rig and its body: other
traffic only hides more ground.

Near-field LDR (`NearFieldCounts`): vehicles whose box centre lies in the front half (x >= 0) within
NEAR_RANGE_M of the reference point, binned by distance (NEAR_BIN_M rings) and bearing (NEAR_BEARING_BIN_DEG
sectors from -90 to 90 degrees, counter-clockwise from +x): total and LiDAR-detected per rig.
"""
from __future__ import annotations

import math

import numpy as np

from detbench.data.regions import DETECTED_MIN_POINTS
from detbench.sim.raycast import cast_lidar
from detbench.sim.scene_objects import KIND_EGO, pack_scene
from detbench.sim.rig_cast import rig_scene, to_ego_frame, to_sensor_frame
from detbench.sim.rigs import EgoBody, Rig

NEAR_RANGE_M = 30.0
NEAR_BIN_M = 10.0
NEAR_BEARING_BIN_DEG = 30.0
BLIND_ZONE_DIRECTIONS = ("ahead", "front_left", "front_right", "left", "right")


def idealised_ego_scene(body: EgoBody):
    """A road with only the single-sensor studies' idealised ego box (the body's length, width and roof
    height, behind the reference point as the simulator places it)."""
    L, W, H = body.length_m, body.width_m, body.roof_height_m
    loc = np.array([[0.0, 0.0, H / 2, L / 2, W / 2, H / 2]])
    return pack_scene([(-0.5 * L - 0.01, 0.0, 0.0)], [tuple(loc[0])], [loc], [KIND_EGO], [0.0], [-1])


def rig_ground_points(rig: Rig, body: EgoBody) -> tuple[list[np.ndarray], np.ndarray]:
    """Noise-free returns of each sensor on the empty road ((N, 4) ego-frame points per sensor) and the rays
    of each sensor whose first hit is the ego (S,)."""
    scene = idealised_ego_scene(body)
    points, self_hits = [], []
    for s in rig.sensors:
        quiet = s.lidar.replace(range_noise_m=0.0, dropout=0.0, dropoff_zero_intensity=0.0)
        local = to_sensor_frame(rig_scene(rig, scene, s), s)
        res = cast_lidar(quiet, local, key=0, with_points=True, roll_deg=s.roll_deg)
        pts = to_ego_frame(res.points, s)
        points.append(pts[np.abs(pts[:, 2]) <= 1e-6])
        self_hits.append(res.self_hits)
    return points, np.asarray(self_hits, np.int64)


def _nearest(values: np.ndarray) -> float | None:
    return round(float(values.min()), 3) if values.size else None


def blind_zone(ground: np.ndarray, body: EgoBody) -> dict:
    """{direction: metres or None} of the ground points (N, >=2) around the body (see the module doc)."""
    x, y = ground[:, 0].astype(np.float64), ground[:, 1].astype(np.float64)
    w, L = body.width_m / 2, body.length_m
    front, beside = x >= 0, (x <= 0) & (x >= -L)
    return {
        "ahead": _nearest(x[front & (np.abs(y) <= w)]),
        "front_left": _nearest(np.hypot(x, y - w)[front & (y >= w)]),
        "front_right": _nearest(np.hypot(x, -y - w)[front & (y <= -w)]),
        "left": _nearest((y - w)[beside & (y >= w)]),
        "right": _nearest((-y - w)[beside & (y <= -w)]),
    }


def blind_zones(rig: Rig, body: EgoBody) -> dict:
    """The rig's blind zone (all sensors together), each sensor's, and the rays the body takes from each
    sensor: {"blind_zone_m", "per_sensor": {name: {"blind_zone_m", "self_hits", "rays"}}, "self_hits"}."""
    points, hits = rig_ground_points(rig, body)
    per = {s.name: {"blind_zone_m": blind_zone(p, body), "self_hits": int(h), "rays": int(s.lidar.num_rays)}
           for s, p, h in zip(rig.sensors, points, hits)}
    return {"blind_zone_m": blind_zone(np.concatenate(points), body), "per_sensor": per,
            "self_hits": {s.name: int(h) for s, h in zip(rig.sensors, hits)}}


class NearFieldCounts:
    """Total and detected vehicles by distance ring and bearing sector in the front half (module doc)."""

    def __init__(self):
        self.num_rings = int(math.ceil(NEAR_RANGE_M / NEAR_BIN_M))
        self.num_sectors = int(math.ceil(180.0 / NEAR_BEARING_BIN_DEG))
        self.total: dict[str, np.ndarray] = {}
        self.detected: dict[str, np.ndarray] = {}

    def cells(self, boxes: np.ndarray) -> np.ndarray:
        """(M,) flat cell index (ring * sectors + sector) of each box, -1 outside the near field."""
        x, y = boxes[:, 0].astype(np.float64), boxes[:, 1].astype(np.float64)
        r = np.hypot(x, y)
        ring = np.minimum((r / NEAR_BIN_M).astype(np.int64), self.num_rings - 1)
        bearing = np.degrees(np.arctan2(y, x))
        sector = np.clip(((bearing + 90.0) / NEAR_BEARING_BIN_DEG).astype(np.int64), 0, self.num_sectors - 1)
        inside = (x >= 0) & (r <= NEAR_RANGE_M)
        return np.where(inside, ring * self.num_sectors + sector, -1)

    def add(self, key: str, boxes: np.ndarray, counts: np.ndarray) -> None:
        n = self.num_rings * self.num_sectors
        tot = self.total.setdefault(key, np.zeros(n, np.int64))
        det = self.detected.setdefault(key, np.zeros(n, np.int64))
        if not len(boxes):
            return
        cell = self.cells(np.asarray(boxes))
        sel = cell >= 0
        tot += np.bincount(cell[sel], minlength=n)
        det += np.bincount(cell[sel], weights=(np.asarray(counts)[sel] >= DETECTED_MIN_POINTS), minlength=n
                           ).astype(np.int64)

    def report(self) -> dict:
        """{"rings_m", "sectors_deg", "rigs": {key: {"total", "detected", "ldr"} as [ring][sector] lists}}."""
        def ratio(d, t):
            return [[(float(a) / float(b) if b else None) for a, b in zip(dr, tr)] for dr, tr in zip(d, t)]

        shape = (self.num_rings, self.num_sectors)
        out = {}
        for k in self.total:
            t, d = self.total[k].reshape(shape), self.detected[k].reshape(shape)
            out[k] = {"total": t.tolist(), "detected": d.tolist(), "ldr": ratio(d, t)}
        return {"region": f"box centre x >= 0 and within {NEAR_RANGE_M:g} m of the reference point",
                "rings_m": [[i * NEAR_BIN_M, min((i + 1) * NEAR_BIN_M, NEAR_RANGE_M)] for i in range(shape[0])],
                "sectors_deg": [[-90.0 + j * NEAR_BEARING_BIN_DEG, min(-90.0 + (j + 1) * NEAR_BEARING_BIN_DEG, 90.0)]
                                for j in range(shape[1])],
                "rigs": out}


__all__ = ["blind_zone", "blind_zones", "rig_ground_points", "idealised_ego_scene", "NearFieldCounts",
           "NEAR_RANGE_M", "NEAR_BIN_M", "NEAR_BEARING_BIN_DEG", "BLIND_ZONE_DIRECTIONS"]
