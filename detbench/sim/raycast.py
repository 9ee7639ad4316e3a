"""Numba ray caster: exact ray/box and ray/ground intersection with azimuth-column culling.

Scene model (`detbench.sim.scene_objects.SceneObjects`, everything in the ego ground frame: x forward, y left, z up,
metres; the LiDAR sits at (0, 0, height)):
- objects: vehicles, occluders (barriers) and the ego; each has a yaw pose (x, y, heading),
  a label box and one or more parts, both axis-aligned boxes in the object's own frame
  (origin on the road under the object's pose, x along its heading);
- the ground: the plane z = 0.

Pipeline for one LiDAR (`cast_lidar`), each stage a numba kernel:
1. prepare: per object, the azimuth interval its footprint covers as seen from the sensor
   (exact: the corners of the footprint rectangle bound it), the smallest horizontal
   distance to it, and bounds of the ray slope (dz / horizontal) that can reach it;
2. cull: a column table (CSR) listing, for each of the `h_samples` scan columns, the
   objects whose azimuth interval overlaps the column's world azimuth span (the span over
   the column's channels, so a pitched sensor is handled exactly), sorted by distance;
3. cast (parallel over rays): ground hit if the ray points down; then the column's
   objects front to back, stopping at the first whose distance exceeds the current hit;
   a slope check, then a slab test on the label box in the object's frame, then slab
   tests on its parts (also axis-aligned in that frame);
4. post (parallel): range noise along the ray, random and intensity drop-off, intensity,
   max range; a hit on the ego gives no point;
5. count (parallel): for every kept point, the vehicle box that contains it with the box
   bottom raised by `bottom_lift` (by default DETECTED_BOTTOM_LIFT, the LiDAR-detected rule of
   detbench.data.regions; the same test as `detbench.ops.points_in_boxes`, run on
   the float32 point and the float32 frame box), from the column's objects only: a point
   lies on its ray, so only objects of its column can contain it.

Randomness comes from a counter-based hash of (key, ray index, stream), so results do not
depend on the number of threads and the same key gives the same bytes.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from detbench.data.regions import DETECTED_BOTTOM_LIFT
from detbench.sim.lidar import LidarConfig
from detbench.sim.scene_objects import KIND_EGO, KIND_VEHICLE, TWO_PI, SceneObjects, wrap_angle

HIT_NONE = -2
HIT_GROUND = -1


@dataclass
class CastResult:
    """Output of `cast_lidar`.

    points: (N, 4) float32 x, y, z, intensity in the ego ground frame (empty when points
      were not requested);
    point_box: (N,) int64 row of `boxes` containing each point (bottom lift applied) or -1;
    counts: (M,) int64 points inside each box with the bottom raised by `bottom_lift`;
    rays_cast: number of rays traced; timings: seconds per stage;
    self_hits: rays whose first hit is the ego (of the rays traced: all of them with points).
    """

    points: np.ndarray
    point_box: np.ndarray
    counts: np.ndarray
    rays_cast: int
    timings: dict = field(default_factory=dict)
    self_hits: int = 0


class _RayTable:
    """Per-LiDAR constants: ray directions and the world azimuth span of each column."""

    def __init__(self, lidar: LidarConfig, roll_deg: float = 0.0):
        d = lidar.ray_directions() if roll_deg == 0.0 else rolled_directions(lidar, roll_deg)  # (C, W, 3)
        C, W, _ = d.shape
        self.dirs = np.ascontiguousarray(d.reshape(C * W, 3))
        az_sensor = lidar.azimuths()
        az_world = np.arctan2(d[..., 1], d[..., 0])  # (C, W)
        delta = wrap_angle(az_world - az_sensor[None, :])
        eps = 1e-7
        self.col_lo = az_sensor + delta.min(axis=0) - eps
        self.col_hi = az_sensor + delta.max(axis=0) + eps
        self.delta_max = float(np.abs(delta).max()) + eps
        self.az0 = float(az_sensor[0])
        self.step = float(az_sensor[1] - az_sensor[0]) if W > 1 else TWO_PI
        self.width = W
        self.num_rays = C * W


_TABLES: dict = {}


def _table(lidar: LidarConfig, roll_deg: float = 0.0) -> _RayTable:
    key = (lidar.vfov_deg, lidar.channels, lidar.hfov_deg, lidar.h_samples, lidar.pitch_deg, roll_deg)
    t = _TABLES.get(key)
    if t is None:
        if len(_TABLES) > 32:
            _TABLES.clear()
        t = _TABLES[key] = _RayTable(lidar, roll_deg)
    return t


def rolled_directions(lidar: LidarConfig, roll_deg: float) -> np.ndarray:
    """(channels, h_samples, 3) ray directions of a LiDAR rolled by `roll_deg` about its +x axis (positive: the
    left side up) before its pitch: world d = R_y(pitch) R_x(roll) d_sensor, in the sensor's yawed ground frame."""
    d = lidar.replace(pitch_deg=0.0).ray_directions()
    r = math.radians(roll_deg)
    c, s = math.cos(r), math.sin(r)
    rolled = np.empty_like(d)
    rolled[..., 0] = d[..., 0]
    rolled[..., 1] = c * d[..., 1] - s * d[..., 2]
    rolled[..., 2] = s * d[..., 1] + c * d[..., 2]
    p = math.radians(lidar.pitch_deg)
    c, s = math.cos(p), math.sin(p)
    out = np.empty_like(d)
    out[..., 0] = c * rolled[..., 0] + s * rolled[..., 2]
    out[..., 1] = rolled[..., 1]
    out[..., 2] = -s * rolled[..., 0] + c * rolled[..., 2]
    return out


