"""Training-free placement scores of a LiDAR height: how good is a height before any detector is trained?

Two families, both computed from the simulated scenes and the sensor alone (docs/evaluation.md,
"Placement scores", has the definitions with their reasons):

**Evidence scores** (per range r, per height h; from the ray caster's per-box hit counts, so
occlusion by other vehicles is in them). A vehicle v of range r has the importance weight

    w_r(v) = 1 + [v in Top6 of r] + [v in Top3 of r]

(the nearest vehicle of the ego, left and right lanes weighs 3, the second nearest 2, every
other vehicle 1), and n_h(v) points inside its box (bottom raised 0.05 m, the LiDAR-detected
rule). With the saturating evidence q(n) = 1 - exp(-n / n0) (n0 = `EVIDENCE_SCALE_POINTS`,
10 points: a vehicle with n0 points holds 63 % of full evidence), summed over all frames:

- ``evidence``      = sum w q(n) / sum w over the LiDAR-detected vehicles (n >= 1): how well
                      the vehicles a detector is scored on are covered (the paper's recall and
                      AP@R40 count only LiDAR-detected vehicles); the primary score;
- ``evidence_all``  = sum w q(n) / sum w over all vehicles of the range (q(0) = 0): coverage
                      and detection rate together;
- ``points``        = sum w n / sum w over the LiDAR-detected vehicles: the importance-weighted
                      mean number of points per LiDAR-detected vehicle (not saturating: near
                      vehicles with thousands of points dominate it);
- ``ldr_w``         = sum w [n >= 1] / sum w over all vehicles: the importance-weighted LDR.

**S-MIG** (Hu et al., CVPR 2022, "Investigating the Impact of Multi-LiDAR Placement on Object
Detection for Autonomous Driving"): the region of interest is cut into voxels; the
probabilistic occupancy grid (POG) gives each voxel the share p of frames in which it lies in a
vehicle box; a voxel's uncertainty is its binary entropy H(p) (bits). The LiDAR's rays are
traced through the *empty* scene (no vehicles: as Hu et al., the metric ignores occlusion; here
the road surface and the sensor's maximum range stop a ray), and every voxel a ray passes through
is observed. S-MIG = the sum of H(p) over the observed voxels (bits), the information the
LiDAR can gain about where vehicles are; ``smig_fraction`` divides it by the total entropy of
the region's voxels. The POG comes from the same frames at every height, so only the ray
pattern differs between heights.

Everything here is numpy / numba on arrays; the sensor enters S-MIG as its ray directions (the
tool gets them from detbench.sim), so eval does not import sim.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from detbench.data.regions import LEVELS, RANGE_NAMES, RANGES

EVIDENCE_SCALE_POINTS = 10.0  # n0 of q(n) = 1 - exp(-n / n0)
SCORE_NAMES: tuple[str, ...] = ("evidence", "evidence_all", "points", "ldr_w", "smig")
PRIMARY_SCORE = "evidence"
SCORE_UNITS = {"evidence": "fraction in [0, 1]", "evidence_all": "fraction in [0, 1]",
               "points": "points per LiDAR-detected vehicle", "ldr_w": "fraction in [0, 1]",
               "smig": "bits"}
_CELL_INDEX = {(r, lv): i for i, (r, lv) in enumerate((r, lv) for r in RANGE_NAMES for lv in LEVELS)}


# ---------------------------------------------------------------------------- evidence scores
def importance_weights(masks: np.ndarray) -> np.ndarray:
    """(3, M) float64 weights w_r(v) per range (rows follow RANGE_NAMES) from the (9, M) cell masks of
    `detbench.studies.ability.stacked_masks`: 0 outside the range, else 1 + [Top6] + [Top3]."""
    masks = np.asarray(masks, dtype=bool)
    out = np.zeros((len(RANGE_NAMES), masks.shape[1]), np.float64)
    for i, r in enumerate(RANGE_NAMES):
        inside = masks[_CELL_INDEX[(r, "all")]]
        out[i] = inside * (1.0 + masks[_CELL_INDEX[(r, "top6")]] + masks[_CELL_INDEX[(r, "top3")]])
    return out


def evidence(counts: np.ndarray, scale: float = EVIDENCE_SCALE_POINTS) -> np.ndarray:
    """q(n) = 1 - exp(-n / scale) for point counts n >= 0 (0 for no point, -> 1 for many)."""
    if not scale > 0:
        raise ValueError(f"the evidence scale must be a positive number of points, got {scale}")
    return -np.expm1(-np.asarray(counts, dtype=np.float64) / float(scale))


# The per-frame sums behind the evidence scores, rows of `evidence_sums` (each (3,) per range):
SUM_FIELDS: tuple[str, ...] = ("w_all", "w_detected", "wq_detected", "wn_detected")


def evidence_sums(weights: np.ndarray, counts: np.ndarray, scale: float = EVIDENCE_SCALE_POINTS) -> np.ndarray:
    """(4, 3) sums of one frame at one height, rows `SUM_FIELDS`: sum w, sum w over detected vehicles,
    sum w q(n) (q(0) = 0, so the sum over detected vehicles is the sum over all), sum w n over detected
    vehicles. weights (3, M) from `importance_weights`; counts (M,) points per box (0.05 m lift)."""
    counts = np.asarray(counts, dtype=np.float64)
    det = (counts >= 1).astype(np.float64)
    return np.stack([weights.sum(axis=1), weights @ det, weights @ evidence(counts, scale), weights @ (counts * det)])


def scores_from_sums(sums: np.ndarray) -> dict[str, np.ndarray]:
    """The four evidence scores from summed `evidence_sums` (4, ...): {name: array (...)} with NaN where a
    denominator is 0."""
    s = np.asarray(sums, dtype=np.float64)
    w_all, w_det, wq, wn = s[0], s[1], s[2], s[3]

    def ratio(a, b):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(b > 0, a / np.where(b > 0, b, 1.0), np.nan)

    return {"evidence": ratio(wq, w_det), "evidence_all": ratio(wq, w_all), "points": ratio(wn, w_det),
            "ldr_w": ratio(w_det, w_all)}


# ---------------------------------------------------------------------------- S-MIG
@dataclass(frozen=True)
class VoxelGrid:
    """An axis-aligned voxel grid in the ego ground frame (metres): x in [x_min, x_max), y in
    [-y_half, y_half), z in [0, z_max), cubes of `voxel` metres. The default covers the large
    range (0 <= x <= 150, |y| <= 15) up to 4.5 m, above the tallest simulated vehicle (4 m)."""

    x_min: float = 0.0
    x_max: float = RANGES["large"][1]
    y_half: float = RANGES["large"][2]
    z_max: float = 4.5
    voxel: float = 0.5

    def __post_init__(self):
        if not (self.voxel > 0 and self.x_max > self.x_min and self.y_half > 0 and self.z_max > 0):
            raise ValueError(f"VoxelGrid needs voxel > 0, x_max > x_min, y_half > 0 and z_max > 0, got {self}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return (int(math.ceil((self.x_max - self.x_min) / self.voxel - 1e-9)),
                int(math.ceil(2 * self.y_half / self.voxel - 1e-9)),
                int(math.ceil(self.z_max / self.voxel - 1e-9)))

    @property
    def origin(self) -> tuple[float, float, float]:
        return (float(self.x_min), float(-self.y_half), 0.0)

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel centre coordinates along x (nx,), y (ny,), z (nz,), metres."""
        nx, ny, nz = self.shape
        x0, y0, z0 = self.origin
        v = self.voxel
        return x0 + (np.arange(nx) + 0.5) * v, y0 + (np.arange(ny) + 0.5) * v, z0 + (np.arange(nz) + 0.5) * v

    def range_mask(self, range_name: str) -> np.ndarray:
        """(nx, ny, nz) bool: voxels whose centre lies in the range (the paper's borders, inclusive)."""
        x0, x1, ym = RANGES[range_name]
        cx, cy, _ = self.centres()
        m2 = ((cx >= x0) & (cx <= x1))[:, None] & (np.abs(cy) <= ym)[None, :]
        return np.broadcast_to(m2[:, :, None], self.shape).copy()

    def to_dict(self) -> dict:
        return {"x_m": [self.x_min, self.x_max], "abs_y_max_m": self.y_half, "z_m": [0.0, self.z_max],
                "voxel_m": self.voxel, "shape": list(self.shape)}


