"""The road model: a per-frame estimate of the road surface, which labels the points that are road.

Most returns of a highway scan are road (about 90 % of a simulated frame). A detector that voxelises or
samples them spends its budget on nothing, so a model's config may drop them (`road.drop`) before its
input is built; `crop_model_input` is the one preparation of every point cloud a model sees (training
samples, inference, benchmarks): the crop to the model's range, then the road removal.

The fit (`fit_road`), in the frame's own coordinates, with no assumption that the road is z = 0:
1. candidates: the lowest point of each occupied BEV cell (`cell` metres square). A vehicle hides the
   road under it, so a cell it covers offers its body, which the fit then rejects as an outlier.
2. the surface is fitted per x band (`band_length` metres), each band as
   z = a + b x + c y + d y^2: a plane (pitch b, roll c) with a crown term d. RANSAC over the band's
   candidates (and half a band either side, so neighbours agree) picks the hypothesis with the most
   candidates within `inlier` metres, among those whose slope stays under `max_slope_deg` across the
   band; a least-squares fit to every point of the band window within `inlier` of it (twice, the
   second time around the first refit) removes the minimal sample's noise.
3. the bands are blended linearly in x between band centres, so the surface is continuous; a band
   with fewer than `min_points` candidate inliers takes its nearest fitted neighbour's surface
   (the nearer one to the sensor on a tie). No band fitted: no surface, and no point is road.

Why bands of planes and not one surface: a single plane cannot follow a vertical curve over 150 m (a
crest of radius 10 km rises 1.1 m there) and a global polynomial is ruled by the dense near range,
while the far range, where the points are sparse, is where its error grows. A plane over a 40 m window
of such a curve is at most 2 cm off, and a band whose road is hidden (a truck alongside) borrows its
neighbour's surface instead of bending the others. The y^2 term follows a crowned carriageway (a
parabolic crown exactly; a 2 % tent crown over 16 m to within 4 cm). Candidate selection by lowest point
per cell, not by a height window, keeps the fit independent of where the road lies (a tilted road is
metres above or below z = 0 at 100 m).

Deterministic: the RANSAC samples come from a generator seeded by the points' bytes (CRC-32) and the
caller's seed; there is no global state. Units: metres; the only angle is `max_slope_deg` (config edge).
Config: the `road` section of configs/default.yaml (each model's YAML sets its own `drop`).
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numba import njit

from detbench.config import ConfigError, section_with_defaults, shipped_defaults
from detbench.data.augment import crop_to_range

__all__ = ["ROAD_DEFAULTS", "RoadConfig", "RoadFit", "crop_model_input", "fit_road", "road_mask"]

ROAD_DEFAULTS: dict[str, Any] = shipped_defaults("road")  # configs/default.yaml `road:`


@dataclass(frozen=True)
class RoadConfig:
    """The road model's settings (metres; `max_slope_deg` in degrees). Built by `from_dict` from the
    `road` section of a run config; `off()` drops nothing."""

    drop: bool
    margin: float
    cell: float
    band_length: float
    inlier: float
    iterations: int
    smoothness: float
    min_points: int
    max_slope_deg: float

    @classmethod
    def from_dict(cls, d: Mapping | None, where: str = "road") -> RoadConfig:
        """From a `road` section (None = the shipped defaults); unknown keys and out-of-range values are
        ConfigErrors naming `where`."""
        v = section_with_defaults(d, ROAD_DEFAULTS, where)
        for key in ("margin", "cell", "band_length", "inlier", "max_slope_deg"):
            if not (math.isfinite(float(v[key])) and float(v[key]) > 0):
                raise ConfigError(f"{where}.{key} must be a positive number of "
                                  f"{'degrees' if key.endswith('_deg') else 'metres'}, got {v[key]!r}")
        if not float(v["max_slope_deg"]) < 90:
            raise ConfigError(f"{where}.max_slope_deg must be below 90 degrees, got {v['max_slope_deg']!r}")
        if not (math.isfinite(float(v["smoothness"])) and float(v["smoothness"]) >= 0):
            raise ConfigError(f"{where}.smoothness must be a number >= 0 (points' worth of weight), "
                              f"got {v['smoothness']!r}")
        if int(v["iterations"]) < 1:
            raise ConfigError(f"{where}.iterations must be at least 1, got {v['iterations']!r}")
        if int(v["min_points"]) < 4:
            raise ConfigError(f"{where}.min_points must be at least 4 (a band's surface has 4 terms), "
                              f"got {v['min_points']!r}")
        return cls(drop=bool(v["drop"]), margin=float(v["margin"]), cell=float(v["cell"]),
                   band_length=float(v["band_length"]), inlier=float(v["inlier"]),
                   iterations=int(v["iterations"]), smoothness=float(v["smoothness"]),
                   min_points=int(v["min_points"]),
                   max_slope_deg=float(v["max_slope_deg"]))

    @classmethod
    def of_run_config(cls, cfg: Mapping) -> RoadConfig:
        """The road settings of a run config (a checkpoint's `config`). A config without a `road` section
        drops nothing: its model saw every point."""
        section = cfg.get("road")
        if section is None:
            return cls.off()
        return cls.from_dict(section)

    @classmethod
    def off(cls) -> RoadConfig:
        """The shipped settings with `drop` false."""
        return cls.from_dict({"drop": False})


@dataclass(frozen=True)
class RoadFit:
    """A fitted road surface: per x band, z = a + b x + c y + d y^2, blended linearly between band centres.

    edges: (B + 1,) band edges in x (metres). coefs: (B, 4) [a, b, c, d] per band (a band that borrowed
    its neighbour's surface holds that surface). own: (B,) True where the band has its own fit.
    inliers: (B,) candidate inliers of each band's own fit (0 where none). An empty fit (B = 0 or no
    band with its own fit) has no surface: `ok` is false and every height is +inf.
    """

    edges: np.ndarray
    coefs: np.ndarray
    own: np.ndarray
    inliers: np.ndarray

    @property
    def ok(self) -> bool:
        return bool(self.own.any())

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The surface's z (metres) at (x, y); +inf everywhere when there is no surface."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        if not self.ok:
            return np.full(np.broadcast(x, y).shape, np.inf)
        shape = np.broadcast(x, y).shape
        x, y = (np.ascontiguousarray(np.broadcast_to(v, shape)).reshape(-1) for v in (x, y))
        return _surface_kernel(x, y, float(self.edges[0]), float(self.edges[1] - self.edges[0]),
                               np.ascontiguousarray(self.coefs)).reshape(shape)


@njit(cache=True)
def _surface_kernel(x: np.ndarray, y: np.ndarray, x0: float, band: float, coefs: np.ndarray) -> np.ndarray:
    """The band surfaces blended linearly between the band centres (beyond the outer centres, the outer
    band's own surface): bands of length `band` from `x0`."""
    nb = coefs.shape[0]
    out = np.empty(len(x))
    for i in range(len(x)):
        t = (x[i] - x0) / band - 0.5  # 0 at the first band's centre
        if t < 0.0:
            t = 0.0
        if t > nb - 1:
            t = nb - 1.0
        lo = min(int(t), max(nb - 2, 0))
        hi = min(lo + 1, nb - 1)
        w = t - lo
        yy = y[i]
        z_lo = coefs[lo, 0] + coefs[lo, 1] * x[i] + coefs[lo, 2] * yy + coefs[lo, 3] * yy * yy
        z_hi = coefs[hi, 0] + coefs[hi, 1] * x[i] + coefs[hi, 2] * yy + coefs[hi, 3] * yy * yy
        out[i] = (1.0 - w) * z_lo + w * z_hi
    return out


@njit(cache=True)
def _normal_sums(x, y, z, lo, hi, xc, h, half_width, theta, inlier):
    """Normal equations (F^T F, F^T z, count) of the points with lo <= x < hi within `inlier` of the
    normalised surface `theta`, F the `_features` rows."""
    lhs = np.zeros((4, 4))
    rhs = np.zeros(4)
    n = 0
    f = np.empty(4)
    for i in range(len(x)):
        if x[i] < lo or x[i] >= hi:
            continue
        v = y[i] / half_width
        f[0] = 1.0
        f[1] = (x[i] - xc) / h
        f[2] = v
        f[3] = v * v
        r = theta[0] + theta[1] * f[1] + theta[2] * f[2] + theta[3] * f[3] - z[i]
        if abs(r) >= inlier:
            continue
        n += 1
        for a in range(4):
            rhs[a] += f[a] * z[i]
            for b in range(4):
                lhs[a, b] += f[a] * f[b]
    return lhs, rhs, n


@njit(cache=True)
def _lowest_kernel(x: np.ndarray, y: np.ndarray, z: np.ndarray, cell: float) -> np.ndarray:
    x0, y0 = np.floor(x.min() / cell), np.floor(y.min() / cell)
    nx = int(np.floor(x.max() / cell) - x0) + 1
    ny = int(np.floor(y.max() / cell) - y0) + 1
    best = np.full(nx * ny, -1, np.int64)
    for i in range(len(z)):
        k = int(np.floor(x[i] / cell) - x0) * ny + int(np.floor(y[i] / cell) - y0)
        j = best[k]
        if j < 0 or z[i] < z[j]:
            best[k] = i
    return best[best >= 0]


def _lowest_per_cell(x: np.ndarray, y: np.ndarray, z: np.ndarray, cell: float) -> np.ndarray:
    """Index of the lowest point of each occupied BEV cell (the first of equals), in cell order."""
    cells = (math.floor(x.max() / cell) - math.floor(x.min() / cell) + 1) * (
        math.floor(y.max() / cell) - math.floor(y.min() / cell) + 1)
    if cells > 4 * len(x) + 65536:  # a sparse cloud over a wide area: sort instead of a dense grid
        ij = np.floor(np.stack([x, y], axis=1) / cell).astype(np.int64)
        ij -= ij.min(axis=0)
        key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
        order = np.lexsort((z, key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        return order[first]
    return _lowest_kernel(x, y, z, cell)


_HALF_WIDTH = 16.0  # m: the lateral scale of roll and crown in the smoothness term (half a highway's width)


def _features(x: np.ndarray, y: np.ndarray, xc: float, h: float) -> np.ndarray:
    """Normalised terms of the band surface: 1, (x - xc) / h, y / W, (y / W)^2 (each about 1 at the window's
    edges, so the smoothness weight means the same for each)."""
    v = y / _HALF_WIDTH
    return np.stack([np.ones_like(x), (x - xc) / h, v, v * v], axis=-1)


def _absolute(theta: np.ndarray, xc: float, h: float) -> np.ndarray:
    """Normalised band coefficients as coefficients of (1, x, y, y^2) in metres."""
    a, b, c, d = theta
    b, c, d = b / h, c / _HALF_WIDTH, d / _HALF_WIDTH ** 2
    return np.array([a - b * xc, b, c, d])


def _normalised(coef: np.ndarray, xc: float, h: float) -> np.ndarray:
    a, b, c, d = coef
    return np.array([a + b * xc, b * h, c * _HALF_WIDTH, d * _HALF_WIDTH ** 2])


def _fit_band(cand: np.ndarray, pts: tuple[np.ndarray, np.ndarray, np.ndarray], xc: float, h: float,
              prior: np.ndarray, cfg: RoadConfig,
              rng: np.random.Generator) -> tuple[np.ndarray | None, int]:
    """One band window's surface (the window: x within xc +- h; `pts` the frame's x, y, z), normalised
    ([a, b, c, d] of `_features`) with its candidate inliers, or (None, 0) when it has too few. `prior`: the
    normalised slopes (b, c, d) it is held to.

    RANSAC hypotheses are planes through 3 candidates with the prior's crown; the refinement is least
    squares on the points within `cfg.inlier` of the best, plus `cfg.smoothness` points' worth of weight
    on (b, c, d) = prior, which fixes what the points leave free (the slope of a band whose road is a
    single scan ring)."""
    m = len(cand)
    if m < cfg.min_points:
        return None, 0
    fc = _features(cand[:, 0], cand[:, 1], xc, h)
    zc = cand[:, 2] - fc[:, 3] * prior[2]  # the prior's crown taken out: hypotheses are planes
    idx = rng.integers(0, m, size=(cfg.iterations, 3))  # (T, 3); a repeated index makes a singular sample
    a_mat = fc[idx][..., :3]
    good = np.abs(np.linalg.det(a_mat)) > 1e-6
    if not good.any():
        return None, 0
    hyp = np.linalg.solve(a_mat[good], zc[idx[good]][..., None])[..., 0]  # (T', 3) normalised a, b, c
    # the slope anywhere in the window: pitch |b|, roll |c + 2 d v| at the window's widest |v|
    vmax = float(np.abs(fc[:, 2]).max())
    max_rise = math.tan(math.radians(cfg.max_slope_deg))
    pitch = np.abs(hyp[:, 1]) / h
    roll = (np.abs(hyp[:, 2]) + 2 * abs(prior[2]) * vmax) / _HALF_WIDTH
    hyp = hyp[(pitch <= max_rise) & (roll <= max_rise)]
    if len(hyp) == 0:
        return None, 0
    counts = (np.abs(fc[:, :3] @ hyp.T - zc[:, None]) < cfg.inlier).sum(axis=0)
    if int(counts.max()) < cfg.min_points:
        return None, 0
    theta = np.array([*hyp[int(np.argmax(counts))], prior[2]])
    reg = np.diag([0.0, cfg.smoothness, cfg.smoothness, cfg.smoothness])  # normal equations of the smoothness rows
    for _ in range(2):
        lhs, rhs, n = _normal_sums(pts[0], pts[1], pts[2], xc - h, xc + h, xc, h, _HALF_WIDTH, theta, cfg.inlier)
        lhs += reg
        if n < 4 or abs(np.linalg.det(lhs)) < 1e-12:
            break
        theta = np.linalg.solve(lhs, rhs + reg @ np.concatenate([[0.0], prior]))
    n_in = int((np.abs(fc @ theta - cand[:, 2]) < cfg.inlier).sum())
    if n_in < cfg.min_points:
        return None, 0
    return theta, n_in


def _frame_seed(xyz: np.ndarray, seed: int) -> int:
    return zlib.crc32(np.ascontiguousarray(xyz, dtype=np.float32).tobytes()) ^ (int(seed) & 0xFFFFFFFF)


def fit_road(points: np.ndarray, cfg: RoadConfig, seed: int = 0) -> RoadFit:
    """The road surface of one frame's points ((N, >=3) x, y, z metres, any frame whose z is up); see the
    module doc. Deterministic for the same points, config and `seed`."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3] if len(points) else np.zeros((0, 3))
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    empty = RoadFit(np.zeros(1), np.zeros((0, 4)), np.zeros(0, bool), np.zeros(0, np.int64))
    if len(xyz) < cfg.min_points:
        return empty
    rng = np.random.default_rng(_frame_seed(xyz, seed))
    cols = tuple(np.ascontiguousarray(xyz[:, k]) for k in range(3))
    cand = xyz[_lowest_per_cell(*cols, cfg.cell)]
    bl = cfg.band_length
    first = math.floor(float(xyz[:, 0].min()) / bl)
    last = math.floor(float(xyz[:, 0].max()) / bl)
    edges = np.arange(first, last + 2, dtype=np.float64) * bl
    centres = 0.5 * (edges[:-1] + edges[1:])
    nb = len(centres)
    coefs = np.zeros((nb, 4))
    own = np.zeros(nb, bool)
    inliers = np.zeros(nb, np.int64)
    h = bl  # the window is the band and half a band either side: x - xc within +-h
    # bands from the sensor outwards, each held to the slopes of the nearest band fitted before it
    for b in np.argsort(np.abs(centres), kind="stable"):
        xc = centres[b]
        lo, hi = xc - h, xc + h
        c = cand[(cand[:, 0] >= lo) & (cand[:, 0] < hi)]
        done = np.flatnonzero(own)
        ref = coefs[done[np.argmin(np.abs(done - b))]] if len(done) else np.zeros(4)
        theta, n_in = _fit_band(c, cols, xc, h, _normalised(ref, xc, h)[1:], cfg, rng)
        if theta is not None:
            coefs[b], own[b], inliers[b] = _absolute(theta, xc, h), True, n_in
    if not own.any():
        return RoadFit(edges, coefs, own, inliers)
    fitted = np.flatnonzero(own)
    for b in np.flatnonzero(~own):  # the nearest band with its own fit; the nearer to the sensor on a tie
        coefs[b] = coefs[fitted[np.argmin(np.abs(fitted - b) * 2 + (np.abs(centres[fitted]) > abs(centres[b])))]]
    return RoadFit(edges, coefs, own, inliers)


def road_mask(points: np.ndarray, cfg: RoadConfig, seed: int = 0, fit: RoadFit | None = None
              ) -> tuple[np.ndarray, RoadFit]:
    """((N,) bool, True where a point is road: less than `cfg.margin` metres above the fitted surface;
    the fit). `fit` reuses a surface already fitted. No surface: no point is road."""
    points = np.asarray(points)
    if fit is None:
        fit = fit_road(points, cfg, seed)
    if not fit.ok or len(points) == 0:
        return np.zeros(len(points), bool), fit
    xyz = points[:, :3].astype(np.float64)
    above = xyz[:, 2] - fit.height(xyz[:, 0], xyz[:, 1])
    return above < cfg.margin, fit


def crop_model_input(points: np.ndarray, boxes: np.ndarray, point_cloud_range: Sequence[float],
                     road: RoadConfig | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A model's input points: cropped to its range (`detbench.data.augment.crop_to_range`), then, when
    `road.drop`, without the road points (fitted on the cropped points). Returns (points (N', C),
    boxes (M', 7), keep (M,) bool mask of the kept boxes); boxes are cropped, never dropped for the road."""
    points, boxes, keep = crop_to_range(points, boxes, point_cloud_range)
    if road is not None and road.drop and len(points):
        is_road, _ = road_mask(points, road)
        points = points[~is_road]
    return points, boxes, keep
