"""Vehicle types and their shapes: every vehicle is a few boxes ("parts") in its own frame.

Vehicle frame: x forward, y left, z up, metres; the origin is on the road at the centre of
the vehicle's footprint. A part is (cx, cy, cz, hx, hy, hz): centre and half sizes, axis
aligned in the vehicle frame (all parts share the vehicle's heading).

Shapes (each from published dimensions; length/width/height spreads come from the config):
- sedan: lower body from the ground clearance to the belt line over the full length and
  width, a narrower and shorter greenhouse (cabin) up to the roof, four wheels;
- suv: the same with more clearance, a higher belt line and a longer, squarer cabin;
- taxi: a sedan with a roof sign (part of the label box);
- van: a low bonnet at the front and a tall box behind it, four wheels;
- truck: cab (cab-over) + gap + cargo box raised on a chassis, side guards/tanks/frame
  closing the space under the cargo box down to ~0.5 m, front wheels and a rear tandem;
- bus: one tall body on raised floor, four wheels.

The label box of a vehicle is the tight box around all its parts, from the road surface
(z = 0) to the roof, enlarged by `label_margin` metres on the four sides and the top (the
parts are built so that their union spans exactly length x width x height).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SHAPES = ("sedan", "suv", "taxi", "van", "truck", "bus")


@dataclass(frozen=True)
class VehicleType:
    """Size distribution of one class: (mean, std, min, max) in metres for each dimension."""

    name: str
    shape: str
    length: tuple[float, float, float, float]
    width: tuple[float, float, float, float]
    height: tuple[float, float, float, float]
    speed_factor: float = 1.0  # desired speed relative to the speed limit
    outer_lanes_only: int = 0  # >0: only the n outer lanes of a carriageway (trucks keep right)
    lane_change: bool = True


@dataclass
class VehicleShape:
    """One sampled vehicle: class name, label size (metres), parts (P, 6), reflectivity in [0, 1]."""

    cls: str
    length: float
    width: float
    height: float
    parts: np.ndarray
    reflectivity: float


def _draw(rng: np.random.Generator, spec: tuple[float, float, float, float]) -> float:
    mean, std, lo, hi = spec
    return float(np.clip(rng.normal(mean, std) if std > 0 else mean, lo, hi))


def _box(x0, x1, y0, y1, z0, z1) -> list[float]:
    return [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2, (x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2]


def _wheels(length, width, radius, wheel_w, axles_x) -> list[list[float]]:
    y = width / 2 - wheel_w / 2
    out = []
    for ax, alen in axles_x:
        for side in (-1.0, 1.0):
            out.append(_box(ax - alen / 2, ax + alen / 2, side * y - wheel_w / 2, side * y + wheel_w / 2,
                            0.0, 2 * radius))
    return out


def build_parts(shape: str, length: float, width: float, height: float, rng: np.random.Generator) -> np.ndarray:
    """Parts (P, 6) of a vehicle of the given shape and overall size (metres).

    The union of the parts spans exactly [-L/2, L/2] x [-W/2, W/2] x [0 or clearance, H];
    their bounding box therefore has the vehicle's size (z from the ground when the
    wheels reach it, which all shapes have).
    """
    L, W, H = length, width, height

    def u(a, b):
        return float(rng.uniform(a, b))

    parts: list[list[float]] = []
    if shape in ("sedan", "taxi", "suv"):
        suv = shape == "suv"
        roof = H
        if shape == "taxi":
            sign_h = u(0.2, 0.28)
            roof = H - sign_h
        clear = u(0.18, 0.24) if suv else u(0.13, 0.18)
        belt = roof * (u(0.6, 0.66) if suv else u(0.68, 0.74))
        cab_len = L * (u(0.56, 0.66) if suv else u(0.45, 0.54))
        cab_w = W * (u(0.88, 0.93) if suv else u(0.84, 0.9))
        cab_x = -L * (u(0.04, 0.1) if suv else u(0.03, 0.09))
        radius = u(0.34, 0.39) if suv else u(0.3, 0.33)
        parts.append(_box(-L / 2, L / 2, -W / 2, W / 2, clear, belt))
        parts.append(_box(cab_x - cab_len / 2, cab_x + cab_len / 2, -cab_w / 2, cab_w / 2, belt, roof))
        if shape == "taxi":
            sx = cab_x + u(-0.1, 0.1) * cab_len
            parts.append(_box(sx - 0.15, sx + 0.15, -0.3, 0.3, roof, H))
        over = L * 0.2
        parts += _wheels(L, W, radius, 0.22,
                         ((L / 2 - over, 2 * radius * 0.9), (-L / 2 + over * 1.05, 2 * radius * 0.9)))
    elif shape == "van":
        clear = u(0.17, 0.22)
        bonnet_len = L * u(0.14, 0.2)
        bonnet_h = u(1.0, 1.2)
        radius = u(0.34, 0.37)
        parts.append(_box(L / 2 - bonnet_len, L / 2, -W / 2, W / 2, clear, bonnet_h))
        parts.append(_box(-L / 2, L / 2 - bonnet_len, -W / 2, W / 2, clear, H))
        parts += _wheels(L, W, radius, 0.24,
                         ((L / 2 - L * 0.17, 2 * radius * 0.9), (-L / 2 + L * 0.2, 2 * radius * 0.9)))
    elif shape == "truck":
        cab_len = u(2.0, 2.4)
        cab_h = min(H, u(2.9, 3.4))
        cab_w = W * u(0.94, 0.98)
        gap = u(0.3, 0.6)
        cargo_bottom = u(1.0, 1.3)
        radius = u(0.47, 0.52)
        parts.append(_box(L / 2 - cab_len, L / 2, -cab_w / 2, cab_w / 2, u(0.3, 0.4), cab_h))
        parts.append(_box(-L / 2, L / 2 - cab_len - gap, -W / 2, W / 2, cargo_bottom, H))
        # under the cargo box: side guards, tanks and frame (EU trucks must have side guards)
        parts.append(_box(-L / 2 + 0.3, L / 2 - cab_len, -W / 2 + 0.05, W / 2 - 0.05, u(0.3, 0.4), cargo_bottom))
        tandem = min(2.6, 0.35 * L)
        rear_x = -L / 2 + max(0.15 * L, tandem / 2 + 0.3)
        parts += _wheels(L, W, radius, 0.3, ((L / 2 - 1.3, 2 * radius * 0.9), (rear_x, tandem)))
    elif shape == "bus":
        radius = u(0.48, 0.52)
        parts.append(_box(-L / 2, L / 2, -W / 2, W / 2, u(0.3, 0.4), H))
        parts += _wheels(L, W, radius, 0.3, ((L / 2 - 2.6, 2 * radius * 0.9), (-L / 2 + 3.0, 2 * radius * 0.9)))
    else:
        raise ValueError(f"unknown vehicle shape {shape!r}; use one of {', '.join(SHAPES)}")
    return np.asarray(parts, dtype=np.float64)


class VehicleCatalog:
    """Vehicle classes with their mix (probabilities) and size spreads, from the `vehicles` config."""

    def __init__(self, cfg: dict):
        self.label_margin = float(cfg.get("label_margin_m", 0.0))
        if self.label_margin < 0:
            raise ValueError("vehicles.label_margin_m must be >= 0 metres")
        types = cfg["types"]
        mix = cfg["mix"]
        self.types: dict[str, VehicleType] = {}
        for name, t in types.items():
            shape = t.get("shape", name)
            if shape not in SHAPES:
                raise ValueError(f"vehicles.types.{name}.shape: unknown shape {shape!r}; "
                                 f"use one of {', '.join(SHAPES)}")
            dims = {}
            for k in ("length_m", "width_m", "height_m"):
                v = t[k]
                if not (isinstance(v, (list, tuple)) and len(v) == 4) or not (0 < v[2] <= v[0] <= v[3]):
                    raise ValueError(f"vehicles.types.{name}.{k} must be [mean, std, min, max] metres with "
                                     f"0 < min <= mean <= max, got {v!r}")
                dims[k] = tuple(float(x) for x in v)
            self.types[name] = VehicleType(name, shape, dims["length_m"], dims["width_m"], dims["height_m"],
                                           float(t.get("speed_factor", 1.0)), int(t.get("outer_lanes_only", 0)),
                                           bool(t.get("lane_change", True)))
        unknown = [k for k in mix if k not in self.types]
        if unknown:
            raise ValueError(f"vehicles.mix names unknown type(s) {unknown}; known: {', '.join(self.types)}")
        w = np.array([float(mix.get(k, 0.0)) for k in self.types])
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError("vehicles.mix: weights must be >= 0 and not all zero")
        self.names = list(self.types)
        self.probs = w / w.sum()
        self.deck_size = int(cfg.get("mix_deck_size", 0))
        if self.deck_size < 0:
            raise ValueError("vehicles.mix_deck_size must be >= 0 (0 draws every type independently)")

    def sample_type(self, rng: np.random.Generator) -> str:
        return self.names[int(rng.choice(len(self.names), p=self.probs))]

    def deck(self, rng: np.random.Generator) -> TypeDeck | None:
        """A stratified type deck for one scene (None when `mix_deck_size` is 0)."""
        return TypeDeck(self.names, self.probs, self.deck_size, rng) if self.deck_size > 0 else None

    def sample(self, rng: np.random.Generator, type_name: str | None = None) -> VehicleShape:
        """One vehicle: its class, label size (metres, margin included), parts and reflectivity."""
        t = self.types[type_name or self.sample_type(rng)]
        L, W, H = _draw(rng, t.length), _draw(rng, t.width), _draw(rng, t.height)
        parts = build_parts(t.shape, L, W, H, rng)
        m = self.label_margin
        return VehicleShape(t.name, L + 2 * m, W + 2 * m, H + m, parts, float(rng.uniform(0.35, 0.95)))


class TypeDeck:
    """Vehicle types dealt from shuffled decks of `size` cards that hold the mix in proportion.

    Each deck gets size x p_k cards of type k, rounded by systematic sampling (one random
    offset, so the expected count is exactly size x p_k); a new deck is shuffled when one
    runs out. Every type keeps its probability, but a scene's share of trucks or vans
    scatters much less than with independent draws.
    """

    def __init__(self, names: list[str], probs: np.ndarray, size: int, rng: np.random.Generator):
        self.names = list(names)
        self.cdf = np.cumsum(np.asarray(probs, dtype=np.float64))
        self.cdf[-1] = 1.0
        self.size = int(size)
        self.rng = rng
        self.cards: list[int] = []

    def _deal(self) -> None:
        u = (self.rng.random() + np.arange(self.size)) / self.size
        cards = np.searchsorted(self.cdf, u, side="right")
        self.rng.shuffle(cards)
        self.cards = [int(c) for c in cards]

    def draw(self) -> str:
        if not self.cards:
            self._deal()
        return self.names[self.cards.pop()]


def label_box_local(parts: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Tight box (7,) x, y, z, dx, dy, dz, 0 around parts (P, 6), from z = 0, grown by `margin`."""
    lo = (parts[:, :3] - parts[:, 3:]).min(axis=0)
    hi = (parts[:, :3] + parts[:, 3:]).max(axis=0)
    lo = np.array([lo[0] - margin, lo[1] - margin, 0.0])
    hi = hi + np.array([margin, margin, margin])
    c = (lo + hi) / 2
    return np.array([c[0], c[1], c[2], hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.0])


__all__ = ["VehicleType", "VehicleShape", "VehicleCatalog", "TypeDeck", "build_parts", "label_box_local", "SHAPES"]
