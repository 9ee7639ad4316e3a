"""LiDAR rigs: sensors at mounting poses on the ego, the ego's own body, and the rig file (configs/rigs.yaml).

Ego frame (the reference point of every pose and every range): x forward, y left, z up, metres, origin on
the road under the centre of the ego's front bumper, which is where the single-sensor studies put their
LiDAR. A sensor's pose is x, y, z (its optical centre) and yaw, pitch, roll in degrees: yaw turns it
counter-clockwise about +z, a positive pitch tilts it down (as `LidarConfig.pitch_deg`), a positive roll
lifts its left side; the ray directions are R_z(yaw) R_y(pitch) R_x(roll) applied to the sensor-frame rays.

A rig is a named list of sensors whose returns merge into one cloud in the ego frame with a per-point
sensor index. With `ego_body: true` the ego is the rig file's `body` (a sedan of a hood, a body and a
cabin box, front bumper at x = 0): its parts occlude rays and return points, and the self-filter
(`self_filter: true`, the default) drops those returns and counts them. Without the body the ego is the
single-sensor studies' idealised box behind the reference point, which blocks the rays of sensors in
front of it and returns nothing; a sensor mounted within that box ignores it (an idealised mount).

Rig file keys (unknown keys are refused, naming the file and the key):
  body: {length_m, width_m, clearance_m, hood_length_m, hood_height_m, belt_height_m,
         cabin_front_m, cabin_rear_m, cabin_width_m, roof_height_m}
  rigs: {NAME: {ego_body, self_filter, sensors: [{name, preset, x, y, z, yaw_deg, pitch_deg, roll_deg,
         and any LidarConfig field: hfov_deg, vfov_deg, channels, h_samples, max_range, ...}]}}
A sensor's `preset` is a `lidar_preset` name or height; `z` replaces its height and `pitch_deg` its pitch.
"""
from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detbench.config import CONFIG_DIR, ConfigError, load_config
from detbench.sim.lidar import LidarConfig, lidar_preset

RIGS_CONFIG = CONFIG_DIR / "rigs.yaml"
MOUNT_CLEARANCE_M = 0.01  # a sensor closer than this to a body part counts as inside it
_POSE_KEYS = ("x", "y", "z", "yaw_deg", "pitch_deg", "roll_deg")
_LIDAR_KEYS = tuple(f.name for f in dataclasses.fields(LidarConfig) if f.name not in ("height", "pitch_deg", "name"))
_SENSOR_KEYS = ("name", "preset", *_POSE_KEYS, *_LIDAR_KEYS)
_RIG_KEYS = ("ego_body", "self_filter", "sensors")
_BODY_KEYS = ("length_m", "width_m", "clearance_m", "hood_length_m", "hood_height_m", "belt_height_m",
              "cabin_front_m", "cabin_rear_m", "cabin_width_m", "roof_height_m")


@dataclass(frozen=True)
class RigSensor:
    """One LiDAR of a rig: its model (height = z, pitch) and the rest of its pose in the ego frame."""

    name: str
    lidar: LidarConfig
    x: float = 0.0
    y: float = 0.0
    yaw_deg: float = 0.0
    roll_deg: float = 0.0

    @property
    def at_reference(self) -> bool:
        """True for a sensor on the reference point's vertical, unyawed and unrolled (the single-sensor pose)."""
        return self.x == 0.0 and self.y == 0.0 and self.yaw_deg == 0.0 and self.roll_deg == 0.0

    @property
    def reach_m(self) -> float:
        """The farthest a ray reaches from the reference point's vertical."""
        return float(self.lidar.max_range) + math.hypot(self.x, self.y)

    def key(self) -> int:
        """A stable 32-bit id of the model and pose (seeds this sensor's noise; two poses, two streams)."""
        if self.at_reference:
            return self.lidar.key()
        pose = f"{self.lidar.key()} {self.x!r} {self.y!r} {self.yaw_deg!r} {self.roll_deg!r}"
        return zlib.crc32(pose.encode("utf-8"))

    def pose_dict(self) -> dict:
        return {"name": self.name, "x": self.x, "y": self.y, "z": float(self.lidar.height), "yaw_deg": self.yaw_deg,
                "pitch_deg": float(self.lidar.pitch_deg), "roll_deg": self.roll_deg}