@njit(cache=True)
def _occupy(boxes, x0, y0, z0, vox, nx, ny, nz, counts, stamp, frame):
    """counts[v] += 1 for every voxel whose centre lies in at least one box of this frame (once per frame)."""
    for m in range(boxes.shape[0]):
        cx, cy, cz = boxes[m, 0], boxes[m, 1], boxes[m, 2]
        hx, hy, hz = 0.5 * boxes[m, 3], 0.5 * boxes[m, 4], 0.5 * boxes[m, 5]
        c, s = math.cos(boxes[m, 6]), math.sin(boxes[m, 6])
        ex = abs(hx * c) + abs(hy * s)
        ey = abs(hx * s) + abs(hy * c)
        i0 = max(int(math.floor((cx - ex - x0) / vox)), 0)
        i1 = min(int(math.floor((cx + ex - x0) / vox)), nx - 1)
        j0 = max(int(math.floor((cy - ey - y0) / vox)), 0)
        j1 = min(int(math.floor((cy + ey - y0) / vox)), ny - 1)
        k0 = max(int(math.floor((cz - hz - z0) / vox)), 0)
        k1 = min(int(math.floor((cz + hz - z0) / vox)), nz - 1)
        for i in range(i0, i1 + 1):
            px = x0 + (i + 0.5) * vox - cx
            for j in range(j0, j1 + 1):
                py = y0 + (j + 0.5) * vox - cy
                lx = c * px + s * py
                ly = -s * px + c * py
                if abs(lx) > hx or abs(ly) > hy:
                    continue
                for k in range(k0, k1 + 1):
                    pz = z0 + (k + 0.5) * vox - cz
                    if abs(pz) <= hz and stamp[i, j, k] != frame:
                        stamp[i, j, k] = frame
                        counts[i, j, k] += 1


