"""`HighwaySimulator`: scenes of moving highway traffic seen by any number of LiDARs.

One scene = a fresh road (straights and curves), fresh traffic around the ego, a warm-up,
then `frames_per_scene` frames saved at `frame_rate_hz`. Every frame, all LiDARs see the
same traffic at the same instant; each gets its own `SimFrame` (a `Frame` plus the
per-box hit counts of the ray caster). Randomness is drawn from numpy generators seeded
by (seed, scene), and per-ray noise from a hash of (seed, scene, frame, LiDAR), so the
same seed and config give byte-identical output whatever the thread count.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from collections.abc import Iterator, Sequence

import numpy as np

from detbench.config import CONFIG_DIR, ConfigError, apply_overrides, deep_merge, load_config, validate
from detbench.data.frame import LANE_OPPOSITE, Frame
from detbench.data.regions import DETECTED_BOTTOM_LIFT
from detbench.sim.lidar import LidarConfig
from detbench.sim.raycast import cast_lidar
from detbench.sim.scene_objects import KIND_EGO, KIND_OCCLUDER, KIND_VEHICLE, pack_scene, wrap_angle
from detbench.sim.probes import PROBE_KINDS, PROBE_PLACES, PROBE_REFLECTIVITY, Probes, probe_parts
from detbench.sim.rig_cast import cast_rig
from detbench.sim.rigs import Rig
from detbench.sim.road import Road, RoadLayout
from detbench.sim.traffic import Traffic, lane_profile
from detbench.sim.vehicles import VehicleCatalog, label_box_local

SIM_CONFIG = CONFIG_DIR / "sim.yaml"


# ---------------------------------------------------------------------------- config
def _reference() -> dict:
    cfg = load_config(SIM_CONFIG)
    cfg.pop("presets", None)
    return cfg


def sim_presets() -> list[str]:
    """Names of the presets in configs/sim.yaml."""
    return list(load_config(SIM_CONFIG).get("presets", {}) or {})


def load_sim_config(preset: str = "paper", overrides: Sequence[str] = ()) -> dict:
    """The simulator config: configs/sim.yaml's defaults, the named preset, then overrides.

    overrides: "section.key=value" strings (YAML values); an unknown key raises ConfigError
    naming the closest known key. Returns a plain dict (see configs/sim.yaml for the keys).
    """
    full = load_config(SIM_CONFIG)
    presets = full.pop("presets", {}) or {}
    if preset not in presets:
        raise ConfigError(f"{SIM_CONFIG}: unknown simulator preset {preset!r}; known: {', '.join(presets)}")
    validate(presets[preset] or {}, full, where=f"{SIM_CONFIG}: presets.{preset}")
    cfg = deep_merge(full, presets[preset] or {})
    cfg = apply_overrides(cfg, list(overrides), reference=full)
    check_sim_config(cfg)
    return cfg


def _num(cfg, dotted, lo=None, hi=None, integer=False):
    node = cfg
    for k in dotted.split("."):
        node = node[k]
    ok = isinstance(node, (int, float)) and not isinstance(node, bool) and math.isfinite(node)
    if ok and integer:
        ok = float(node).is_integer()
    if ok and lo is not None:
        ok = node >= lo
    if ok and hi is not None:
        ok = node <= hi
    if not ok:
        rng = f" in [{lo}, {hi}]" if hi is not None else (f" >= {lo}" if lo is not None else "")
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"sim config: {dotted} must be {kind}{rng}, got {node!r} (configs/sim.yaml; fix the "
                          f"preset or the --set override)")
    return node


def _pair(cfg, dotted, lo=0.0):
    node = cfg
    for k in dotted.split("."):
        node = node[k]
    if not (isinstance(node, (list, tuple)) and len(node) == 2 and all(isinstance(u, (int, float)) for u in node)
            and lo <= node[0] <= node[1]):
        raise ConfigError(f"sim config: {dotted} must be [min, max] with {lo} <= min <= max, got {node!r}")


def check_sim_config(cfg: dict) -> None:
    """Raise ConfigError for unknown keys or out-of-range values (naming the key)."""
    validate(cfg, _reference(), where="sim config")
    _num(cfg, "scene.frames_per_scene", 1, integer=True)
    _num(cfg, "scene.frame_rate_hz", 1e-3)
    _num(cfg, "scene.sim_dt_s", 1e-3, 1.0)
    _num(cfg, "scene.warmup_s", 0.0)
    _num(cfg, "road.lanes_per_direction", 1, 8, integer=True)
    _num(cfg, "road.lane_width_m", 2.0, 6.0)
    _num(cfg, "road.median_width_m", 0.0)
    _num(cfg, "road.shoulder_m", 0.0)
    _num(cfg, "road.curve_fraction", 0.0, 1.0)
    _pair(cfg, "road.curve_radius_m", 50.0)
    _pair(cfg, "road.curve_length_m", 0.0)
    _pair(cfg, "road.straight_length_m", 1.0)
    _num(cfg, "road.transition_m", 0.0)
    _num(cfg, "road.barriers.segment_length_m", 1.0)
    for b in ("median", "outer"):
        _num(cfg, f"road.barriers.{b}.height_m", 0.0)
        _num(cfg, f"road.barriers.{b}.width_m", 0.01)
    _num(cfg, "traffic.window_behind_m", 50.0)
    _num(cfg, "traffic.window_ahead_m", 100.0)
    _num(cfg, "traffic.density_per_km_lane", 0.0, 150.0)
    _num(cfg, "traffic.opposite_density_per_km_lane", 0.0, 150.0)
    _num(cfg, "traffic.scene_density_shape", 0.0)
    _num(cfg, "traffic.platoon.follow_fraction", 0.0, 0.95)
    _pair(cfg, "traffic.platoon.gap_m", 0.5)
    _num(cfg, "traffic.platoon.free_gap_spread", 0.0, 1.0)
    _num(cfg, "traffic.platoon.follower_speed_boost", 0.0, 0.5)
    _num(cfg, "traffic.ego_speed_factor", 0.5, 1.5)
    every = cfg["traffic"]["ego_lane_change_every_s"]
    if every not in ([], None):
        _pair(cfg, "traffic.ego_lane_change_every_s", 1.0)
    _num(cfg, "traffic.ego_lane_change_lookahead_m", 0.0)
    _num(cfg, "traffic.ego_lane_change_time_gap_s", 0.0)
    _num(cfg, "traffic.speed_limit_mps", 1.0, 60.0)
    _num(cfg, "traffic.speed_spread", 0.0, 0.5)
    _num(cfg, "traffic.lateral_jitter_m", 0.0, 0.5)
    _pair(cfg, "traffic.idm.time_headway_s", 0.1)
    _pair(cfg, "traffic.ego_time_headway_s", 0.1)
    _num(cfg, "traffic.idm.min_gap_m", 0.5)
    _num(cfg, "traffic.idm.min_gap_hard_m", 0.1)
    _num(cfg, "traffic.lane_change.rate_per_s", 0.0)
    _num(cfg, "traffic.lane_change.duration_s", 0.5)
    _num(cfg, "vehicles.label_margin_m", 0.0, 0.5)
    _pair(cfg, "output.region_x_m", -1e9)
    _num(cfg, "output.region_abs_y_m", 0.0)
    _num(cfg, "output.count_bottom_lift_m", 0.0)
    _num(cfg, "output.ground_reflectivity", 0.0, 1.0)
    for key in ("lane_density_weights", "ego_lane_weights", "lane_speed_factors"):
        w = cfg["traffic"][key]
        if not (isinstance(w, list) and all(isinstance(u, (int, float)) and not isinstance(u, bool) and u >= 0
                                            for u in w) and (not w or sum(w) > 0)):
            raise ConfigError(f"sim config: traffic.{key} must be a list of non-negative numbers, inner lane first "
                              f"(a list of another length than road.lanes_per_direction is interpolated), got {w!r}")
    if cfg["traffic"]["window_ahead_m"] <= cfg["output"]["region_x_m"][1]:
        raise ConfigError("sim config: traffic.window_ahead_m must exceed output.region_x_m[1] (the traffic seam "
                          "would be visible)")
    try:
        catalog = VehicleCatalog(cfg["vehicles"])
    except (ValueError, KeyError) as e:
        raise ConfigError(f"sim config: vehicles: {e}") from None
    ego = cfg["traffic"]["ego_type"]
    if not catalog.knows(ego):
        raise ConfigError(f"sim config: traffic.ego_type {ego!r} is not a vehicle type, blueprint or blueprint class "
                          f"of vehicles.draw: {catalog.draw}; known: {', '.join([*catalog.classes, *catalog.types])} "
                          f"(configs/sim.yaml)")


# ---------------------------------------------------------------------------- frames
@dataclass
class SimFrame(Frame):
    """A `Frame` from the simulator, with the ray caster's per-box counts.

    hit_counts: (M,) int64 points inside each box with the box bottom raised by
      `count_bottom_lift` metres (the study's rule when DETECTED_BOTTOM_LIFT); filled also when the
      simulator ran with `with_points=False` (then `points` is empty);
    point_box: (N,) int64 row of `boxes` containing each point under the same rule, or -1
      (empty without points);
    rays_cast: rays traced for this frame;
    rig: the rig's name for a frame of a `Rig` ("" for a single LiDAR);
    sensor_index: (N,) int64 index of the rig sensor of each point (empty for a single LiDAR);
    self_hits: (S,) int64 rays of each rig sensor whose first hit is the ego (of the rays traced);
    probe_boxes, probe_kinds, probe_places, probe_counts: the small-object probe's objects in the frame
      ((P, 7) float32 boxes, (P,) kind and place names, (P,) points inside each with the bottom lift), empty
      without the probe.
    """

    hit_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_box: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    count_bottom_lift: float = DETECTED_BOTTOM_LIFT
    rays_cast: int = 0
    rig: str = ""
    sensor_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    self_hits: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    probe_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7), np.float32))
    probe_kinds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U5"))
    probe_places: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype="<U11"))
    probe_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def _mix64(*vals: int) -> int:
    """A 64-bit hash of integers (splitmix64 chain); stable across runs and machines."""
    z = 0x243F6A8885A308D3
    mask = (1 << 64) - 1
    for v in vals:
        z = (z + (int(v) & mask) + 0x9E3779B97F4A7C15) & mask
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        z ^= z >> 31
    return z


def _seed64(seed: int) -> int:
    """`seed` itself below 2**64 (the ray-noise keys of every such seed stay as they were), else a
    64-bit hash of all its 64-bit words, so 2**64 does not repeat seed 0's noise."""
    if seed < 2**64:
        return seed
    words = [(seed >> s) & (2**64 - 1) for s in range(0, seed.bit_length(), 64)]
    return _mix64(len(words), *words)


# ---------------------------------------------------------------------------- simulator
class HighwaySimulator:
    """Highway scenes seen by LiDARs (see the module doc).

    config: a dict like `load_sim_config()` returns (checked again here);
    seed: any integer >= 0, however large (every bit of it seeds the scenes); the same
    (config, seed) gives byte-identical frames.
    """

    def __init__(self, config: dict, seed: int):
        if not isinstance(config, dict):
            raise ConfigError(f"HighwaySimulator: config must be a dict (use load_sim_config()), got "
                              f"{type(config).__name__}")
        check_sim_config(config)
        self.config = copy.deepcopy(config)
        if isinstance(seed, bool) or int(seed) != seed or seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        self.seed = int(seed)
        r = self.config["road"]
        self.layout = RoadLayout(int(r["lanes_per_direction"]), float(r["lane_width_m"]), float(r["median_width_m"]),
                                 float(r["shoulder_m"]))
        self.catalog = VehicleCatalog(self.config["vehicles"])
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------------ public
    def run(self, num_frames: int, lidars: Sequence[LidarConfig | Rig], frames_per_scene: int | None = None,
            with_points: bool = True, small_objects: bool = False) -> Iterator[list[SimFrame]]:
        """Yield `num_frames` time steps; each is a list of `SimFrame`, one per LiDAR or rig in `lidars`.

        A `Rig` (detbench.sim.rigs) gives one frame of its sensors' merged returns (`rig`, `sensor_index`,
        `self_hits` set); a rig of one sensor at the reference point without the body gives exactly that
        sensor's frame.

        Scenes hold `frames_per_scene` frames (config `scene.frames_per_scene` when None);
        frame ids are f"{scene:04d}_{index:03d}", scene ids f"{scene:04d}".
        with_points=False returns frames without points (empty (0, 4)) but with
        `hit_counts`, which are identical to those of a run with points.
        small_objects: place the small-object probe's objects on the road (detbench.sim.probes); each frame
        then carries their boxes and counts (`probe_*`) apart from the vehicles'.
        """
        if int(num_frames) != num_frames or num_frames < 0:
            raise ValueError(f"num_frames must be a non-negative integer, got {num_frames!r}")
        lidars = list(lidars)
        if not lidars or not all(isinstance(lidar, (LidarConfig, Rig)) for lidar in lidars):
            raise ValueError("lidars must be a non-empty list of LidarConfig or Rig (see detbench.sim.lidar_preset, "
                             "detbench.sim.rigs)")
        fps = int(frames_per_scene if frames_per_scene is not None else self.config["scene"]["frames_per_scene"])
        if fps < 1:
            raise ValueError(f"frames_per_scene must be >= 1, got {frames_per_scene!r}")
        done = 0
        scene = 0
        while done < num_frames:
            n = min(fps, num_frames - done)
            yield from self._scene(scene, n, fps, lidars, with_points, small_objects)
            done += n
            scene += 1

    # ------------------------------------------------------------------ scenes
    def _scene(self, scene: int, n_frames: int, fps: int, lidars: list[LidarConfig | Rig], with_points: bool,
               small_objects: bool = False):
        cfg = self.config
        sc, rd, tr, out = cfg["scene"], cfg["road"], cfg["traffic"], cfg["output"]
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, scene, 1]))  # takes big integers whole
        t0 = time.perf_counter()
        rate = float(sc["frame_rate_hz"])
        dt_frame = 1.0 / rate
        substeps = max(1, int(round(dt_frame / float(sc["sim_dt_s"]))))
        dt = dt_frame / substeps
        duration = float(sc["warmup_s"]) + fps * dt_frame
        max_range = max(lidar.reach_m if isinstance(lidar, Rig) else lidar.max_range for lidar in lidars)
        behind = float(tr["window_behind_m"]) + 50.0
        # the fastest anyone can go: the ego's factor or 1.3 (largest individual factor) plus the platoon boost,
        # in the fastest lane
        lane_max = max(lane_profile(tr["lane_speed_factors"], self.layout.lanes_per_direction))
        v_max = float(tr["speed_limit_mps"]) * lane_max * max(float(tr["ego_speed_factor"]),
                                                              1.3 * (1 + float(tr["platoon"]["follower_speed_boost"])))
        length = behind + v_max * duration + float(tr["window_ahead_m"]) + max_range + 200.0
        road = Road.random(self.layout, rng, -behind, length, float(rd["curve_fraction"]), tuple(rd["curve_radius_m"]),
                           tuple(rd["curve_length_m"]), tuple(rd["straight_length_m"]), float(rd["transition_m"]))
        traffic = Traffic(tr, self.layout, self.catalog, rng, first_track=1)
        probes = None
        if small_objects:  # a stream of its own: the traffic is the same with and without the probe
            probes = Probes.random(self.layout, np.random.default_rng(np.random.SeedSequence([self.seed, scene, 3])),
                                   0.0, road.s_end - 10.0)
        s_ego = 0.0
        for _ in range(int(round(float(sc["warmup_s"]) / dt))):
            s_ego += traffic.step(dt)
        self._add_time("traffic", time.perf_counter() - t0)
        x_lo, x_hi = (float(u) for u in out["region_x_m"])
        x_hi = max(x_hi, max_range + 10.0)
        y_max = float(out["region_abs_y_m"])
        keys = [[s.key() for s in lidar.sensors] if isinstance(lidar, Rig) else lidar.key() for lidar in lidars]
        for index in range(n_frames):
            if index > 0:
                t0 = time.perf_counter()
                for _ in range(substeps):
                    s_ego += traffic.step(dt)
                self._add_time("traffic", time.perf_counter() - t0)
            t0 = time.perf_counter()
            objects, meta = self._objects(road, traffic, s_ego, x_lo, x_hi, y_max, max_range, probes)
            self._add_time("transform", time.perf_counter() - t0)
            frames = []
            for lidar, lkey in zip(lidars, keys):
                if isinstance(lidar, Rig):
                    frames.append(self._rig_frame(lidar, lkey, objects, meta, scene, index, dt_frame, with_points))
                    continue
                key = _mix64(_seed64(self.seed), scene, index, lkey)
                res = cast_lidar(lidar, objects, key=key, with_points=with_points,
                                 bottom_lift=float(out["count_bottom_lift_m"]),
                                 ground_reflectivity=float(out["ground_reflectivity"]), timings=self.timings)
                frames.append(self._frame(scene, index, dt_frame, objects, meta, lidar.sensor, res.points,
                                          res.counts, res.point_box, res.rays_cast))
            yield frames

    def _frame(self, scene: int, index: int, dt_frame: float, objects, meta: dict, sensor, points, counts, point_box,
               rays_cast: int, **rig) -> SimFrame:
        m = meta["num_vehicles"]
        probe = {}
        if len(objects.boxes) > m:  # the probe's objects follow the vehicles in the box table
            probe = {"probe_boxes": objects.boxes[m:].copy(), "probe_kinds": meta["probe_kinds"].copy(),
                     "probe_places": meta["probe_places"].copy(), "probe_counts": counts[m:]}
            counts = counts[:m]
            point_box = np.where(point_box < m, point_box, -1)
        return SimFrame(
            frame_id=f"{scene:04d}_{index:03d}", scene_id=f"{scene:04d}", points=points,
            boxes=objects.boxes[:m].copy(), classes=meta["classes"].copy(), track_ids=meta["track_ids"].copy(),
            lanes=meta["lanes"].copy(), sensor=sensor, ego=dict(meta["ego"]),
            timestamp=index * dt_frame, hit_counts=counts, point_box=point_box,
            count_bottom_lift=float(self.config["output"]["count_bottom_lift_m"]), rays_cast=rays_cast, **rig,
            **probe)

    def _rig_frame(self, rig: Rig, keys: list[int], objects, meta: dict, scene: int, index: int, dt_frame: float,
                   with_points: bool) -> SimFrame:
        """One frame of a rig's merged returns (a single reference sensor without body: exactly its own frame)."""
        out = self.config["output"]
        keys = [_mix64(_seed64(self.seed), scene, index, k) for k in keys]
        lift, refl = float(out["count_bottom_lift_m"]), float(out["ground_reflectivity"])
        if rig.is_single_reference:
            res = cast_lidar(rig.sensors[0].lidar, objects, key=keys[0], with_points=with_points, bottom_lift=lift,
                             ground_reflectivity=refl, timings=self.timings)
            return self._frame(scene, index, dt_frame, objects, meta, rig.sensors[0].lidar.sensor, res.points,
                               res.counts, res.point_box, res.rays_cast, rig=rig.name,
                               sensor_index=np.zeros(len(res.points), np.int64),
                               self_hits=np.array([res.self_hits], np.int64))
        rc = cast_rig(rig, objects, keys, with_points=with_points, bottom_lift=lift, ground_reflectivity=refl,
                      timings=self.timings)
        return self._frame(scene, index, dt_frame, objects, meta, rig.sensors[0].lidar.sensor, rc.points, rc.counts,
                           rc.point_box, rc.rays_cast, rig=rig.name, sensor_index=rc.sensor_index,
                           self_hits=rc.self_hits)

    def _add_time(self, name: str, dt: float) -> None:
        self.timings[name] = self.timings.get(name, 0.0) + dt

    # ------------------------------------------------------------------ geometry
    def _objects(self, road: Road, traffic: Traffic, s_ego: float, x_lo: float, x_hi: float, y_max: float,
                 max_range: float, probes: Probes | None = None):
        """SceneObjects (vehicles, barriers, ego) in the ego ground frame, plus frame metadata."""
        layout = self.layout
        own, opp = traffic.own, traffic.opp
        # ego pose: centre on the road, the LiDAR at its front
        d_own, chg_own, dw_own, span_own = own.lateral_offset(layout)
        d_opp, chg_opp, dw_opp, span_opp = opp.lateral_offset(layout)
        yaw_own = np.arctan2(span_own * dw_own / traffic.lc_duration, np.maximum(own.v, 1.0)) * chg_own
        yaw_opp = -np.arctan2(span_opp * dw_opp / traffic.lc_duration, np.maximum(opp.v, 1.0)) * chg_opp
        s_all = np.concatenate([s_ego + own.x, s_ego + opp.x])
        d_all = np.concatenate([d_own, d_opp])
        X, Y, TH = road.to_world(s_all, d_all)
        head = TH + np.concatenate([yaw_own, yaw_opp + math.pi])
        ego_len = own.shapes[0].length
        ex, ey, eh = X[0], Y[0], head[0]
        ox = ex + 0.5 * ego_len * math.cos(eh)
        oy = ey + 0.5 * ego_len * math.sin(eh)
        c, s = math.cos(eh), math.sin(eh)
        lx = c * (X - ox) + s * (Y - oy)
        ly = -s * (X - ox) + c * (Y - oy)
        lh = wrap_angle(head - eh)
        sel = (lx >= x_lo) & (lx <= x_hi) & (np.abs(ly) <= y_max)
        sel[0] = False  # the ego is not a box of its own frame
        idx = np.flatnonzero(sel)
        shapes = own.shapes + opp.shapes
        # a changing vehicle belongs to the lane it is nearer to
        own_lane_now = np.where((own.lane_from >= 0) & (own.lc_prog < 0.5), own.lane_from, own.lane)
        ego_lane = int(own_lane_now[0])
        lanes_rel = np.concatenate([ego_lane - own_lane_now, np.full(opp.n, LANE_OPPOSITE, np.int64)])
        tracks = np.concatenate([own.track, opp.track])
        poses, labels, parts, kinds, refl, bidx = [], [], [], [], [], []
        for m, i in enumerate(idx):
            shp = shapes[i]
            poses.append((lx[i], ly[i], lh[i]))
            labels.append((0.0, 0.0, shp.height / 2, shp.length / 2, shp.width / 2, shp.height / 2))
            parts.append(shp.parts)
            kinds.append(KIND_VEHICLE)
            refl.append(shp.reflectivity)
            bidx.append(m)
        probe_kinds, probe_places = np.zeros(0, dtype="<U5"), np.zeros(0, dtype="<U11")
        if probes is not None:  # counted like vehicles, in box rows after them
            ppose, pidx = probes.in_frame(road, ox, oy, eh, x_lo, x_hi, y_max)
            for j, (pose, i) in enumerate(zip(ppose, pidx)):
                kind = PROBE_KINDS[probes.kind[i]]
                pp = probe_parts(kind)
                lb = label_box_local(pp, 0.0)
                poses.append(tuple(pose))
                labels.append((lb[0], lb[1], lb[2], lb[3] / 2, lb[4] / 2, lb[5] / 2))
                parts.append(pp)
                kinds.append(KIND_VEHICLE)
                refl.append(PROBE_REFLECTIVITY)
                bidx.append(len(idx) + j)
            probe_kinds = np.array([PROBE_KINDS[k] for k in probes.kind[pidx]], dtype="<U5")
            probe_places = np.array([PROBE_PLACES[k] for k in probes.place[pidx]], dtype="<U11")
        # barriers within the LiDAR's reach
        rb = self.config["road"]["barriers"]
        offsets_h_w = []
        if rb["median"]["enabled"] and rb["median"]["height_m"] > 0:
            offsets_h_w.append(([0.0], rb["median"]["height_m"], rb["median"]["width_m"]))
        if rb["outer"]["enabled"] and rb["outer"]["height_m"] > 0:
            e = layout.edge_offset + float(rb["outer"]["offset_m"]) + 0.5 * float(rb["outer"]["width_m"])
            offsets_h_w.append(([-e, e], rb["outer"]["height_m"], rb["outer"]["width_m"]))
        s_lidar = s_ego + 0.5 * ego_len
        for offs, h, w in offsets_h_w:
            seg = road.barrier_segments(s_lidar - 30.0, s_lidar + max_range + 30.0, offs, float(h), float(w),
                                        float(rb["segment_length_m"]))
            for b in seg:
                bx = c * (b[0] - ox) + s * (b[1] - oy)
                by = -s * (b[0] - ox) + c * (b[1] - oy)
                poses.append((bx, by, b[6] - eh))
                labels.append((0.0, 0.0, b[2], b[3] / 2, b[4] / 2, b[5] / 2))
                parts.append(np.array([[0.0, 0.0, b[2], b[3] / 2, b[4] / 2, b[5] / 2]]))
                kinds.append(KIND_OCCLUDER)
                refl.append(0.5)
                bidx.append(-1)
        # the ego's body, behind the LiDAR: blocks rays, gives no points
        eg = own.shapes[0]
        poses.append((-0.5 * eg.length - 0.01, 0.0, 0.0))
        labels.append((0.0, 0.0, eg.height / 2, eg.length / 2, eg.width / 2, eg.height / 2))
        parts.append(np.array([[0.0, 0.0, eg.height / 2, eg.length / 2, eg.width / 2, eg.height / 2]]))
        kinds.append(KIND_EGO)
        refl.append(0.0)
        bidx.append(-1)
        objects = pack_scene(poses, labels, parts, kinds, refl, bidx)
        _, _, _, kappa = road.centre(np.array([s_ego]))
        meta = {
            "classes": np.array([shapes[i].cls for i in idx], dtype=str) if idx.size else np.zeros(0, dtype="<U5"),
            "track_ids": tracks[idx].astype(np.int64),
            "lanes": lanes_rel[idx].astype(np.int64),
            "ego": {"speed_mps": float(own.v[0]), "lane_index": ego_lane,
                    "lanes_per_direction": int(layout.lanes_per_direction), "s_m": float(s_lidar),
                    "road_curvature_1pm": float(kappa[0]), "type": traffic.ego_type,
                    "length_m": float(eg.length), "width_m": float(eg.width), "height_m": float(eg.height)},
            "num_vehicles": int(idx.size), "probe_kinds": probe_kinds, "probe_places": probe_places,
        }
        return objects, meta


__all__ = ["HighwaySimulator", "SimFrame", "load_sim_config", "check_sim_config", "sim_presets"]