# ---------------------------------------------------------------------------- kernels
@njit(cache=True)
def _prepare(pose, label, height, max_range):
    """Per object: azimuth interval [a0, a1] (a1 may exceed pi), d_min, slope bounds."""
    K = pose.shape[0]
    a0 = np.empty(K)
    a1 = np.empty(K)
    dmin = np.empty(K)
    slo = np.empty(K)
    shi = np.empty(K)
    for k in range(K):
        c = math.cos(pose[k, 2])
        s = math.sin(pose[k, 2])
        lcx, lcy = label[k, 0], label[k, 1]
        hx, hy = label[k, 3], label[k, 4]
        # footprint centre in the ego frame
        cx = pose[k, 0] + c * lcx - s * lcy
        cy = pose[k, 1] + s * lcx + c * lcy
        # sensor column (origin) in the label frame
        qx = -(c * cx + s * cy)
        qy = -(-s * cx + c * cy)
        ex = max(abs(qx) - hx, 0.0)
        ey = max(abs(qy) - hy, 0.0)
        dm = math.sqrt(ex * ex + ey * ey)
        dmax = 0.0
        ref = 0.0
        lo = 0.0
        hi = 0.0
        for i in range(4):
            sx = hx if (i & 1) else -hx
            sy = hy if (i & 2) else -hy
            px = cx + c * sx - s * sy
            py = cy + s * sx + c * sy
            r = math.sqrt(px * px + py * py)
            if r > dmax:
                dmax = r
            a = math.atan2(py, px)
            if i == 0:
                ref = a
            else:
                dl = (a - ref + math.pi) % TWO_PI - math.pi
                if dl < lo:
                    lo = dl
                if dl > hi:
                    hi = dl
        if dm <= 0.0:
            a0[k] = -math.pi
            a1[k] = math.pi
        else:
            a0[k] = ref + lo - 1e-6
            a1[k] = ref + hi + 1e-6
        dmin[k] = dm
        zlo = label[k, 2] - label[k, 5] - height
        zhi = label[k, 2] + label[k, 5] - height
        if dm <= 1e-9:
            slo[k] = -np.inf
            shi[k] = np.inf
        else:
            shi[k] = (zhi / dm if zhi > 0.0 else zhi / dmax) + 1e-9
            slo[k] = (zlo / dmax if zlo > 0.0 else zlo / dm) - 1e-9
        if dm > max_range:
            a1[k] = a0[k] - 1.0  # empty: out of range
    return a0, a1, dmin, slo, shi


@njit(cache=True)
def _build_columns(a0, a1, dmin, col_lo, col_hi, az0, step, delta_max, width):
    """CSR table col_start (W + 1,), col_obj (E,) int32 of objects per column, nearest first."""
    K = a0.shape[0]
    order = np.argsort(dmin, kind="mergesort")
    counts = np.zeros(width, dtype=np.int64)
    last = np.full(width, -1, dtype=np.int64)
    tmp_obj = np.empty(3 * K * width + 1, dtype=np.int32)
    tmp_col = np.empty(3 * K * width + 1, dtype=np.int32)
    n = 0
    for oi in range(K):
        k = order[oi]
        if a1[k] < a0[k]:
            continue
        for si in range(3):
            shift = (si - 1) * TWO_PI
            lo = a0[k] + shift
            hi = a1[k] + shift
            j0 = max(int(math.floor((lo - delta_max - az0) / step)) - 1, 0)
            j1 = min(int(math.ceil((hi + delta_max - az0) / step)) + 1, width - 1)
            for j in range(j0, j1 + 1):
                if col_hi[j] >= lo and col_lo[j] <= hi and last[j] != k:
                    last[j] = k
                    tmp_obj[n] = k
                    tmp_col[n] = j
                    counts[j] += 1
                    n += 1
    start = np.zeros(width + 1, dtype=np.int64)
    for j in range(width):
        start[j + 1] = start[j] + counts[j]
    fill = start[:-1].copy()
    col_obj = np.empty(n, dtype=np.int32)
    for i in range(n):
        j = tmp_col[i]
        col_obj[fill[j]] = tmp_obj[i]
        fill[j] += 1
    return start, col_obj


