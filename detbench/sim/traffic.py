"""Traffic on both carriageways: car-following (IDM), lane changes (MOBIL-like), and a
window of road that travels with the ego.

Each carriageway is a set of lane rings: a vehicle's longitudinal position is kept as
`x = s - s_ego` (metres, relative to the ego's centre along the road) inside the window
[-behind, ahead). A vehicle leaving the window at one end re-enters at the other end of
the same lane as a new vehicle (new track id): the window is a ring, so gaps and order
never change at the seam, and the seam lies far outside the region any LiDAR sees
(`ahead` > max range). The ego is vehicle 0 of its carriageway and never leaves.

Car-following is IDM+ (Schakel et al. 2010), the Intelligent Driver Model (Treiber et al.
2000) with its free-road and interaction terms combined by a minimum: acceleration
a min(1 - (v / v0)^4, 1 - (s* / gap)^2), s* = s0 + v T + v dv / (2 sqrt(a b)); a follower
therefore settles at the gap s0 + v T (CARLA-like tight platoons) even when it drives
close to its desired speed. Integration is
ballistic with step dt; a hard guard then limits every advance so that the bumper-to-bumper
gap to the leader never drops below `min_gap_hard` metres, so vehicles never overlap.
A vehicle changing lanes occupies both lanes until it has finished, and is leader and
follower in both, so lane changes cannot cause overlaps either.

Spawning: each lane ring holds exactly its share (density x window length) of vehicles,
filled front to back: a vehicle follows the one ahead at a short platoon gap with
probability `platoon.follow_fraction`, else at a free gap, and the free gaps are scaled to
fill the ring (see `Traffic._spawn_lane`). Vehicles come from a shuffled deck that holds every
blueprint once (`vehicles.blueprint_deck`), or the class mix in proportion
(`vehicles.mix_deck_size`), so every scene has close to the catalogue's share of trucks and vans.
Desired speeds: speed limit x lane factor (faster inside) x vehicle factor; platoon
followers want slightly more than their leader so platoons stay together.

The ego drives like CARLA's autopilot in traffic: a little faster than the flow
(`ego_speed_factor`) so that it catches up and follows the vehicle ahead at its own short
headway (`ego_time_headway_s`), and every `ego_lane_change_every_s` it moves to a
neighbouring lane that has traffic ahead, which renews its surroundings within a scene.

Lane changes: each vehicle draws at `rate_per_s` a chance to consider its neighbours; it
changes when the gap ahead and behind in the target lane are safe (the new follower would
not brake harder than `safe_decel`), and its own IDM acceleration there beats the current
one by `threshold` (minus `keep_right_bias` for moving right). The lateral move follows a
smoothstep over `duration_s`; the vehicle's yaw follows the lateral speed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from detbench.sim.vehicles import VehicleCatalog, VehicleShape


@dataclass
class IDMParams:
    accel: float = 1.5  # m/s^2
    decel: float = 2.5  # comfortable deceleration, m/s^2
    time_headway: tuple[float, float] = (1.0, 1.8)  # s, uniform per vehicle
    min_gap: float = 2.0  # s0, metres
    min_gap_hard: float = 0.5  # metres, never closer
    delta: float = 4.0


# ------------------------------------------------------------------------- kernels
@njit(cache=True)
def _fwd(xi, xj, direction, ring):
    d = direction * (xj - xi)
    d = d % ring
    return d


@njit(cache=True)
def _nearest(i, lane_q, x, lane, lane_from, direction, ring, ahead):
    """Nearest vehicle in lane `lane_q` ahead of vehicle i (ahead=True) or behind it, and its gap."""
    best = np.inf
    bj = -1
    for j in range(x.shape[0]):
        if j == i:
            continue
        if lane[j] != lane_q and lane_from[j] != lane_q:
            continue
        d = _fwd(x[i], x[j], direction, ring) if ahead else _fwd(x[j], x[i], direction, ring)
        if d < best:
            best = d
            bj = j
    return bj, best


@njit(cache=True)
def _leader(i, lane_q, x, lane, lane_from, direction, ring):
    return _nearest(i, lane_q, x, lane, lane_from, direction, ring, True)


@njit(cache=True)
def _follower(i, lane_q, x, lane, lane_from, direction, ring):
    return _nearest(i, lane_q, x, lane, lane_from, direction, ring, False)


@njit(cache=True)
def _idm(v, v0, vl, gap, T, a, b, s0, delta):
    if gap == np.inf:
        inter = 0.0
    else:
        s_star = s0 + max(0.0, v * T + v * (v - vl) / (2.0 * math.sqrt(a * b)))
        g = max(gap, 0.1)
        inter = (s_star / g) ** 2
    acc = a * min(1.0 - (v / max(v0, 0.1)) ** delta, 1.0 - inter)
    return max(acc, -9.0)


@njit(cache=True)
def _acc_in_lane(i, lane_q, x, lane, lane_from, v, v0, length, T, a, b, s0, delta, direction, ring):
    j, d = _leader(i, lane_q, x, lane, lane_from, direction, ring)
    if j < 0:
        return _idm(v[i], v0[i], v[i], np.inf, T[i], a, b, s0, delta)
    gap = d - 0.5 * (length[i] + length[j])
    return _idm(v[i], v0[i], v[j], gap, T[i], a, b, s0, delta)


@njit(cache=True)
def gap_accepted(i, tgt, x, lane, lane_from, v, base_v0, lane_factor, length, T, a, b, s0, delta, direction, ring,
                 safe_decel, time_gap):
    """True if vehicle i can move into lane `tgt` now: room ahead and behind (s0 + time_gap v,
    metres) and the new follower would not brake harder than `safe_decel` (m/s^2)."""
    jl, dl = _leader(i, tgt, x, lane, lane_from, direction, ring)
    jf, df = _follower(i, tgt, x, lane, lane_from, direction, ring)
    if jl >= 0 and dl - 0.5 * (length[i] + length[jl]) < s0 + time_gap * v[i]:
        return False
    if jf >= 0:
        gap_f = df - 0.5 * (length[i] + length[jf])
        if gap_f < s0 + time_gap * v[jf]:
            return False
        af = _idm(v[jf], base_v0[jf] * lane_factor[tgt], v[i], gap_f, T[jf], a, b, s0, delta)
        if af < -safe_decel:
            return False
    return True


@njit(cache=True)
def traffic_step(x, lane, lane_from, lc_prog, v, base_v0, lane_factor, length, T, lane_lo, lane_hi, can_change,
                 direction, ring, dt, a, b, s0, delta, s_hard, lc_rate, lc_duration, lc_threshold, keep_right_bias,
                 safe_decel, n_lanes, uniforms, ego_ds):
    """Advance one carriageway by dt seconds, in place.

    x (n,) metres relative to the ego (window coordinates, not yet wrapped); lane/lane_from
    (n,) int64 (lane_from = -1 unless changing); lc_prog (n,) in [0, 1]; v (n,) m/s; the desired
    speed of vehicle i is base_v0[i] * lane_factor[lane[i]] (m/s; faster lanes inside);
    length (n,) metres; T (n,) s; lane_lo/lane_hi (n,) allowed lanes; can_change (n,) bool;
    direction +1 (ego's carriageway) or -1; ring = window length; uniforms (n,) in [0, 1);
    ego_ds: the ego's advance this step (metres), subtracted from every x.
    Returns the advance ds (n,) metres of every vehicle along its own direction.
    """
    n = x.shape[0]
    v0 = np.empty(n)
    for i in range(n):
        v0[i] = base_v0[i] * lane_factor[lane[i]]
    acc = np.empty(n)
    for i in range(n):
        acc[i] = _acc_in_lane(i, lane[i], x, lane, lane_from, v, v0, length, T, a, b, s0, delta, direction, ring)
        if lane_from[i] >= 0:
            acc[i] = min(acc[i], _acc_in_lane(i, lane_from[i], x, lane, lane_from, v, v0, length, T, a, b, s0,
                                              delta, direction, ring))
    # lane changes: decided on the state at the start of the step
    for i in range(n):
        if lane_from[i] >= 0 or not can_change[i] or uniforms[i] >= lc_rate * dt:
            continue
        best_gain = 0.0
        best_lane = -1
        for side in range(2):
            tgt = lane[i] - 1 if side == 0 else lane[i] + 1  # lane numbers grow outwards (to the right)
            if tgt < lane_lo[i] or tgt > lane_hi[i] or tgt < 0 or tgt >= n_lanes:
                continue
            jl, dl = _leader(i, tgt, x, lane, lane_from, direction, ring)
            jf, df = _follower(i, tgt, x, lane, lane_from, direction, ring)
            if jl >= 0 and dl - 0.5 * (length[i] + length[jl]) < s0 + 0.3 * v[i]:
                continue
            if jf >= 0:
                gap_f = df - 0.5 * (length[i] + length[jf])
                if gap_f < s0 + 0.3 * v[jf]:
                    continue
                af = _idm(v[jf], v0[jf], v[i], gap_f, T[jf], a, b, s0, delta)
                if af < -safe_decel:
                    continue
            if jl >= 0:
                a_new = _idm(v[i], base_v0[i] * lane_factor[tgt], v[jl], dl - 0.5 * (length[i] + length[jl]), T[i],
                             a, b, s0, delta)
            else:
                a_new = _idm(v[i], base_v0[i] * lane_factor[tgt], v[i], np.inf, T[i], a, b, s0, delta)
            gain = a_new - acc[i] - lc_threshold + (keep_right_bias if side == 1 else -keep_right_bias)
            if gain > best_gain:
                best_gain = gain
                best_lane = tgt
        if best_lane >= 0:
            lane_from[i] = lane[i]
            lane[i] = best_lane
            lc_prog[i] = 0.0
    # ballistic update, then the no-overlap guard
    vn = np.empty(n)
    ds = np.empty(n)
    for i in range(n):
        vn[i] = max(v[i] + acc[i] * dt, 0.0)
        ds[i] = 0.5 * (v[i] + vn[i]) * dt
    for _ in range(8):
        changed = False
        for i in range(n):
            for q in range(2):
                lq = lane[i] if q == 0 else lane_from[i]
                if lq < 0:
                    continue
                j, d = _leader(i, lq, x, lane, lane_from, direction, ring)
                if j < 0:
                    continue
                room = d - 0.5 * (length[i] + length[j]) - s_hard + ds[j]
                if ds[i] > room:
                    ds[i] = max(room, 0.0)
                    vn[i] = min(vn[i], vn[j])
                    changed = True
        if not changed:
            break
    for i in range(n):
        v[i] = vn[i]
        x[i] += direction * ds[i] - ego_ds
        if lane_from[i] >= 0:
            lc_prog[i] += dt / lc_duration
            if lc_prog[i] >= 1.0:
                lc_prog[i] = 0.0
                lane_from[i] = -1
    return ds


def lane_profile(values, n_lanes: int) -> np.ndarray:
    """A per-lane profile (inner lane first) resampled to `n_lanes` lanes, (n_lanes,) float64.

    The config lists one value per lane; a list of another length is read as a profile
    from the inner to the outer lane and interpolated linearly, so changing
    `road.lanes_per_direction` needs no other edit. An empty list means all ones.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        return np.ones(n_lanes)
    if v.size == n_lanes:
        return v.copy()
    if v.size == 1 or n_lanes == 1:
        return np.full(n_lanes, v.mean() if n_lanes == 1 else v[0])
    return np.interp(np.linspace(0.0, 1.0, n_lanes), np.linspace(0.0, 1.0, v.size), v)


# ------------------------------------------------------------------------- state
class Carriageway:
    """Vehicles of one carriageway (see the module doc). Arrays are (n,); index 0 is the ego
    on the ego's carriageway."""

    def __init__(self, direction: int, n_lanes: int, ring: float):
        self.direction = int(direction)
        self.n_lanes = int(n_lanes)
        self.ring = float(ring)
        self.x = np.zeros(0)
        self.lane = np.zeros(0, np.int64)
        self.lane_from = np.zeros(0, np.int64)
        self.lc_prog = np.zeros(0)
        self.v = np.zeros(0)
        self.v0 = np.zeros(0)
        self.T = np.zeros(0)
        self.lat = np.zeros(0)  # lateral offset in the lane, metres, + to the left of the driving direction
        self.lane_lo = np.zeros(0, np.int64)
        self.lane_hi = np.zeros(0, np.int64)
        self.can_change = np.zeros(0, bool)
        self.track = np.zeros(0, np.int64)
        self.shapes: list[VehicleShape] = []

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    @property
    def length(self) -> np.ndarray:
        return np.array([s.length for s in self.shapes])

    def add(self, shape: VehicleShape, x, lane, v, v0, T, lat, lane_lo, lane_hi, can_change, track):
        """Append one vehicle: x metres (window coordinates), lane, speed v and base desired speed
        v0 (m/s), headway T (s), lateral offset lat (m), allowed lanes, lane-change flag, track id."""
        self.shapes.append(shape)
        cat = np.concatenate
        self.x = cat([self.x, [x]])
        self.lane = cat([self.lane, [lane]]).astype(np.int64)
        self.lane_from = cat([self.lane_from, [-1]]).astype(np.int64)
        self.lc_prog = cat([self.lc_prog, [0.0]])
        self.v = cat([self.v, [v]])
        self.v0 = cat([self.v0, [v0]])
        self.T = cat([self.T, [T]])
        self.lat = cat([self.lat, [lat]])
        self.lane_lo = cat([self.lane_lo, [lane_lo]]).astype(np.int64)
        self.lane_hi = cat([self.lane_hi, [lane_hi]]).astype(np.int64)
        self.can_change = cat([self.can_change, [can_change]]).astype(bool)
        self.track = cat([self.track, [track]]).astype(np.int64)

    def finalize(self):
        """Freeze the lengths (n,) metres used by the kernels (shapes never change in a scene)."""
        self._len = self.length

    def lateral_offset(self, layout):
        """Where the vehicles are across the road, including lane changes.

        Returns d (n,) metres from the centre line (+ left of +s), changing (n,) bool,
        dw (n,) the derivative of the smoothstep lane-change profile w.r.t. its progress,
        span (n,) metres between the old and new lane centres; the lateral speed of a
        changing vehicle is span * dw / duration.
        """
        opp = self.direction < 0
        d_now = layout.lane_offset(self.lane, opposite=opp)
        changing = self.lane_from >= 0
        d_from = layout.lane_offset(np.where(changing, self.lane_from, self.lane), opposite=opp)
        p = np.clip(self.lc_prog, 0.0, 1.0)
        w = p * p * (3.0 - 2.0 * p)
        dw = 6.0 * p * (1.0 - p)
        sign = 1.0 if not opp else -1.0  # the vehicle's left in world d terms
        d = d_from + (d_now - d_from) * w + sign * self.lat
        return d, changing, dw, d_now - d_from


class Traffic:
    """Both carriageways of one scene around the ego (see the module doc)."""

    def __init__(self, cfg: dict, layout, catalog: VehicleCatalog, rng: np.random.Generator, first_track: int = 1):
        t = cfg
        self.layout = layout
        self.catalog = catalog
        self.rng = rng
        self.behind = float(t["window_behind_m"])
        self.ahead = float(t["window_ahead_m"])
        self.ring = self.behind + self.ahead
        idm = t["idm"]
        self.idm = IDMParams(float(idm["accel"]), float(idm["decel"]), tuple(float(u) for u in idm["time_headway_s"]),
                             float(idm["min_gap_m"]), float(idm["min_gap_hard_m"]), float(idm["delta"]))
        lc = t["lane_change"]
        self.lc_enabled = bool(lc["enabled"])
        self.lc_rate = float(lc["rate_per_s"])
        self.lc_duration = float(lc["duration_s"])
        self.lc_threshold = float(lc["threshold_mps2"])
        self.lc_keep_right = float(lc["keep_right_bias_mps2"])
        self.lc_safe = float(lc["safe_decel_mps2"])
        self.speed_limit = float(t["speed_limit_mps"])
        self.speed_spread = float(t["speed_spread"])
        self.lat_jitter = float(t["lateral_jitter_m"])
        pl = t["platoon"]
        self.follow_fraction = float(pl["follow_fraction"])
        self.free_gap_spread = float(pl["free_gap_spread"])
        self.platoon_gap = tuple(float(u) for u in pl["gap_m"])
        self.platoon_boost = float(pl["follower_speed_boost"])
        self.ego_in_platoon = bool(pl.get("ego_in_platoon", False))
        self.ego_speed_factor = float(t["ego_speed_factor"])
        self.ego_headway = tuple(float(u) for u in t["ego_time_headway_s"])
        every = t["ego_lane_change_every_s"]
        self.ego_lc_every = tuple(float(u) for u in every) if every else None
        self.ego_lc_lookahead = float(t["ego_lane_change_lookahead_m"])
        self.ego_lc_time_gap = float(t["ego_lane_change_time_gap_s"])
        self.ego_lc_timer = float(rng.uniform(*self.ego_lc_every)) if self.ego_lc_every else 0.0
        self.lane_factor = lane_profile(t["lane_speed_factors"], layout.lanes_per_direction)
        self.next_track = int(first_track)
        self.deck = catalog.deck(rng)
        n_lanes = layout.lanes_per_direction
        self.own = Carriageway(+1, n_lanes, self.ring)
        self.opp = Carriageway(-1, n_lanes, self.ring)
        self._populate(t)

    # ------------------------------------------------------------------ set-up
    def _new_track(self) -> int:
        k = self.next_track
        self.next_track += 1
        return k

    def _lane_range(self, type_name: str) -> tuple[int, int]:
        n = self.layout.lanes_per_direction
        outer = self.catalog.types[type_name].outer_lanes_only
        return (max(n - outer, 0), n - 1) if outer > 0 else (0, n - 1)

    def _draw_type(self, lane: int) -> str | None:
        """A vehicle type allowed in `lane`, from the stratified deck (or freely when the deck
        is off); None when no allowed type turns up in 20 draws."""
        for _ in range(20):
            name = self.deck.draw() if self.deck is not None else self.catalog.sample_type(self.rng)
            lo, hi = self._lane_range(name)
            if lo <= lane <= hi:
                return name
        return None

    def _spawn_lane(self, cw: Carriageway, lane: int, density_km: float, ego_shape: VehicleShape | None = None):
        """Fill one lane ring with exactly its share of vehicles.

        The lane holds n = density_km x ring / 1000 vehicles (the fraction rounded up with
        its probability), so scenes differ in where the vehicles are, not in how many there
        are. Going from the front to the back, each vehicle follows the one ahead at a short
        platoon gap (uniform in `platoon.gap_m`, bumper to bumper) with probability
        `platoon.follow_fraction`, else at a free gap of min_gap + 0.5 m plus a share of the
        room left, in proportion to a weight uniform in [1 - spread, 1 + spread]
        (`platoon.free_gap_spread`; 1 gives the most irregular traffic), so that the ring is
        filled exactly. A lane too short for its vehicles bumper to bumper at min_gap_hard
        keeps only those that fit (never dropping the ego). A
        follower's desired speed is its leader's plus `platoon.follower_speed_boost`, so
        platoons stay together; other vehicles draw their own. On the ego's lane the ego
        (`ego_shape`, already added at x = 0) is the first vehicle of the ring and counts
        towards n.
        """
        rng = self.rng
        n_mean = max(density_km, 0.0) * self.ring / 1000.0
        n = int(math.floor(n_mean)) + int(rng.random() < n_mean - math.floor(n_mean))
        if ego_shape is not None:
            n = max(n, 1)
        if n == 0:
            return
        p = self.follow_fraction
        items = []  # (type_name or None for the ego, shape, following)
        if ego_shape is not None:  # with ego_in_platoon the ego follows the vehicle ahead like any other vehicle
            items.append((None, ego_shape, self.ego_in_platoon and rng.random() < p))
        while len(items) < n:
            name = self._draw_type(lane)
            if name is None:
                break
            items.append((name, self.catalog.sample(rng, name), len(items) > 0 and rng.random() < p))
        # a lane cannot hold more than bumper-to-bumper at min_gap_hard: drop the last ones (never the ego)
        while len(items) > 1 and sum(it[1].length for it in items) + len(items) * self.idm.min_gap_hard > self.ring:
            items.pop()
        n = len(items)
        lengths = np.array([it[1].length for it in items])
        follow = np.array([it[2] for it in items])
        if follow.all() and n > 1:  # a ring needs one free gap to close it: the ego followed, so free another one
            follow[int(rng.integers(1, n))] = False
        gaps = np.where(follow, rng.uniform(*self.platoon_gap, size=n), 0.0)
        if ego_shape is not None and follow[0]:
            # the ego is spawned already following at its own headway (not stopped behind a platoon gap)
            v_ego = cw.v0[0] * self.lane_factor[lane]
            gaps[0] = max(gaps[0], self.idm.min_gap + v_ego * cw.T[0])
        weights = np.where(follow, 0.0, rng.uniform(1.0 - self.free_gap_spread, 1.0 + self.free_gap_spread, size=n))
        free_min = self.idm.min_gap + 0.5
        room = self.ring - lengths.sum() - gaps.sum() - free_min * (~follow).sum()
        if room < 0 or weights.sum() <= 0:
            # too dense for the window: every gap becomes the same (at least min_gap_hard)
            gaps = np.full(n, max((self.ring - lengths.sum()) / n, self.idm.min_gap_hard))
        else:
            gaps = gaps + np.where(follow, 0.0, free_min + weights * room / weights.sum())
        # gaps[k] is the gap between vehicle k and the one ahead of it (k - 1; for k = 0 the last one, around the ring)
        x0 = 0.0 if ego_shape is not None else float(rng.uniform(-self.behind, self.ahead))
        pos = x0
        prev_speed = None
        for k, (name, shape, following) in enumerate(items):
            if k > 0:
                pos -= 0.5 * (lengths[k - 1] + lengths[k]) + gaps[k]
            if name is None:  # the ego is already in place
                prev_speed = None
                continue
            if following and prev_speed is not None:
                speed = prev_speed * (1.0 + self.platoon_boost)
            else:
                speed = float(np.clip(rng.normal(1.0, self.speed_spread), 0.7, 1.3))
            prev_speed = speed
            x = -self.behind + (pos + self.behind) % self.ring
            self._add(cw, shape, name, x, lane, speed=speed)

    def _add(self, cw: Carriageway, shape: VehicleShape, type_name: str, x: float, lane: int, ego: bool = False,
             speed: float | None = None):
        rng = self.rng
        vt = self.catalog.types[type_name]
        if ego:
            f = self.ego_speed_factor
        elif speed is not None:
            f = speed
        else:
            f = float(np.clip(rng.normal(1.0, self.speed_spread), 0.7, 1.3))
        v0 = self.speed_limit * vt.speed_factor * f
        T = float(rng.uniform(*(self.ego_headway if ego else self.idm.time_headway)))
        lat = 0.0 if ego else float(np.clip(rng.normal(0.0, self.lat_jitter),
                                            -2 * self.lat_jitter, 2 * self.lat_jitter))
        lo, hi = self._lane_range(type_name)
        cw.add(shape, x, lane, v0 * self.lane_factor[lane], v0, T, lat, lo, hi, self.lc_enabled and vt.lane_change,
               self._new_track())

    def _populate(self, t: dict):
        rng = self.rng
        n = self.layout.lanes_per_direction
        ego_w = lane_profile(t["ego_lane_weights"], n)
        ego_w = ego_w / ego_w.sum()
        self.ego_type = str(t["ego_type"])
        if not self.catalog.knows(self.ego_type):
            raise ValueError(f"traffic.ego_type {self.ego_type!r} is not a vehicle type, blueprint or blueprint class; "
                             f"known: {', '.join([*self.catalog.classes, *self.catalog.types])}")
        ego_lane = int(rng.choice(n, p=ego_w))
        ego_name = self.catalog.pick(rng, self.ego_type)  # a class of blueprints: one of them
        ego_shape = self.catalog.sample(rng, ego_name)
        self._add(self.own, ego_shape, ego_name, 0.0, ego_lane, ego=True)
        self.own.can_change[0] = False  # the ego changes lanes only on its own schedule (ego_lane_change_every_s)
        self.own.lane_lo[0], self.own.lane_hi[0] = 0, n - 1
        lane_w = lane_profile(t["lane_density_weights"], n)
        # scene-to-scene variation of the traffic volume: a Gamma factor of mean 1
        shape = float(t["scene_density_shape"])
        self.scene_density = float(rng.gamma(shape, 1.0 / shape)) if shape > 0 else 1.0
        for lane in range(n):
            self._spawn_lane(self.own, lane, float(t["density_per_km_lane"]) * lane_w[lane] * self.scene_density,
                             ego_shape if lane == ego_lane else None)
        for lane in range(n):
            self._spawn_lane(self.opp, lane,
                             float(t["opposite_density_per_km_lane"]) * lane_w[lane] * self.scene_density)
        for cw in (self.own, self.opp):
            cw.finalize()
            self._settle_speeds(cw)

    def _settle_speeds(self, cw: Carriageway):
        """Start every vehicle at the IDM equilibrium speed for its gap (no initial braking waves)."""
        for i in range(cw.n):
            j, d = _leader(i, cw.lane[i], cw.x, cw.lane, cw.lane_from, cw.direction, cw.ring)
            if j < 0:
                continue
            gap = d - 0.5 * (cw._len[i] + cw._len[j])
            veq = max((gap - self.idm.min_gap) / cw.T[i], 0.0)
            cw.v[i] = min(cw.v0[i] * self.lane_factor[cw.lane[i]], veq)

    # ------------------------------------------------------------------ time
    def step(self, dt: float) -> float:
        """Advance both carriageways by dt seconds; returns the ego's advance (metres)."""
        own, opp = self.own, self.opp
        p = self.idm
        self._ego_lane_change(dt)
        u_own = self.rng.random(own.n)
        u_opp = self.rng.random(opp.n)
        ds_own = traffic_step(own.x, own.lane, own.lane_from, own.lc_prog, own.v, own.v0, self.lane_factor, own._len,
                              own.T,
                              own.lane_lo, own.lane_hi, own.can_change, 1, self.ring, dt, p.accel, p.decel,
                              p.min_gap, p.delta, p.min_gap_hard, self.lc_rate, self.lc_duration, self.lc_threshold,
                              self.lc_keep_right, self.lc_safe, own.n_lanes, u_own, 0.0)
        ego_ds = float(ds_own[0])
        own.x -= ego_ds  # re-centre on the ego (traffic_step moved everyone by their own advance)
        traffic_step(opp.x, opp.lane, opp.lane_from, opp.lc_prog, opp.v, opp.v0, self.lane_factor, opp._len, opp.T,
                     opp.lane_lo,
                     opp.lane_hi, opp.can_change, -1, self.ring, dt, p.accel, p.decel, p.min_gap, p.delta,
                     p.min_gap_hard, self.lc_rate, self.lc_duration, self.lc_threshold, self.lc_keep_right,
                     self.lc_safe, opp.n_lanes, u_opp, ego_ds)
        for cw in (own, opp):
            self._wrap(cw)
        return ego_ds

    def _ego_lane_change(self, dt: float) -> None:
        """The ego changes to a random neighbouring lane every `ego_lane_change_every_s` seconds
        (uniform in that range), as soon as the gap there is accepted. Only lanes with a vehicle
        ahead within `ego_lane_change_lookahead_m` are chosen: the ego changes lanes to join
        traffic, not into an empty lane; but when it has waited one further full period
        (the lower bound of the range) any neighbouring lane with an accepted gap will do,
        so a scene never stalls behind one leader."""
        if self.ego_lc_every is None:
            return
        own, p = self.own, self.idm
        self.ego_lc_timer -= dt
        if self.ego_lc_timer > 0 or own.lane_from[0] >= 0:
            return
        k = int(own.lane[0])
        # after waiting a further full period, any lane with an accepted gap will do (no scene-long stalls)
        impatient = self.ego_lc_timer < -self.ego_lc_every[0]
        options = []
        for q in (k - 1, k + 1):
            if not 0 <= q < own.n_lanes:
                continue
            j, d = _leader(0, q, own.x, own.lane, own.lane_from, 1, self.ring)
            if (j < 0 or d > self.ego_lc_lookahead) and not impatient:
                continue
            if gap_accepted(0, q, own.x, own.lane, own.lane_from, own.v, own.v0, self.lane_factor, own._len, own.T,
                            p.accel, p.decel, p.min_gap, p.delta, 1, self.ring, self.lc_safe, self.ego_lc_time_gap):
                options.append(q)
        if not options:
            return  # nothing suitable now: look again next step
        tgt = int(options[int(self.rng.integers(len(options)))])
        own.lane_from[0] = own.lane[0]
        own.lane[0] = tgt
        own.lc_prog[0] = 0.0
        self.ego_lc_timer = float(self.rng.uniform(*self.ego_lc_every))

    def _wrap(self, cw: Carriageway):
        lo, hi = -self.behind, self.ahead
        out = (cw.x < lo) | (cw.x >= hi)
        if cw is self.own:
            out[0] = False
        if out.any():
            for i in np.flatnonzero(out):
                cw.x[i] = lo + (cw.x[i] - lo) % self.ring
                cw.track[i] = self._new_track()