@dataclass(frozen=True)
class EgoBody:
    """The ego as a sedan of boxes in the ego frame (front bumper at x = 0, metres): a hood from the front to
    `hood_length_m` up to `hood_height_m`, the body behind it up to the belt line, and a narrower cabin from
    `cabin_front_m` to `cabin_rear_m` behind the bumper, from the belt line to the roof."""

    length_m: float
    width_m: float
    clearance_m: float
    hood_length_m: float
    hood_height_m: float
    belt_height_m: float
    cabin_front_m: float
    cabin_rear_m: float
    cabin_width_m: float
    roof_height_m: float

    def parts(self) -> np.ndarray:
        """(3, 6) boxes cx, cy, cz, hx, hy, hz in the ego frame: hood, body, cabin."""
        def box(x0, x1, y_half, z0, z1):
            return [(x0 + x1) / 2, 0.0, (z0 + z1) / 2, (x1 - x0) / 2, y_half, (z1 - z0) / 2]

        w = self.width_m / 2
        return np.array([box(-self.hood_length_m, 0.0, w, self.clearance_m, self.hood_height_m),
                         box(-self.length_m, -self.hood_length_m, w, self.clearance_m, self.belt_height_m),
                         box(-self.cabin_rear_m, -self.cabin_front_m, self.cabin_width_m / 2, self.belt_height_m,
                             self.roof_height_m)], dtype=np.float64)

    def part_containing(self, x: float, y: float, z: float, margin: float = MOUNT_CLEARANCE_M) -> str | None:
        """The name of the part within `margin` metres of whose inside (x, y, z) lies, or None."""
        for name, p in zip(("hood", "body", "cabin"), self.parts()):
            if all(abs(v - p[i]) < p[i + 3] + margin for i, v in enumerate((x, y, z))):
                return name
        return None


@dataclass(frozen=True)
class Rig:
    """A named list of LiDARs on the ego; see the module doc."""

    name: str
    sensors: tuple[RigSensor, ...]
    ego_body: bool = False
    self_filter: bool = True
    body: EgoBody | None = None

    @property
    def is_single_reference(self) -> bool:
        """One sensor at the reference point without the body: exactly the single-sensor path."""
        return len(self.sensors) == 1 and self.sensors[0].at_reference and not self.ego_body

    @property
    def reach_m(self) -> float:
        return max(s.reach_m for s in self.sensors)

    def describe(self) -> dict:
        """JSON-ready: the rig's sensors (pose and model) and its body settings."""
        return {"name": self.name, "ego_body": self.ego_body, "self_filter": self.self_filter,
                "sensors": [{**s.pose_dict(), "model": s.lidar.sensor.to_dict()} for s in self.sensors],
                "body": dataclasses.asdict(self.body) if (self.ego_body and self.body is not None) else None}


# ---------------------------------------------------------------------------- rig files
def _number(where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}.{key}: must be a number, got {value!r}")
    return float(value)


def _unknown(where: str, given: dict, known: tuple[str, ...]) -> None:
    if not isinstance(given, dict):
        raise ConfigError(f"{where}: must be a mapping, got {type(given).__name__}")
    for k in given:
        if k not in known:
            raise ConfigError(f"{where}.{k}: unknown key; known: {', '.join(known)}")


def _body(path: Path, node) -> EgoBody:
    where = f"{path}: body"
    _unknown(where, node, _BODY_KEYS)
    missing = [k for k in _BODY_KEYS if k not in node]
    if missing:
        raise ConfigError(f"{where}: missing {', '.join(missing)}")
    body = EgoBody(**{k: _number(where, k, node[k]) for k in _BODY_KEYS})
    if not (0 <= body.clearance_m < body.hood_height_m <= body.belt_height_m < body.roof_height_m
            and 0 < body.hood_length_m < body.cabin_front_m < body.cabin_rear_m <= body.length_m
            and 0 < body.cabin_width_m <= body.width_m):
        raise ConfigError(f"{where}: needs clearance < hood height <= belt < roof, hood length < cabin front < "
                          f"cabin rear <= length and cabin width <= width (metres)")
    return body