@njit(cache=True)
def _slab(ox, oy, oz, dx, dy, dz, cx, cy, cz, hx, hy, hz):
    """Entry/exit distances of a ray through an axis-aligned box; (t0, t1, axis) with t0 > t1 on a miss."""
    t0 = -np.inf
    t1 = np.inf
    axis = -1
    for ax in range(3):
        if ax == 0:
            o, d, c, h = ox, dx, cx, hx
        elif ax == 1:
            o, d, c, h = oy, dy, cy, hy
        else:
            o, d, c, h = oz, dz, cz, hz
        if abs(d) < 1e-15:
            if abs(o - c) > h:
                return 1.0, -1.0, -1
            continue
        inv = 1.0 / d
        ta = (c - h - o) * inv
        tb = (c + h - o) * inv
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
            axis = ax
        if tb < t1:
            t1 = tb
        if t0 > t1:
            return 1.0, -1.0, -1
    return t0, t1, axis


@njit(cache=True, parallel=True)
def _cast(dirs, width, height, max_range, col_start, col_obj, pose, label, parts, part_start, dmin, slo, shi,
          kind, only_vehicle_cols, nblocks):
    """Nearest hit per ray: t (R,) metres (inf: none), hit (R,) object / HIT_GROUND / HIT_NONE, cos incidence."""
    R = dirs.shape[0]
    t_out = np.full(R, np.inf)
    hit_out = np.full(R, HIT_NONE, dtype=np.int32)
    cos_out = np.zeros(R, dtype=np.float32)
    for b in prange(nblocks):
        c = (b * 37) % nblocks  # scatter the chunks so both threads get low and high channels
        for r in range(c * R // nblocks, (c + 1) * R // nblocks):
            j = r % width
            cs, ce = col_start[j], col_start[j + 1]
            if only_vehicle_cols and ce == cs:
                continue
            dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
            horiz = math.sqrt(dx * dx + dy * dy)
            slope = dz / horiz if horiz > 1e-12 else (np.inf if dz > 0 else -np.inf)
            best = max_range
            hit = HIT_NONE
            cosi = 0.0
            if dz < 0.0:
                tg = height / -dz
                if tg <= best:
                    best = tg
                    hit = HIT_GROUND
                    cosi = -dz
            for e in range(cs, ce):
                k = col_obj[e]
                if dmin[k] > best * horiz:
                    break
                if slope > shi[k] or slope < slo[k]:
                    continue
                c = math.cos(pose[k, 2])
                s = math.sin(pose[k, 2])
                px = -pose[k, 0]
                py = -pose[k, 1]
                ox = c * px + s * py
                oy = -s * px + c * py
                ldx = c * dx + s * dy
                ldy = -s * dx + c * dy
                t0, t1, ax = _slab(ox, oy, height, ldx, ldy, dz, label[k, 0], label[k, 1], label[k, 2],
                                   label[k, 3], label[k, 4], label[k, 5])
                if t0 > t1 or t1 <= 0.0 or t0 >= best:
                    continue
                for p in range(part_start[k], part_start[k + 1]):
                    u0, u1, pax = _slab(ox, oy, height, ldx, ldy, dz, parts[p, 0], parts[p, 1], parts[p, 2],
                                        parts[p, 3], parts[p, 4], parts[p, 5])
                    if u0 <= u1 and u0 > 0.0 and u0 < best:
                        best = u0
                        hit = k
                        cosi = abs(ldx) if pax == 0 else (abs(ldy) if pax == 1 else abs(dz))
            if hit != HIT_NONE:
                t_out[r] = best
                hit_out[r] = hit
                cos_out[r] = cosi
    return t_out, hit_out, cos_out


@njit(cache=True, inline="always")
def _hash(key, r, stream):
    z = key + np.uint64(r) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(stream) * np.uint64(0xD1B54A32D192ED03)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, parallel=True)
