"""The `Frame`: one LiDAR sweep at one mounting height with every vehicle of the scene.

Conventions (docs/architecture.md):
- ego ground frame: right-handed, x forward, y left, z up, metres; origin on the road
  surface directly below the LiDAR, so boxes have the same z whatever the mounting height;
- points: float32 (N, 4) x, y, z, intensity in [0, 1];
- boxes: float32 (M, 7) x, y, z, dx, dy, dz, heading; centre of the box, dx along heading,
  heading counter-clockwise from +x in [-pi, pi);
- lane: int64 (M,) relative to the ego lane: 0 ego lane, +1 left, -1 right, +-2 ... further
  lanes of the ego's carriageway, `LANE_OPPOSITE` for the opposite carriageway and
  `LANE_UNKNOWN` where a dataset gives no lane and none could be derived. Datasets without
  lane ids get lanes from the lateral offset (`lanes_from_lateral`, lanes `DEFAULT_LANE_WIDTH`
  wide).
"""
from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass, field

import numpy as np

LANE_OPPOSITE = 99
LANE_UNKNOWN = -99
DEFAULT_LANE_WIDTH = 3.5  # metres

BOX_DIM = 7
POINT_DIM = 4
RIG_NAME = re.compile(r"[A-Za-z][A-Za-z0-9._-]*")


def height_key(height: float) -> str:
    """Mounting height in metres as the decimal string used in folder names and reports.

    >>> height_key(1.8), height_key(1), height_key(0.25)
    ('1.8', '1.0', '0.25')
    """
    h = float(height)
    if not math.isfinite(h) or h <= 0:
        raise ValueError(f"mounting height must be a positive number of metres, got {height!r}")
    s = f"{h:.3f}".rstrip("0")
    if s == "0.":  # keys are written to the millimetre: a smaller height would be the key 0.0
        raise ValueError(f"mounting height {height!r} m is below 1 mm, the resolution heights are written in; "
                         f"give a height of at least 0.001 m")
    return s + "0" if s.endswith(".") else s


def data_key(value: float | str) -> str:
    """The key a dataset files one sensor set under: a mounting height's `height_key` for a number (or a
    numeric string), a rig's name (docs/rigs.md: a letter, then letters, digits, '.', '_' or '-') otherwise.

    >>> data_key(1.8), data_key("0.50"), data_key("headlights")
    ('1.8', '0.5', 'headlights')
    """
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            if not RIG_NAME.fullmatch(value):
                raise ValueError(f"{value!r} is neither a mounting height in metres nor a rig name (a letter, then "
                                 f"letters, digits, '.', '_' or '-')") from None
            return value
    return height_key(float(value))


def key_value(value: float | str) -> float | str:
    """A height as a float (metres), a rig as its name: the value a run records for its data's sensors."""
    key = data_key(value)
    return key if is_rig_key(key) else float(key)


def key_label(value: float | str) -> str:
    """"1.8 m" for a height, "rig headlights" for a rig: how reports name the sensors a run used."""
    if isinstance(value, str) and is_rig_key(value):
        return f"rig {data_key(value)}"
    return f"{float(value):g} m"


def key_text(value: float | str) -> str:
    """"1.8" (`:g`) for a height, the name for a rig: the short form study keys and stage names use."""
    if isinstance(value, str) and is_rig_key(value):
        return data_key(value)
    return f"{float(value):g}"


def height_or_rig(value: float | str) -> float | str:
    """A report's or a run's height as a key: metres as a float, a rig by its name (unchanged)."""
    return value if isinstance(value, str) and is_rig_key(value) else float(value)


def key_heading(key: str) -> str:
    """A dataset key as a column heading: "1.8 m" for a height's key (as written), the name for a rig."""
    return key if is_rig_key(key) else f"{key} m"


def key_order(value: float | str) -> tuple:
    """Sort key of heights and rigs: the heights by metres, then the rigs by name."""
    key = data_key(value)
    return (1, 0.0, key) if is_rig_key(key) else (0, float(key), "")