def _sensor(path: Path, rig: str, i: int, node) -> RigSensor:
    where = f"{path}: rigs.{rig}.sensors[{i}]"
    _unknown(where, node, _SENSOR_KEYS)
    if "preset" not in node:
        raise ConfigError(f"{where}: missing preset (a LiDAR preset name or a height, e.g. h3-1.0)")
    changes = {k: node[k] for k in _LIDAR_KEYS if k in node}
    if "vfov_deg" in changes:
        changes["vfov_deg"] = tuple(changes["vfov_deg"])
    if "z" in node:
        changes["height"] = _number(where, "z", node["z"])
    if "pitch_deg" in node:
        changes["pitch_deg"] = _number(where, "pitch_deg", node["pitch_deg"])
    name = str(node.get("name", f"lidar{i}"))
    try:
        lidar = lidar_preset(node["preset"], **changes)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{where}: {e}") from None
    pose = {k: _number(where, k, node[k]) for k in ("x", "y", "yaw_deg", "roll_deg") if k in node}
    return RigSensor(name=name, lidar=lidar, **pose)


def parse_rigs(data: dict, path: Path) -> dict[str, Rig]:
    """Rigs by name from a rig file's mapping (see the module doc); ConfigError names the file and the key."""
    _unknown(str(path), data, ("body", "rigs"))
    body = _body(path, data["body"]) if "body" in data else None
    rigs = {}
    for name, node in (data.get("rigs") or {}).items():
        where = f"{path}: rigs.{name}"
        _unknown(where, node, _RIG_KEYS)
        sensors = node.get("sensors")
        if not isinstance(sensors, list) or not sensors:
            raise ConfigError(f"{where}.sensors: must be a non-empty list of sensors")
        parsed = tuple(_sensor(path, name, i, s) for i, s in enumerate(sensors))
        names = [s.name for s in parsed]
        if len(set(names)) != len(names):
            raise ConfigError(f"{where}.sensors: sensor names must be distinct, got {names}")
        flags = {}
        for k in ("ego_body", "self_filter"):
            if k in node and not isinstance(node[k], bool):
                raise ConfigError(f"{where}.{k}: must be true or false, got {node[k]!r}")
            flags[k] = node.get(k, k == "self_filter")
        if flags["ego_body"] and body is None:
            raise ConfigError(f"{where}.ego_body: the file has no body: section to take the ego's shape from")
        rig = Rig(str(name), parsed, body=body, **flags)
        if rig.ego_body:
            for s in parsed:
                part = body.part_containing(s.x, s.y, float(s.lidar.height))
                if part is not None:
                    raise ConfigError(f"{where}: sensor {s.name!r} at x={s.x:g}, y={s.y:g}, z={s.lidar.height:g} m "
                                      f"lies inside the ego's {part} (or within {MOUNT_CLEARANCE_M} m of it); "
                                      f"mount it outside the body")
        rigs[str(name)] = rig
    return rigs


def load_rigs(path: str | Path | None = None) -> dict[str, Rig]:
    """The rigs of a rig file (configs/rigs.yaml by default), by name."""
    p = Path(path) if path is not None else RIGS_CONFIG
    if not p.is_file():
        raise ConfigError(f"{p}: no such rig file")
    return parse_rigs(load_config(p), p)


def rig_by_name(name: str, path: str | Path | None = None) -> Rig:
    """One rig of a rig file; ConfigError lists the known names."""
    rigs = load_rigs(path)
    if name not in rigs:
        raise ConfigError(f"{path or RIGS_CONFIG}: unknown rig {name!r}; known: {', '.join(rigs)}")
    return rigs[name]


__all__ = ["RigSensor", "EgoBody", "Rig", "RIGS_CONFIG", "load_rigs", "parse_rigs", "rig_by_name"]