class OccupancyGrid:
    """The probabilistic occupancy grid (POG) of vehicles: per voxel, the share of frames in which its
    centre lies inside a vehicle box. Feed one frame's (M, 7) boxes at a time with `add`."""

    def __init__(self, grid: VoxelGrid | None = None):
        self.grid = grid or VoxelGrid()
        self.counts = np.zeros(self.grid.shape, np.int64)
        self._stamp = np.full(self.grid.shape, -1, np.int64)
        self.frames = 0

    def add(self, boxes: np.ndarray) -> None:
        b = np.ascontiguousarray(np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
        x0, y0, z0 = self.grid.origin
        nx, ny, nz = self.grid.shape
        _occupy(b, x0, y0, z0, float(self.grid.voxel), nx, ny, nz, self.counts, self._stamp, self.frames)
        self.frames += 1

    def probabilities(self) -> np.ndarray:
        """(nx, ny, nz) float64 occupancy probabilities (zeros before any frame)."""
        return self.counts / max(self.frames, 1)


def binary_entropy_bits(p: np.ndarray) -> np.ndarray:
    """H(p) = -p log2 p - (1 - p) log2 (1 - p), 0 at p = 0 and p = 1."""
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)
    out = np.zeros_like(p)
    mid = (p > 0) & (p < 1)
    q = p[mid]
    out[mid] = -(q * np.log2(q) + (1 - q) * np.log2(1 - q))
    return out