def height_or_rig_arg(text: str) -> float | str:
    """argparse type of an option that takes a mounting height in metres or a rig's name: a number as a float (as
    type=float, so the tool's own check names a bad height), anything else as a rig's name."""
    try:
        return float(text)
    except ValueError:
        pass
    try:
        return key_value(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def is_rig_key(key: str) -> bool:
    """True when a dataset key names a rig rather than a mounting height."""
    try:
        float(key)
    except ValueError:
        return True
    return False


def lanes_from_lateral(y: np.ndarray, lane_width: float = DEFAULT_LANE_WIDTH, ego_offset: float = 0.0) -> np.ndarray:
    """(M,) int64 relative lane index from the lateral offsets `y` (M,) in metres, for datasets without lane ids.

    The ego is taken to drive in the middle of its lane (`ego_offset` shifts that centre,
    metres, positive to the left); lane i covers y in [(i - 1/2) w, (i + 1/2) w) about it.
    This is exact on straight roads and an approximation on curves.
    """
    if lane_width <= 0:
        raise ValueError(f"lane_width must be positive, got {lane_width}")
    y = np.asarray(y, dtype=np.float64) - ego_offset
    return np.floor(y / lane_width + 0.5).astype(np.int64)


@dataclass(frozen=True)
class Sensor:
    """The LiDAR that produced a frame (what the data layer needs to know of it)."""

    height: float  # mounting height above the road, metres
    pitch_deg: float = 0.0  # rotation about +y; positive pitches the sensor down
    vfov_deg: tuple[float, float] = (-12.5, 12.5)  # lower, upper elevation in the sensor frame
    hfov_deg: float = 180.0  # centred on +x
    channels: int = 128
    h_samples: int = 480
    max_range: float = 150.0
    name: str = ""

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "height": float(self.height),
            "pitch_deg": float(self.pitch_deg),
            "vfov_deg": [float(self.vfov_deg[0]), float(self.vfov_deg[1])],
            "hfov_deg": float(self.hfov_deg),
            "channels": int(self.channels),
            "h_samples": int(self.h_samples),
            "max_range": float(self.max_range),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Sensor:
        known = {"name", "height", "pitch_deg", "vfov_deg", "hfov_deg", "channels", "h_samples", "max_range"}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown sensor field(s) {sorted(unknown)}; known: {sorted(known)}")
        kw = dict(d)
        if "vfov_deg" in kw:
            lo, hi = kw["vfov_deg"]
            kw["vfov_deg"] = (float(lo), float(hi))
        return cls(**kw)


@dataclass
class Frame:
    """One sweep at one height. Arrays are validated by `check()`; see the module doc for units."""

    frame_id: str
    scene_id: str
    points: np.ndarray  # (N, 4) float32, ego ground frame
    boxes: np.ndarray  # (M, 7) float32, every vehicle of the scene near the ego
    classes: np.ndarray  # (M,) str, vehicle type (car, suv, van, taxi, truck, ...)
    track_ids: np.ndarray  # (M,) int64, stable across the frames of a scene
    lanes: np.ndarray  # (M,) int64, relative lane (see module doc)
    sensor: Sensor
    ego: dict = field(default_factory=dict)  # ego state, e.g. speed_mps, lane_index, s_m
    timestamp: float = 0.0  # seconds since the scene started

    @property
    def height(self) -> float:
        return self.sensor.height

    @property
    def num_boxes(self) -> int:
        return int(self.boxes.shape[0])

    def check(self, where: str = "") -> Frame:
        """Raise ValueError naming `where` (a file or frame id) if any array is malformed."""
        where = where or f"frame {self.frame_id}"
        p, b = self.points, self.boxes
        if not isinstance(p, np.ndarray) or p.ndim != 2 or p.shape[1] != POINT_DIM:
            raise ValueError(f"{where}: points must be an (N, {POINT_DIM}) array, "
                             f"got shape {getattr(p, 'shape', None)}")
        if p.dtype != np.float32:
            raise ValueError(f"{where}: points must be float32, got {p.dtype}")
        if not np.isfinite(p).all():
            bad = int((~np.isfinite(p)).any(axis=1).sum())
            raise ValueError(f"{where}: {bad} point(s) have NaN or inf coordinates; drop them before use")
        if not isinstance(b, np.ndarray) or b.ndim != 2 or b.shape[1] != BOX_DIM:
            raise ValueError(f"{where}: boxes must be an (M, {BOX_DIM}) array, got shape {getattr(b, 'shape', None)}")
        if not np.isfinite(b).all():
            raise ValueError(f"{where}: boxes contain NaN or inf")
        if (b[:, 3:6] < 0).any():
            raise ValueError(f"{where}: boxes have negative sizes (dx, dy, dz must be >= 0)")
        m = b.shape[0]
        for name in ("classes", "track_ids", "lanes"):
            arr = getattr(self, name)
            if len(arr) != m:
                raise ValueError(f"{where}: {name} has {len(arr)} entries for {m} boxes")
        return self

