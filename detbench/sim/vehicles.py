"""Vehicles: CARLA's blueprints or per-class size distributions, each vehicle a few boxes ("parts").

Vehicle frame: x forward, y left, z up, metres; the origin is on the road at the centre of
the vehicle's footprint. A part is (cx, cy, cz, hx, hy, hz): centre and half sizes, axis
aligned in the vehicle frame (all parts share the vehicle's heading).

Two ways to draw a vehicle (`vehicles.draw` in configs/sim.yaml):
- blueprints: one of CARLA's blueprints, uniformly (as CARLA's generate_traffic.py picks them),
  every instance of a blueprint with its one size and shape; the label box is the blueprint's
  bounding box and the parts span it shrunk by `label_margin` (on the four sides and the top),
  narrower where the blueprint's body is narrower than its box (a box that holds mirrors);
- types: a class, then its length, width and height drawn independently from truncated
  normals; the label box is the parts' tight box grown by `label_margin`.

Shapes (each from published dimensions; the overall size comes from the blueprint or the class):
- sedan: lower body from the ground clearance to the belt line over the full length and
  width, a narrower and shorter greenhouse (cabin) up to the roof, four wheels;
- suv: the same with more clearance, a higher belt line and a longer, squarer cabin;
- taxi: a sedan with a roof sign (part of the label box);
- van: a low bonnet at the front and a tall box behind it, four wheels;
- truck: cab (cab-over) + gap + cargo box raised on a chassis, side guards/tanks/frame
  closing the space under the cargo box down to ~0.5 m, front wheels and a rear tandem;
- bus: one tall body on raised floor, four wheels.

The label box runs from the road surface (z = 0) to the roof; the parts are built so that
their union spans exactly the length x width x height they are built for.
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
    """One sampled vehicle: class name, label size (metres), parts (P, 6), reflectivity in [0, 1], and what it was
    drawn as (its blueprint id, or its class for a type)."""

    cls: str
    length: float
    width: float
    height: float
    parts: np.ndarray
    reflectivity: float
    name: str = ""


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


@dataclass(frozen=True)
class Blueprint:
    """One of CARLA's vehicle blueprints: id, class, shape, bounding box (metres) and body width (metres,
    at most the box width: a box may hold mirrors that the body does not)."""

    name: str
    cls: str
    shape: str
    length: float
    width: float
    height: float
    body_width: float
    speed_factor: float = 1.0
    outer_lanes_only: int = 0
    lane_change: bool = True


DRAWS = ("blueprints", "types")


def _blueprint(row, k: int) -> Blueprint:
    where = f"vehicles.blueprints[{k}]"
    if not (isinstance(row, (list, tuple)) and len(row) in (6, 7) and all(isinstance(v, str) for v in row[:3])
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in row[3:])):
        raise ValueError(f"{where} must be [blueprint id, class, shape, length, width, height] or with a body width "
                         f"after them (metres > 0), got {row!r} (configs/sim.yaml)")
    name, cls, shape = row[:3]
    if shape not in SHAPES:
        raise ValueError(f"{where} ({name}): unknown shape {shape!r}; use one of {', '.join(SHAPES)}")
    length, width, height = (float(v) for v in row[3:6])
    body = float(row[6]) if len(row) == 7 else width
    if body > width:
        raise ValueError(f"{where} ({name}): the body width {body} m exceeds the box width {width} m; the label box "
                         f"holds the whole body")
    return Blueprint(name, cls, shape, length, width, height, body)


class VehicleCatalog:
    """What vehicles are drawn from, by the `vehicles` config: CARLA's blueprints (`draw: blueprints`) or classes
    with size spreads (`draw: types`). `names` are what is drawn (blueprint ids or class names), `probs` their
    probabilities, `types[name]` their speed and lane attributes."""

    def __init__(self, cfg: dict):
        self.label_margin = float(cfg.get("label_margin_m", 0.0))
        if self.label_margin < 0:
            raise ValueError("vehicles.label_margin_m must be >= 0 metres")
        self.draw = cfg.get("draw", "types")
        if self.draw not in DRAWS:
            raise ValueError(f"vehicles.draw must be one of {', '.join(DRAWS)}, got {self.draw!r}")
        self.types: dict[str, VehicleType | Blueprint] = {}
        self.classes: dict[str, list[str]] = {}  # blueprints: class -> its blueprint ids
        if self.draw == "blueprints":
            self._init_blueprints(cfg)
        else:
            self._init_types(cfg)

    def _init_types(self, cfg: dict) -> None:
        types = cfg["types"]
        mix = cfg["mix"]
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

    def _init_blueprints(self, cfg: dict) -> None:
        rows = cfg.get("blueprints")
        if not isinstance(rows, (list, tuple)) or not rows:
            raise ValueError("vehicles.blueprints must be a non-empty list of blueprint rows (configs/sim.yaml)")
        for k, row in enumerate(rows):
            bp = _blueprint(row, k)
            if bp.name in self.types:
                raise ValueError(f"vehicles.blueprints: {bp.name} is listed twice")
            self.types[bp.name] = bp
            self.classes.setdefault(bp.cls, []).append(bp.name)
        spawn = cfg.get("spawn_classes")
        if not (isinstance(spawn, (list, tuple)) and spawn and all(isinstance(c, str) for c in spawn)):
            raise ValueError(f"vehicles.spawn_classes must be a non-empty list of classes of vehicles.blueprints "
                             f"({', '.join(self.classes)}), got {spawn!r}")
        unknown = [c for c in spawn if c not in self.classes]
        if unknown:
            raise ValueError(f"vehicles.spawn_classes names class(es) {unknown} that no blueprint has; known: "
                             f"{', '.join(self.classes)}")
        self.names = [n for n, bp in self.types.items() if bp.cls in spawn]
        self.probs = np.full(len(self.names), 1.0 / len(self.names))
        deck = cfg.get("blueprint_deck", True)
        if not isinstance(deck, bool):
            raise ValueError(f"vehicles.blueprint_deck must be true or false, got {deck!r}")
        self.deck_size = len(self.names) if deck else 0  # a deck holds every spawnable blueprint once

    def knows(self, name: str) -> bool:
        """Whether `name` names something a vehicle can be drawn as: a type, a blueprint or a blueprint class."""
        return name in self.types or name in self.classes

    def pick(self, rng: np.random.Generator, name: str) -> str:
        """The type or blueprint `name` names: itself, or for a class of blueprints one of its blueprints, uniformly
        (no draw otherwise)."""
        if name in self.types:
            return name
        if name in self.classes:
            ids = self.classes[name]
            return ids[int(rng.integers(len(ids)))]
        raise ValueError(f"{name!r} is neither a vehicle type, a blueprint nor a blueprint class; known: "
                         f"{', '.join([*self.classes, *self.types])}")

    def sample_type(self, rng: np.random.Generator) -> str:
        return self.names[int(rng.choice(len(self.names), p=self.probs))]

    def deck(self, rng: np.random.Generator) -> TypeDeck | None:
        """A stratified deck for one scene (None when draws are independent)."""
        return TypeDeck(self.names, self.probs, self.deck_size, rng) if self.deck_size > 0 else None

    def sample(self, rng: np.random.Generator, type_name: str | None = None) -> VehicleShape:
        """One vehicle: its class, label size (metres), parts and reflectivity."""
        t = self.types[type_name or self.sample_type(rng)]
        m = self.label_margin
        if isinstance(t, Blueprint):
            L, W, H = t.length, t.width, t.height  # the label box is the blueprint's box
            parts = build_parts(t.shape, L - 2 * m, min(t.body_width, W - 2 * m), H - m, rng)
            return VehicleShape(t.cls, L, W, H, parts, float(rng.uniform(0.35, 0.95)), t.name)
        L, W, H = _draw(rng, t.length), _draw(rng, t.width), _draw(rng, t.height)
        parts = build_parts(t.shape, L, W, H, rng)
        return VehicleShape(t.name, L + 2 * m, W + 2 * m, H + m, parts, float(rng.uniform(0.35, 0.95)), t.name)


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


__all__ = ["VehicleType", "Blueprint", "VehicleShape", "VehicleCatalog", "DRAWS", "TypeDeck", "build_parts",
           "label_box_local", "SHAPES"]