@njit(cache=True, parallel=True)
def _coverage(dirs, height, max_range, x0, y0, z0, vox, nx, ny, nz, out):
    """Mark (out = 1) every voxel that a ray from (0, 0, height) passes through before it meets the road
    (z = 0), reaches max_range or leaves the grid: Amanatides-Woo traversal, exact per voxel."""
    xb = (x0, x0 + nx * vox)
    yb = (y0, y0 + ny * vox)
    zb = (z0, z0 + nz * vox)
    for r in prange(dirs.shape[0]):
        d0, d1, d2 = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t_end = max_range
        if d2 < 0.0:
            t_end = min(t_end, height / -d2)
        # clip the ray [0, t_end] to the grid box (slabs)
        t_in = 0.0
        t_out = t_end
        o = (0.0, 0.0, height)
        d = (d0, d1, d2)
        ok = True
        for a in range(3):
            lo = xb[0] if a == 0 else (yb[0] if a == 1 else zb[0])
            hi = xb[1] if a == 0 else (yb[1] if a == 1 else zb[1])
            if abs(d[a]) < 1e-15:
                if o[a] < lo or o[a] >= hi:
                    ok = False
            else:
                ta = (lo - o[a]) / d[a]
                tb = (hi - o[a]) / d[a]
                if ta > tb:
                    ta, tb = tb, ta
                t_in = max(t_in, ta)
                t_out = min(t_out, tb)
        if not ok or t_in >= t_out:
            continue
        t = t_in + 1e-9
        px = o[0] + d0 * t
        py = o[1] + d1 * t
        pz = o[2] + d2 * t
        i = min(max(int(math.floor((px - x0) / vox)), 0), nx - 1)
        j = min(max(int(math.floor((py - y0) / vox)), 0), ny - 1)
        k = min(max(int(math.floor((pz - z0) / vox)), 0), nz - 1)
        si = 1 if d0 > 0 else -1
        sj = 1 if d1 > 0 else -1
        sk = 1 if d2 > 0 else -1
        inf = 1e30
        tdx = vox / abs(d0) if abs(d0) > 1e-15 else inf
        tdy = vox / abs(d1) if abs(d1) > 1e-15 else inf
        tdz = vox / abs(d2) if abs(d2) > 1e-15 else inf
        nxt_x = ((x0 + (i + (1 if si > 0 else 0)) * vox) - o[0]) / d0 if abs(d0) > 1e-15 else inf
        nxt_y = ((y0 + (j + (1 if sj > 0 else 0)) * vox) - o[1]) / d1 if abs(d1) > 1e-15 else inf
        nxt_z = ((z0 + (k + (1 if sk > 0 else 0)) * vox) - o[2]) / d2 if abs(d2) > 1e-15 else inf
        while True:
            out[i, j, k] = 1
            if nxt_x <= nxt_y and nxt_x <= nxt_z:
                if nxt_x >= t_out:
                    break
                i += si
                nxt_x += tdx
            elif nxt_y <= nxt_z:
                if nxt_y >= t_out:
                    break
                j += sj
                nxt_y += tdy
            else:
                if nxt_z >= t_out:
                    break
                k += sk
                nxt_z += tdz
            if i < 0 or i >= nx or j < 0 or j >= ny or k < 0 or k >= nz:
                break


def ray_coverage(directions: np.ndarray, height: float, max_range: float, grid: VoxelGrid | None = None) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels of `grid` that at least one ray passes through in the empty scene.

    directions: (R, 3) unit ray directions in the ego ground frame (a LiDAR's `ray_directions()`
    reshaped), the sensor at (0, 0, height) metres; a ray stops at the road surface z = 0 and at
    `max_range` metres along the ray. Vehicles do not stop rays (Hu et al.'s S-MIG is occlusion-free).
    """
    grid = grid or VoxelGrid()
    dirs = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
    if not (math.isfinite(height) and height > 0):
        raise ValueError(f"height must be > 0 m, got {height}")
    out = np.zeros(grid.shape, np.uint8)
    x0, y0, z0 = grid.origin
    nx, ny, nz = grid.shape
    _coverage(dirs, float(height), float(max_range), x0, y0, z0, float(grid.voxel), nx, ny, nz, out)
    return out.astype(bool)


def smig(probabilities: np.ndarray, covered: np.ndarray, region: np.ndarray | None = None) -> dict:
    """S-MIG of one sensor: {"bits": sum of H(p) over the covered voxels of `region`, "total_bits": the
    region's total entropy, "fraction": bits / total_bits (NaN when the total is 0), "covered_voxels"}."""
    h = binary_entropy_bits(probabilities)
    region = np.ones(h.shape, bool) if region is None else np.asarray(region, bool)
    cov = np.asarray(covered, bool) & region
    bits = float(h[cov].sum())
    total = float(h[region].sum())
    return {"bits": bits, "total_bits": total, "fraction": bits / total if total > 0 else float("nan"),
            "covered_voxels": int(cov.sum()), "region_voxels": int(region.sum())}


__all__ = ["EVIDENCE_SCALE_POINTS", "SCORE_NAMES", "PRIMARY_SCORE", "SCORE_UNITS", "SUM_FIELDS", "VoxelGrid",
           "OccupancyGrid", "importance_weights", "evidence", "evidence_sums", "scores_from_sums",
           "binary_entropy_bits", "ray_coverage", "smig"]