def _post(dirs, height, max_range, t_hit, hit, cosi, kind, refl, ground_refl, key, noise, dropout,
          drop_limit, drop_zero, attenuation, incidence_weight, keep_ego, nblocks):
    """Noisy points (R, 4) float32 and a keep flag (R,) per ray; hits on the ego give points only with keep_ego."""
    R = dirs.shape[0]
    pts = np.zeros((R, 4), dtype=np.float32)
    keep = np.zeros(R, dtype=np.bool_)
    for b in prange(nblocks):
        c = (b * 37) % nblocks  # scatter the chunks so both threads get low and high channels
        for r in range(c * R // nblocks, (c + 1) * R // nblocks):
            h = hit[r]
            if h == HIT_NONE:
                continue
            if h >= 0 and kind[h] == KIND_EGO and not keep_ego:
                continue
            t = t_hit[r]
            if dropout > 0.0 and _hash(key, r, 1) < dropout:
                continue
            if noise > 0.0:
                u1 = _hash(key, r, 2)
                u2 = _hash(key, r, 3)
                g = math.sqrt(-2.0 * math.log(max(u1, 1e-300))) * math.cos(TWO_PI * u2)
                t = t + noise * g
            if t <= 0.0 or t > max_range:
                continue
            rf = ground_refl if h < 0 else refl[h]
            inten = rf * math.exp(-attenuation * t) * (1.0 - incidence_weight * (1.0 - cosi[r]))
            inten = min(max(inten, 0.0), 1.0)
            if drop_zero > 0.0 and inten < drop_limit:
                if _hash(key, r, 4) < drop_zero * (1.0 - inten / drop_limit):
                    continue
            pts[r, 0] = t * dirs[r, 0]
            pts[r, 1] = t * dirs[r, 1]
            if h == HIT_GROUND:
                # height + t_hit * dz is 0 up to rounding (it came out at -4e-16 m, below the road): take the
                # offset from the exact hit instead, so a noise-free ground point has z = 0 exactly
                pts[r, 2] = (t - t_hit[r]) * dirs[r, 2] + 0.0  # (+ 0.0: no -0.0)
            else:
                pts[r, 2] = height + t * dirs[r, 2]
            pts[r, 3] = inten
            keep[r] = True
    return pts, keep


@njit(cache=True, parallel=True)
def _count(pts, keep, width, col_start, col_obj, kind, dmin, box_index, table, nblocks):
    """Row of the box table containing each kept point, or -1 (see `count_table`)."""
    R = pts.shape[0]
    out = np.full(R, -1, dtype=np.int64)
    for b in prange(nblocks):
        c = (b * 37) % nblocks
        for r in range(c * R // nblocks, (c + 1) * R // nblocks):
            if not keep[r]:
                continue
            x = np.float64(pts[r, 0])
            y = np.float64(pts[r, 1])
            z = np.float64(pts[r, 2])
            rh = math.sqrt(x * x + y * y) + 1e-3
            j = r % width
            for e in range(col_start[j], col_start[j + 1]):
                k = col_obj[e]
                if dmin[k] > rh:
                    break
                m = box_index[k]
                if kind[k] != KIND_VEHICLE or m < 0:
                    continue
                if point_in_box(x, y, z, table, m):
                    out[r] = m
                    break
    return out


def count_table(boxes: np.ndarray, bottom_lift: float) -> np.ndarray:
    """(M, 9) float64 per-box constants of the counting test: cx, cy, cos, sin, hx, hy, z_lo, z_hi, 0.

    Built with numpy from the float32 frame boxes exactly as `detbench.ops.points_in_boxes`
    builds its table, so both decide every point the same way.
    """
    b = np.ascontiguousarray(boxes[:, :7], dtype=np.float64)
    t = np.zeros((b.shape[0], 9), dtype=np.float64)
    t[:, 0], t[:, 1] = b[:, 0], b[:, 1]
    t[:, 2], t[:, 3] = np.cos(b[:, 6]), np.sin(b[:, 6])
    t[:, 4], t[:, 5] = 0.5 * b[:, 3], 0.5 * b[:, 4]
    t[:, 6] = b[:, 2] - 0.5 * b[:, 5] + bottom_lift
    t[:, 7] = b[:, 2] + 0.5 * b[:, 5]
    return t


@njit(cache=True)
def point_in_box(x, y, z, table, m):
    """True if (x, y, z) (float64) lies in box m of a `count_table`: all faces inclusive,
    the bottom raised by the table's lift. This is the counting rule of the study."""
    if z < table[m, 6] or z > table[m, 7]:
        return False
    rx = x - table[m, 0]
    ry = y - table[m, 1]
    u = rx * table[m, 2] + ry * table[m, 3]
    v = -rx * table[m, 3] + ry * table[m, 2]
    return abs(u) <= table[m, 4] and abs(v) <= table[m, 5]


# ---------------------------------------------------------------------------- driver
def cast_lidar(lidar: LidarConfig, scene: SceneObjects, key: int = 0, with_points: bool = True,
               bottom_lift: float = DETECTED_BOTTOM_LIFT, ground_reflectivity: float = 0.3,
               timings: dict | None = None, roll_deg: float = 0.0, keep_ego: bool = False) -> CastResult:
    """Cast one LiDAR over a scene; see the module doc for the stages.

    key: 64-bit seed of this sweep's noise/drop-off (same key, same bytes).
    with_points: False skips the rays whose column holds no vehicle (they cannot change a
      count) and returns no points, only `counts`; the counts are identical either way.
    bottom_lift: metres the box bottom is raised for counting (default: the study's DETECTED_BOTTOM_LIFT).
    timings: if a dict is given, seconds per stage are added to it
      ("prepare", "cull", "cast", "post", "count").
    roll_deg: the sensor's roll about its +x axis (see `rolled_directions`); the scene is in the frame of the
      sensor's column (origin on the road under it, x along its yaw).
    keep_ego: hits on KIND_EGO objects give points (a rig without its self-filter); by default they give none.
    """
    tab = _table(lidar, float(roll_deg))
    nblocks = 64
    tm = timings if timings is not None else {}
    t0 = time.perf_counter()
    height = float(lidar.height)
    a0, a1, dmin, slo, shi = _prepare(scene.pose, scene.label, height, float(lidar.max_range))
    t1 = time.perf_counter()
    col_start, col_obj = _build_columns(a0, a1, dmin, tab.col_lo, tab.col_hi, tab.az0, tab.step, tab.delta_max,
                                        tab.width)
    if with_points:
        only = False
        rays = tab.num_rays
    else:
        # only columns holding a vehicle can change a count: empty the lists of the others
        per_col = np.diff(col_start)
        col_of_entry = np.repeat(np.arange(tab.width), per_col)
        veh_entry = scene.kind[col_obj] == KIND_VEHICLE
        has_vehicle = np.bincount(col_of_entry[veh_entry], minlength=tab.width) > 0
        col_obj = col_obj[has_vehicle[col_of_entry]]
        col_start = np.zeros(tab.width + 1, dtype=np.int64)
        np.cumsum(np.where(has_vehicle, per_col, 0), out=col_start[1:])
        only = True
        rays = int(has_vehicle.sum()) * lidar.channels
    t2 = time.perf_counter()
    t_hit, hit, cosi = _cast(tab.dirs, tab.width, height, float(lidar.max_range), col_start, col_obj, scene.pose,
                             scene.label, scene.parts, scene.part_start, dmin, slo, shi, scene.kind, only, nblocks)
    t3 = time.perf_counter()
    pts, keep = _post(tab.dirs, height, float(lidar.max_range), t_hit, hit, cosi, scene.kind, scene.reflectivity,
                      float(ground_reflectivity), np.uint64(key & 0xFFFFFFFFFFFFFFFF), float(lidar.range_noise_m),
                      float(lidar.dropout), float(lidar.dropoff_intensity_limit), float(lidar.dropoff_zero_intensity),
                      float(lidar.attenuation_per_m), float(lidar.incidence_weight), bool(keep_ego), nblocks)
    t4 = time.perf_counter()
    table = count_table(scene.boxes, float(bottom_lift))
    box_of_ray = _count(pts, keep, tab.width, col_start, col_obj, scene.kind, dmin, scene.box_index, table, nblocks)
    m = scene.boxes.shape[0]
    inside = box_of_ray[box_of_ray >= 0]
    counts = np.bincount(inside, minlength=m).astype(np.int64)
    if with_points:
        points = pts[keep]
        point_box = box_of_ray[keep]
    else:
        points = np.zeros((0, 4), dtype=np.float32)
        point_box = np.zeros(0, dtype=np.int64)
    t5 = time.perf_counter()
    for name, dt in (("prepare", t1 - t0), ("cull", t2 - t1), ("cast", t3 - t2), ("post", t4 - t3), ("count", t5 - t4)):
        tm[name] = tm.get(name, 0.0) + dt
    hit_obj = hit[hit >= 0]
    self_hits = int(np.count_nonzero(scene.kind[hit_obj] == KIND_EGO)) if hit_obj.size else 0
    return CastResult(points, point_box, counts, rays, tm, self_hits)


__all__ = ["CastResult", "cast_lidar", "point_in_box", "count_table"]
