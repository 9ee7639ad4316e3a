"""The small-object probe: objects on the road, counted apart from the vehicles, the traffic left unchanged."""
import numpy as np

from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config
from detbench.sim.probes import PROBE_KINDS, probe_parts
from detbench.sim.vehicles import label_box_local


def test_probe_shapes():
    sizes = {k: label_box_local(probe_parts(k))[3:6] for k in PROBE_KINDS}
    assert np.allclose(sizes["cone"], [0.3, 0.3, 0.7]) and np.isclose(sizes["child"][2], 1.2)
    assert sizes["tyre"][2] < 0.3 and sizes["tyre"][0] > 0.6


def test_probe_frames_keep_vehicles_and_count_probes_apart():
    lidar = lidar_preset(0.5)
    cfg = load_sim_config()
    plain = list(HighwaySimulator(cfg, 3).run(6, [lidar], frames_per_scene=3))
    probed = list(HighwaySimulator(cfg, 3).run(6, [lidar], frames_per_scene=3, small_objects=True))
    seen = 0
    for (a,), (b,) in zip(plain, probed):
        assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.track_ids, b.track_ids)
        assert len(b.probe_boxes) == len(b.probe_kinds) == len(b.probe_counts) == len(b.probe_places)
        assert set(b.probe_kinds) <= set(PROBE_KINDS) and set(b.probe_places) <= {"carriageway", "shoulder"}
        # vehicle counts stay per vehicle: the points of a probe are no vehicle's
        assert np.array_equal(np.bincount(b.point_box[b.point_box >= 0], minlength=len(b.boxes)), b.hit_counts)
        assert b.points.tobytes() != a.points.tobytes() or not b.probe_counts.any()
        seen += int((b.probe_counts > 0).sum())
        # objects lie on the ego's carriageway or its shoulder: the right of the road's centre line
        assert len(b.probe_boxes) == 0 or np.all(np.abs(b.probe_boxes[:, 2] - b.probe_boxes[:, 5] / 2) < 1e-5)
    assert seen > 0
    assert len(plain[0][0].probe_boxes) == 0
