"""The highway: a centre line with straight, transition (clothoid) and circular sections,
two carriageways of `lanes_per_direction` lanes each, a median, and barriers.

Lane coordinates: `s` is the arc length along the centre line (metres), `d` the signed
lateral offset from it (metres, positive to the left of the +s direction). The centre
line runs down the middle of the median. The ego's carriageway drives towards +s on the
right (d < 0), the opposite carriageway towards -s on the left (d > 0). Lanes are
numbered from the median outwards: lane 0 is the inner (fast) lane, lane n-1 the outer
one; lane k of the ego's carriageway is centred at d = -(median/2 + (k + 1/2) w), lane k
of the opposite one at d = +(median/2 + (k + 1/2) w).

The world frame is a flat plane (z = 0 is the road surface everywhere). A point (s, d)
maps to c(s) + d n(s), where c is the centre line and n its left normal; a vehicle there
is headed along the tangent (plus its own yaw offset).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RoadLayout:
    """Cross-section of the road (metres)."""

    lanes_per_direction: int = 4
    lane_width: float = 3.5
    median_width: float = 3.0  # between the inner lane edges of the two carriageways
    shoulder: float = 1.0  # outside the outer lane, before the outer barrier

    def lane_offset(self, lane, opposite=False):
        """Lateral offset d (metres) of the centre of `lane` (int or int array)."""
        k = np.asarray(lane, dtype=np.float64)
        mag = self.median_width / 2.0 + (k + 0.5) * self.lane_width
        return mag if opposite else -mag

    @property
    def edge_offset(self) -> float:
        """|d| of the outer edge of the paved shoulder (metres)."""
        return self.median_width / 2.0 + self.lanes_per_direction * self.lane_width + self.shoulder


class Road:
    """A centre line sampled every `step` metres over [s_start, s_end].

    `curvature` (1/m, positive turns left) is given at the samples; heading and position are
    integrated from it. Queries between samples interpolate linearly (exact enough: 1 m
    steps on a 300 m radius are 0.4 mm off the arc).
    """

    def __init__(self, layout: RoadLayout, s_start: float, curvature: np.ndarray, step: float = 1.0):
        curvature = np.asarray(curvature, dtype=np.float64)
        if curvature.ndim != 1 or curvature.size < 2:
            raise ValueError("Road: curvature must be a 1-D array of at least 2 samples")
        self.layout = layout
        self.step = float(step)
        self.s_start = float(s_start)
        self.kappa = curvature
        n = curvature.size
        self.s_end = self.s_start + (n - 1) * self.step
        theta = np.zeros(n)
        theta[1:] = np.cumsum(0.5 * (curvature[1:] + curvature[:-1]) * self.step)
        mid = 0.5 * (theta[1:] + theta[:-1])
        x = np.zeros(n)
        y = np.zeros(n)
        x[1:] = np.cumsum(np.cos(mid) * self.step)
        y[1:] = np.cumsum(np.sin(mid) * self.step)
        self.theta, self.x, self.y = theta, x, y

    @classmethod
    def straight(cls, layout: RoadLayout, s_start: float = -1000.0, length: float = 10000.0) -> Road:
        """A straight road along +x from s_start (the world x equals s)."""
        n = int(math.ceil(length)) + 1
        road = cls(layout, s_start, np.zeros(n), 1.0)
        road.x = road.x + s_start
        return road

    @classmethod
    def random(cls, layout: RoadLayout, rng: np.random.Generator, s_start: float, length: float,
               curve_fraction: float, radius_m: tuple[float, float], curve_length_m: tuple[float, float],
               straight_length_m: tuple[float, float], transition_m: float, step: float = 1.0) -> Road:
        """A road of `length` metres: straights and arcs, joined by linear-curvature transitions.

        Each section after a straight is an arc with probability `curve_fraction` (radius
        uniform in `radius_m`, turning left or right at random, arc length uniform in
        `curve_length_m`), else another straight (length uniform in `straight_length_m`).
        """
        n = int(math.ceil(length / step)) + 1
        kappa = np.zeros(n)
        pos = 0.0
        curve_next = rng.random() < curve_fraction
        t = max(float(transition_m), 0.0)
        while pos < length:
            if not curve_next:
                pos += float(rng.uniform(*straight_length_m))
                curve_next = rng.random() < curve_fraction
                continue
            radius = float(rng.uniform(*radius_m))
            k = (1.0 if rng.random() < 0.5 else -1.0) / radius
            arc = float(rng.uniform(*curve_length_m))
            for plen, kind in ((t, "up"), (arc, "flat"), (t, "down")):
                a, b = int(pos / step), min(int((pos + plen) / step), n)
                if b > a:
                    frac = (np.arange(a, b) - a) / (b - a)
                    kappa[a:b] = k * (frac if kind == "up" else 1.0 if kind == "flat" else 1.0 - frac)
                pos += plen
            curve_next = False  # a straight always follows a curve
        return cls(layout, s_start, kappa, step)

    # ------------------------------------------------------------------ queries
    def _check(self, s: np.ndarray) -> None:
        if s.size and (s.min() < self.s_start - 1e-6 or s.max() > self.s_end + 1e-6):
            raise ValueError(f"Road: s outside the generated road [{self.s_start:.1f}, {self.s_end:.1f}] m "
                             f"(got {s.min():.1f}..{s.max():.1f}); generate a longer road")

    def centre(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, heading, curvature) of the centre line at arc length(s) `s` (metres, radians, 1/m)."""
        s = np.asarray(s, dtype=np.float64)
        self._check(s)
        u = (s - self.s_start) / self.step
        i = np.clip(np.floor(u).astype(np.int64), 0, self.kappa.size - 2)
        f = u - i

        def lerp(a):
            return a[i] * (1.0 - f) + a[i + 1] * f

        return lerp(self.x), lerp(self.y), lerp(self.theta), lerp(self.kappa)

    def to_world(self, s, d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (x, y, tangent heading) of lane coordinates (s, d) (arrays broadcast)."""
        cx, cy, th, _ = self.centre(s)
        d = np.asarray(d, dtype=np.float64)
        return cx - d * np.sin(th), cy + d * np.cos(th), th

    def barrier_segments(self, s_from: float, s_to: float, offsets, height: float, width: float,
                         seg_len: float) -> np.ndarray:
        """Barrier boxes (K, 7) world x, y, z, dx, dy, dz, heading along [s_from, s_to].

        One chord box per `seg_len` metres for each lateral offset in `offsets` (metres);
        boxes are lengthened by 5 cm so the chain has no gaps on curves.
        """
        s_from = max(s_from, self.s_start)
        s_to = min(s_to, self.s_end)
        if s_to <= s_from or not len(offsets):
            return np.zeros((0, 7))
        k0 = math.floor(s_from / seg_len)
        k1 = math.ceil(s_to / seg_len)
        knots = np.clip(np.arange(k0, k1 + 1) * seg_len, self.s_start, self.s_end)
        out = []
        for off in offsets:
            x, y, _ = self.to_world(knots, np.full(knots.shape, float(off)))
            dx, dy = np.diff(x), np.diff(y)
            length = np.hypot(dx, dy)
            keep = length > 1e-6
            seg = np.zeros((int(keep.sum()), 7))
            seg[:, 0] = (x[:-1] + 0.5 * dx)[keep]
            seg[:, 1] = (y[:-1] + 0.5 * dy)[keep]
            seg[:, 2] = height / 2.0
            seg[:, 3] = length[keep] + 0.05
            seg[:, 4] = width
            seg[:, 5] = height
            seg[:, 6] = np.arctan2(dy, dx)[keep]
            out.append(seg)
        return np.concatenate(out, axis=0)


__all__ = ["Road", "RoadLayout"]
