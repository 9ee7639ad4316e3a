"""Highway LiDAR simulator: roads, traffic, vehicle shapes and a numba ray caster.

Public API::

    from detbench.sim import HighwaySimulator, LidarConfig, lidar_preset, load_sim_config

    cfg = load_sim_config("paper", overrides=["traffic.density_per_km_lane=20"])
    lidars = [lidar_preset(h) for h in (0.5, 1.0, 1.8)]     # Table II sensors
    sim = HighwaySimulator(cfg, seed=0)
    for frames in sim.run(400, lidars, frames_per_scene=200, with_points=True):
        ...  # frames: list[SimFrame], one per LiDAR, same traffic, same frame_id

`SimFrame` is a `detbench.data.Frame` (points, boxes, classes, track_ids, lanes, sensor, ego,
timestamp) with three extras filled by the ray caster:

- `hit_counts` (M,) int64: for each box, the number of points inside it with the box
  bottom raised by `count_bottom_lift` metres (config `output.count_bottom_lift_m`,
  0.05 in configs/sim.yaml, i.e. `detbench.data.regions.DETECTED_BOTTOM_LIFT`, the paper's
  LiDAR-detected rule). It is computed on the final float32 points and float32 boxes with
  the same test as `detbench.data.regions.detected_point_counts(points, boxes)`, so the two agree
  exactly (tests/studies/test_ability.py::test_simulator_counts_match_points_in_boxes proves it on
  simulated frames).
- `point_box` (N,) int64: the box containing each point under that rule, or -1.
- `rays_cast`: rays traced for the frame.

Streaming the detection-ability study: call `run(..., with_points=False)`. The simulator
then traces only the rays of azimuth columns that hold a vehicle (the others cannot change
a count), returns `points` empty with shape (0, 4), and fills `hit_counts` with exactly the
values a run with points gives. A vehicle is LiDAR-detected when `hit_counts >= 1`; other
minimum-point thresholds are `hit_counts >= k`.

Frames carry every vehicle whose centre lies in the ego-frame region
`output.region_x_m` x `|y| <= output.region_abs_y_m` (default x in [-20, 170] m, |y| <= 25 m,
the x limit grows with the longest LiDAR range), both carriageways; lanes are relative to
the ego (0, +1 left, -1 right, ...; `LANE_OPPOSITE` for the other carriageway).
The `ego` dict holds speed_mps, lane_index (0 = the inner lane next to the median),
lanes_per_direction, s_m (arc length of the LiDAR along the road), road_curvature_1pm,
type and its length_m/width_m/height_m.

Hand-made scenes for tests and experiments: `detbench.sim.scene_objects.make_scene` builds a
scene from explicit vehicles (parts), occluders and an ego body; `cast_lidar` casts one
LiDAR on it. `detbench.sim.vehicles.build_parts` makes the parts of a shape.

Datasets on disk (`detbench.sim.dataset`): `simulate_dataset` writes one in the detbench
layout; `default_dataset(data_cfg)` is the cached simulated dataset every command uses
without `--data`.
"""
from detbench.sim.lidar import PRESETS as LIDAR_PRESETS, LidarConfig, lidar_preset
from detbench.sim.raycast import CastResult, cast_lidar
from detbench.sim.scene_objects import SceneObjects, make_scene
from detbench.sim.simulator import HighwaySimulator, SimFrame, check_sim_config, load_sim_config, sim_presets
from detbench.sim.vehicles import VehicleCatalog, build_parts
from detbench.sim.dataset import default_dataset, simulate_dataset

__all__ = [
    "HighwaySimulator", "SimFrame", "LidarConfig", "lidar_preset", "LIDAR_PRESETS", "load_sim_config",
    "check_sim_config", "sim_presets", "cast_lidar", "make_scene", "SceneObjects", "CastResult",
    "VehicleCatalog", "build_parts", "default_dataset", "simulate_dataset",
]
