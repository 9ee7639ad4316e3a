"""The split check: a split's all-vehicles cells against a reference ability report."""
import numpy as np
import pytest

from detbench.data.frame import Frame, Sensor
from detbench.studies.ability import AbilityStudy
from detbench.studies.split_check import compare_splits, split_check_markdown, split_check_warnings, split_figures


def _report(vehicles_per_scene: list[int], seen_per_scene: list[int], frames_per_scene: int = 2) -> dict:
    """An AbilityStudy report of scenes whose frames each hold `vehicles` cars 20 m ahead in the ego lane, of
    which the first `seen` have a point (hit counts given)."""
    study = AbilityStudy(bootstrap=200, keep_example=False)
    for s, (n, seen) in enumerate(zip(vehicles_per_scene, seen_per_scene)):
        boxes = np.array([[20.0 + 8 * i, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0] for i in range(n)], np.float32).reshape(-1, 7)
        counts = np.array([5 if i < seen else 0 for i in range(n)], np.int64)
        for k in range(frames_per_scene):
            f = Frame(frame_id=f"{s:04d}_{k:03d}", scene_id=f"{s:04d}", points=np.zeros((0, 4), np.float32),
                      boxes=boxes, classes=np.array(["car"] * n), track_ids=np.arange(n, dtype=np.int64),
                      lanes=np.zeros(n, np.int64), sensor=Sensor(height=1.8))
            study.add(f, counts=counts)
    return study.report()


def test_a_split_like_the_reference_is_inside_and_unresolved():
    ref = _report([3, 4, 3, 4, 3, 4, 3, 4], [2, 3, 2, 3, 2, 3, 2, 3])
    split = _report([3, 4, 4, 3], [2, 3, 3, 2])
    res = compare_splits(split, ref)
    small = {c["metric"]: c for c in res["cells"] if c["range"] == "small"}
    assert small["vehicles_per_frame"]["value"] == pytest.approx(3.5)
    assert small["vehicles_per_frame"]["reference"] == pytest.approx(3.5)
    assert small["ldr"]["value"] == pytest.approx(5 / 7)
    assert small["vehicles_per_frame"]["inside"] and small["ldr"]["inside"]
    assert res["resolved"] == 0 and not split_check_warnings(res, "test split", "ability study")


def test_a_split_of_light_traffic_is_outside_and_resolved():
    ref = _report([3, 4, 3, 4, 3, 4, 3, 4], [2, 3, 2, 3, 2, 3, 2, 3])
    split = _report([1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1])  # light traffic the LiDAR always sees
    res = compare_splits(split, ref)
    small = {c["metric"]: c for c in res["cells"] if c["range"] == "small"}
    assert small["vehicles_per_frame"]["inside"] is False and small["vehicles_per_frame"]["resolved"] is True
    assert small["ldr"]["value"] == pytest.approx(1.0) and small["ldr"]["inside"] is False
    assert small["ldr"]["diff"] == pytest.approx(1.0 - 5 / 7)
    warnings = split_check_warnings(res, "test split", "ability study")
    assert any("vehicles per frame at 1.8 m, small range" in w for w in warnings)
    md = "\n".join(split_check_markdown(res, "test split", "ability study"))
    assert "(outside)" in md and f"{res['outside']} of {res['judged']} cells" in md


def test_split_figures_reads_the_bootstrap_intervals():
    rep = _report([3, 4, 3, 4], [2, 3, 2, 3])
    fig = split_figures(rep)["1.8"]["small"]
    vpf, vpf_ci = fig["vehicles_per_frame"]
    assert vpf == pytest.approx(3.5) and vpf_ci[0] <= 3.5 <= vpf_ci[1] and vpf_ci[0] >= 3.0 and vpf_ci[1] <= 4.0
    ldr, ldr_ci = fig["ldr"]
    assert ldr_ci[0] <= ldr <= ldr_ci[1]
