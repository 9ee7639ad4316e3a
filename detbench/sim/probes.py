"""The small-object probe: low static objects on the carriageway and the shoulder.

Three kinds, each a label box (length x width x height, metres) and its parts in the object's frame
(origin on the road at the footprint's centre):
- cone: a traffic cone of 0.3 x 0.3 x 0.7 m (a base plate and a narrower column);
- tyre: a lost car tyre lying flat, 0.63 m across (a 205/55 R16 tyre's diameter) and 0.21 m high;
- child: a child-sized box 1.2 m tall, 0.3 m deep and 0.45 m wide.
Per scene they are placed at random along the road (`PROBES_PER_KM` of road), each kind equally often, half
on the ego's carriageway (uniform across its lanes) and half on its outer shoulder, at a random yaw. They
stand still, occlude rays and return points like vehicles; traffic does not react to them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detbench.sim.scene_objects import wrap_angle
from detbench.sim.road import Road, RoadLayout

PROBES_PER_KM = 40.0
PROBE_KINDS = ("cone", "tyre", "child")
PROBE_PLACES = ("carriageway", "shoulder")
PROBE_REFLECTIVITY = 0.6


def _box(x0, x1, y0, y1, z0, z1) -> list[float]:
    return [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2, (x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2]


def probe_parts(kind: str) -> np.ndarray:
    """(P, 6) parts of one probe kind (see the module doc); their tight box is the label box."""
    if kind == "cone":
        return np.array([_box(-0.15, 0.15, -0.15, 0.15, 0.0, 0.04), _box(-0.09, 0.09, -0.09, 0.09, 0.04, 0.7)])
    if kind == "tyre":
        return np.array([_box(-0.315, 0.315, -0.2, 0.2, 0.0, 0.21), _box(-0.2, 0.2, -0.315, 0.315, 0.0, 0.21)])
    if kind == "child":
        return np.array([_box(-0.15, 0.15, -0.225, 0.225, 0.0, 1.2)])
    raise ValueError(f"unknown probe kind {kind!r}; known: {', '.join(PROBE_KINDS)}")


@dataclass
class Probes:
    """The probes of one scene in lane coordinates: s, d (metres), yaw (radians, relative to the road),
    kind and place indices into PROBE_KINDS and PROBE_PLACES."""

    s: np.ndarray
    d: np.ndarray
    yaw: np.ndarray
    kind: np.ndarray
    place: np.ndarray

    @classmethod
    def random(cls, layout: RoadLayout, rng: np.random.Generator, s_from: float, s_to: float) -> Probes:
        n = int(rng.poisson(PROBES_PER_KM * max(s_to - s_from, 0.0) / 1000.0))
        s = np.sort(rng.uniform(s_from, s_to, n))
        kind = rng.integers(0, len(PROBE_KINDS), n)
        place = rng.integers(0, len(PROBE_PLACES), n)
        inner = layout.median_width / 2.0
        outer = inner + layout.lanes_per_direction * layout.lane_width
        on_lane = rng.uniform(inner + 0.5, outer - 0.5, n)
        on_shoulder = rng.uniform(outer + 0.3, max(layout.edge_offset - 0.3, outer + 0.3), n)
        d = -np.where(place == 0, on_lane, on_shoulder)
        yaw = rng.uniform(-np.pi, np.pi, n)
        return cls(s, d, yaw, kind, place)

    def in_frame(self, road: Road, ox: float, oy: float, heading: float, x_lo: float, x_hi: float,
                 y_max: float) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame poses (K, 3) x, y, heading of the probes in the region, and their indices (K,)."""
        if not self.s.size:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        ok = (self.s >= road.s_start) & (self.s <= road.s_end)
        X, Y, TH = road.to_world(np.where(ok, self.s, road.s_start), self.d)
        c, s = np.cos(heading), np.sin(heading)
        lx = c * (X - ox) + s * (Y - oy)
        ly = -s * (X - ox) + c * (Y - oy)
        sel = np.flatnonzero(ok & (lx >= x_lo) & (lx <= x_hi) & (np.abs(ly) <= y_max))
        head = wrap_angle(TH + self.yaw - heading)
        return np.stack([lx[sel], ly[sel], head[sel]], axis=1), sel


__all__ = ["Probes", "probe_parts", "PROBE_KINDS", "PROBE_PLACES", "PROBES_PER_KM", "PROBE_REFLECTIVITY"]
