"""LiDAR models: mounting, field of view, scan grid, noise, drop-off, intensity; presets.

A `LidarConfig` describes one sensor. Its scan is a regular grid of `channels` elevations
(inclusive of both vertical FOV limits, like CARLA's ray-cast LiDAR) by `h_samples`
azimuths (cell centres across the horizontal FOV, centred on +x). Directions are defined
in the sensor frame and turned into the ego ground frame by the pitch: a positive
`pitch_deg` rotates the sensor about +y, i.e. tilts it down, so the world direction of a
sensor-frame ray d is R_y(pitch) d and a point's ground-frame z is its (pitch-undone)
sensor-frame z plus the mounting height.

Post-processing per return (all optional, all deterministic per seed):
- `range_noise_m`: Gaussian noise of that standard deviation added to the range (the
  point moves along its ray);
- `dropout`: probability that any return is lost (random drop-off);
- `dropoff_intensity_limit`, `dropoff_zero_intensity`: intensity-driven drop-off, the drop
  probability grows linearly from 0 at `limit` to `zero_intensity` at intensity 0;
- intensity = reflectivity * exp(-attenuation * range) * (1 - incidence_weight * (1 - |cos i|)),
  clipped to [0, 1], with i the angle between the ray and the surface normal.

Presets: the paper's Table II ("h3-1.8", "h3-1.0", "h3-0.5") and the commercial LiDARs of
Table I ("ideal-l8", "aito-m5", "xpeng-g9", "neta-s", "arcfox-as-hi", "avatr-3"; the full
model names work too). Table I gives FOV 120 x 25 deg and the angular resolution
horizontal x vertical, which become h_samples = 120 / h_res and channels = 25 / v_res
(rounded). Forehead units (>= 1.5 m) are pitched down 2.5 deg like the paper's 1.8 m
sensor ("to align with mainstream configurations"); lower units look level.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from detbench.data.frame import Sensor, height_key

PAPER_HEIGHTS = (0.5, 1.0, 1.8)


@dataclass(frozen=True)
class LidarConfig:
    """One LiDAR. Lengths in metres, angles in degrees (`*_deg`), probabilities in [0, 1]."""

    height: float
    pitch_deg: float = 0.0
    vfov_deg: tuple[float, float] = (-12.5, 12.5)
    hfov_deg: float = 180.0
    channels: int = 128
    h_samples: int = 480
    max_range: float = 150.0
    name: str = ""
    range_noise_m: float = 0.0
    dropout: float = 0.0
    dropoff_intensity_limit: float = 0.0
    dropoff_zero_intensity: float = 0.0
    attenuation_per_m: float = 0.004
    incidence_weight: float = 0.5

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.vfov_deg)
        object.__setattr__(self, "vfov_deg", (lo, hi))
        problems = []
        if not (math.isfinite(self.height) and self.height > 0):
            problems.append(f"height must be > 0 m (got {self.height})")
        if not (-90.0 < lo < hi < 90.0):
            problems.append(f"vfov_deg must be (lower, upper) with -90 < lower < upper < 90 (got {self.vfov_deg})")
        if not (0.0 < self.hfov_deg <= 360.0):
            problems.append(f"hfov_deg must be in (0, 360] (got {self.hfov_deg})")
        if not (-90.0 < self.pitch_deg < 90.0):
            problems.append(f"pitch_deg must be in (-90, 90) (got {self.pitch_deg})")
        if int(self.channels) != self.channels or self.channels < 1:
            problems.append(f"channels must be a positive integer (got {self.channels})")
        if int(self.h_samples) != self.h_samples or self.h_samples < 1:
            problems.append(f"h_samples must be a positive integer (got {self.h_samples})")
        if not (self.max_range > 0):
            problems.append(f"max_range must be > 0 m (got {self.max_range})")
        if not (self.range_noise_m >= 0):
            problems.append(f"range_noise_m must be >= 0 (got {self.range_noise_m})")
        for k in ("dropout", "dropoff_intensity_limit", "dropoff_zero_intensity", "incidence_weight"):
            v = getattr(self, k)
            if not (0.0 <= v <= 1.0):
                problems.append(f"{k} must be in [0, 1] (got {v})")
        if not (self.attenuation_per_m >= 0):
            problems.append(f"attenuation_per_m must be >= 0 (got {self.attenuation_per_m})")
        if problems:
            raise ValueError(f"LidarConfig {self.name or ''}: " + "; ".join(problems))
        object.__setattr__(self, "channels", int(self.channels))
        object.__setattr__(self, "h_samples", int(self.h_samples))

    # ------------------------------------------------------------------ derived
    @property
    def sensor(self) -> Sensor:
        """The `Sensor` record stored with every frame of this LiDAR."""
        return Sensor(height=float(self.height), pitch_deg=float(self.pitch_deg),
                      vfov_deg=self.vfov_deg, hfov_deg=float(self.hfov_deg),
                      channels=self.channels, h_samples=self.h_samples,
                      max_range=float(self.max_range), name=self.name)

    @property
    def num_rays(self) -> int:
        return self.channels * self.h_samples

    def replace(self, **changes) -> LidarConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["vfov_deg"] = list(self.vfov_deg)
        return d

    def key(self) -> int:
        """A stable 32-bit id of every field (seeds this LiDAR's noise; same LiDAR, same noise)."""
        return zlib.crc32(json.dumps(self.to_dict(), sort_keys=True).encode("utf-8"))

    def elevations(self) -> np.ndarray:
        """(channels,) sensor-frame elevations in radians, lower to upper, both limits included."""
        lo, hi = (math.radians(v) for v in self.vfov_deg)
        if self.channels == 1:
            return np.array([(lo + hi) / 2.0])
        return np.linspace(lo, hi, self.channels)

    def azimuths(self) -> np.ndarray:
        """(h_samples,) sensor-frame azimuths in radians (cell centres, counter-clockwise from +x)."""
        half = math.radians(self.hfov_deg) / 2.0
        step = 2.0 * half / self.h_samples
        return -half + (np.arange(self.h_samples) + 0.5) * step

    def ray_directions(self) -> np.ndarray:
        """(channels, h_samples, 3) unit ray directions in the ego ground frame (pitch applied).

        Ray r = channel * h_samples + column; row 0 is the lowest channel.
        """
        return _ray_directions(self.vfov_deg, self.channels, self.hfov_deg, self.h_samples, self.pitch_deg).copy()


@lru_cache(maxsize=64)
def _ray_directions(vfov, channels, hfov, h_samples, pitch_deg) -> np.ndarray:
    cfg = LidarConfig(height=1.0, vfov_deg=vfov, channels=channels, hfov_deg=hfov, h_samples=h_samples)
    el = cfg.elevations()[:, None]
    az = cfg.azimuths()[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)
    p = math.radians(pitch_deg)
    c, s = math.cos(p), math.sin(p)
    out = np.empty_like(d)
    out[..., 0] = c * d[..., 0] + s * d[..., 2]
    out[..., 1] = d[..., 1]
    out[..., 2] = -s * d[..., 0] + c * d[..., 2]
    out.setflags(write=False)
    return out


# ---------------------------------------------------------------------- presets
def _table2(height: float, pitch: float, vfov: tuple[float, float]) -> LidarConfig:
    return LidarConfig(height=height, pitch_deg=pitch, vfov_deg=vfov, hfov_deg=180.0, channels=128,
                       h_samples=480, max_range=150.0, name=f"h3-{height:.1f}")


def _table1(name: str, rng: float, h_res: float, v_res: float, height: float) -> LidarConfig:
    return LidarConfig(height=height, pitch_deg=2.5 if height >= 1.5 else 0.0, vfov_deg=(-12.5, 12.5),
                       hfov_deg=120.0, channels=int(round(25.0 / v_res)), h_samples=int(round(120.0 / h_res)),
                       max_range=rng, name=name)


PRESETS: dict[str, LidarConfig] = {
    # Table II of the paper
    "h3-1.8": _table2(1.8, 2.5, (-12.5, 12.5)),
    "h3-1.0": _table2(1.0, 0.0, (-12.5, 12.5)),
    "h3-0.5": _table2(0.5, 0.0, (-12.5, 12.5)),
    # Table I of the paper: FOV 120 x 25 deg, range, resolution h x v (deg), height
    "ideal-l8": _table1("ideal-l8", 200.0, 0.1, 0.2, 1.8),
    "aito-m5": _table1("aito-m5", 150.0, 0.25, 0.26, 1.6),
    "xpeng-g9": _table1("xpeng-g9", 150.0, 0.2, 0.2, 0.6),
    "neta-s": _table1("neta-s", 150.0, 0.25, 0.26, 0.5),
    "arcfox-as-hi": _table1("arcfox-as-hi", 150.0, 0.2, 0.2, 0.4),
    "avatr-3": _table1("avatr-3", 150.0, 0.25, 0.26, 0.4),
}
_ALIASES = {
    "leadingideall8": "ideal-l8", "ideall8": "ideal-l8", "aitom5": "aito-m5", "xpengg9": "xpeng-g9",
    "netas": "neta-s", "arcfoxashi": "arcfox-as-hi", "arcfoxαshi": "arcfox-as-hi", "avatr3": "avatr-3",
}


def _slug(name: str) -> str:
    return re.sub(r"[^0-9a-zα]", "", name.lower())


def lidar_preset(name_or_height: str | float, **changes) -> LidarConfig:
    """A LiDAR preset by name or by mounting height (metres).

    Names: "h3-1.8", "h3-1.0", "h3-0.5" (the paper's Table II) and the Table I models
    (see `PRESETS`; spelling and case are forgiven, e.g. "Leading Ideal L8").
    A number (or a numeric string) is a height: the paper's own heights 0.5, 1.0 and 1.8 m
    give exactly their Table II sensors (so 1.8 is +-12.5 deg in the sensor, pitched down
    2.5 deg: -15..10 deg to the road); any other height takes the paper's 1.0 m specification
    (level, -12.5..12.5 deg, 180 deg, 128 x 480, 150 m) at that height, named "h3-<height>".
    `changes` override fields, e.g. `lidar_preset(1.8, range_noise_m=0.02)`.
    """
    if isinstance(name_or_height, str):
        key = name_or_height.strip().lower()
        try:
            as_height = float(key)
        except ValueError:
            as_height = None
        if as_height is not None:
            return lidar_preset(as_height, **changes)
        if key not in PRESETS:
            key = _ALIASES.get(_slug(key), key)
        if key not in PRESETS:
            raise ValueError(f"unknown LiDAR preset {name_or_height!r}; known: {', '.join(PRESETS)} "
                             f"or a mounting height in metres")
        return PRESETS[key].replace(**changes) if changes else PRESETS[key]
    h = float(name_or_height)
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"a LiDAR height must be a positive number of metres, got {name_or_height!r}")
    for ph in PAPER_HEIGHTS:
        if abs(h - ph) < 1e-9:
            base = PRESETS[f"h3-{ph:.1f}"]
            return base.replace(**changes) if changes else base
    return PRESETS["h3-1.0"].replace(height=h, name=f"h3-{height_key(h)}", **changes)


__all__ = ["LidarConfig", "PRESETS", "PAPER_HEIGHTS", "lidar_preset"]
