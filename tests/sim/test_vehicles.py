"""detbench.sim.vehicles: CARLA's blueprints (calibration v3's vehicles) and their label boxes and bodies."""
from collections import Counter

import numpy as np
import pytest

from detbench.config import ConfigError
from detbench.sim import HighwaySimulator, LidarConfig, load_sim_config
from detbench.sim.vehicles import Blueprint, VehicleCatalog


def _catalog(preset="paper", overrides=()):
    return VehicleCatalog(load_sim_config(preset, list(overrides))["vehicles"])


def test_the_catalogue_is_carlas_four_wheel_blueprints():
    cat = _catalog()
    assert cat.draw == "blueprints" and len(cat.names) == 33
    classes = Counter(cat.types[n].cls for n in cat.names)
    assert classes == {"car": 21, "suv": 5, "van": 4, "truck": 2, "bus": 1}  # 64 / 15 / 12 / 6 / 3 %
    # CARLA's bounding boxes (carla-facts: model3 4.8, a2 3.7 x 1.8 x 1.5, impala 5.4 x 2.0 x 1.4, patrol_2021
    # 5.6 x 2.15 x 2.05, sprinter 5.9 x 2.0 x 2.6, firetruck 8.5 x 2.9 x 3.8, fusorosa 10.3 x 3.9 x 4.25)
    size = {n: (cat.types[n].length, cat.types[n].width, cat.types[n].height) for n in cat.names}
    for name, want in (("vehicle.tesla.model3", (4.79, 2.16, 1.49)), ("vehicle.audi.a2", (3.7, 1.79, 1.55)),
                       ("vehicle.chevrolet.impala", (5.36, 2.03, 1.41)),
                       ("vehicle.nissan.patrol_2021", (5.57, 2.15, 2.05)),
                       ("vehicle.mercedes.sprinter", (5.92, 1.99, 2.56)),
                       ("vehicle.carlamotors.firetruck", (8.47, 2.89, 3.83)),
                       ("vehicle.mitsubishi.fusorosa", (10.27, 3.94, 4.25))):
        np.testing.assert_allclose(size[name], want, atol=0.006, err_msg=name)
    assert not any("bike" in n or "century" in n or "omafiets" in n or "ninja" in n or "yzf" in n
                   or "vespa" in n or "low_rider" in n for n in cat.names)  # no two-wheelers
    # the width and height a LiDAR sees on a vehicle's rear tell its blueprint, and with it its length
    assert len({(w, h) for _, w, h in size.values()}) == 33


def test_every_blueprint_is_labelled_with_its_box_and_its_body_lies_inside():
    cat = _catalog()
    m = cat.label_margin
    rng = np.random.default_rng(3)
    for name in cat.names:
        bp = cat.types[name]
        assert isinstance(bp, Blueprint)
        for _ in range(3):
            shp = cat.sample(rng, name)
            # the label box is the blueprint's box, the same for every instance
            assert (shp.cls, shp.name, shp.length, shp.width, shp.height) == (bp.cls, name, bp.length, bp.width,
                                                                               bp.height)
            lo = (shp.parts[:, :3] - shp.parts[:, 3:]).min(axis=0)
            hi = (shp.parts[:, :3] + shp.parts[:, 3:]).max(axis=0)
            # the body spans the box shrunk by the margin (length, top), from the road, as wide as the body
            assert lo[2] == pytest.approx(0.0, abs=1e-12)
            np.testing.assert_allclose([-lo[0], hi[0]], [bp.length / 2 - m] * 2, atol=1e-9)
            np.testing.assert_allclose([-lo[1], hi[1]], [min(bp.body_width, bp.width - 2 * m) / 2] * 2, atol=1e-9)
            assert hi[2] == pytest.approx(bp.height - m, abs=1e-9)
    bus = cat.types["vehicle.mitsubishi.fusorosa"]
    assert bus.width == pytest.approx(3.944) and bus.body_width == 2.55  # the box holds the mirrors, the body not


def test_vehicles_are_blueprints_drawn_uniformly_each_with_its_one_size():
    cat = _catalog()
    deck = cat.deck(np.random.default_rng(0))
    draws = [deck.draw() for _ in range(33 * 20)]
    for k in range(0, len(draws), 33):  # every deck holds every blueprint once, shuffled
        assert sorted(draws[k:k + 33]) == sorted(cat.names)
    assert draws[:33] != draws[33:66]
    # the simulator's boxes are the blueprints' boxes, and the classes theirs
    sizes = {(round(bp.length, 3), round(bp.width, 3), round(bp.height, 3)): bp.cls for bp in cat.types.values()}
    lid = [LidarConfig(height=1.0, channels=4, h_samples=16)]
    seen = Counter()
    for step in HighwaySimulator(load_sim_config(), 1).run(6, lid, frames_per_scene=2, with_points=False):
        f = step[0]
        for box, cls in zip(f.boxes, f.classes):
            key = tuple(round(float(v), 3) for v in box[3:6])
            assert sizes.get(key) == cls, (key, cls)
            seen[key] += 1
    assert len(seen) >= 15  # many blueprints, each with exactly its size
    # without the deck every vehicle is an independent uniform draw (generate_traffic.py's random.choice)
    free = _catalog(overrides=["vehicles.blueprint_deck=false"])
    assert free.deck(np.random.default_rng(0)) is None
    rng = np.random.default_rng(0)
    counts = Counter(free.types[free.sample_type(rng)].cls for _ in range(6600))
    for cls, n in (("car", 21), ("suv", 5), ("van", 4), ("truck", 2), ("bus", 1)):
        assert abs(counts[cls] / 6600 - n / 33) < 0.02, cls


def test_the_ego_is_a_car_blueprint_or_the_one_named():
    from detbench.sim.traffic import Traffic

    cfg = load_sim_config()
    layout = HighwaySimulator(cfg, 0).layout
    cat = VehicleCatalog(cfg["vehicles"])
    cars = {n for n in cat.names if cat.types[n].cls == "car"}
    egos = set()
    for seed in range(12):
        tr = Traffic(cfg["traffic"], layout, cat, np.random.default_rng(seed))
        ego = tr.own.shapes[0]
        assert ego.cls == "car" and ego.name in cars
        egos.add(ego.name)
    assert len(egos) >= 5
    cfg = load_sim_config("paper", ["traffic.ego_type=vehicle.tesla.model3"])
    tr = Traffic(cfg["traffic"], layout, VehicleCatalog(cfg["vehicles"]), np.random.default_rng(0))
    assert tr.own.shapes[0].name == "vehicle.tesla.model3" and tr.own.shapes[0].length == pytest.approx(4.792)
    with pytest.raises(ConfigError, match="ego_type 'lorry'.*configs/sim.yaml"):
        load_sim_config("paper", ["traffic.ego_type=lorry"])


def test_spawn_classes_filter_the_blueprints():
    cat = _catalog("cars-only")
    assert {cat.types[n].cls for n in cat.names} == {"car", "suv"} and len(cat.names) == 26
    lid = [LidarConfig(height=1.0, channels=4, h_samples=16)]
    step = next(HighwaySimulator(load_sim_config("cars-only"), 0).run(1, lid, with_points=False))
    assert set(step[0].classes.tolist()) <= {"car", "suv"}


@pytest.mark.parametrize("override, message", [
    ("vehicles.draw=catalogue", "vehicles.draw must be one of blueprints, types"),
    ("vehicles.spawn_classes=[car, lorry]", "spawn_classes names class.*lorry"),
    ("vehicles.spawn_classes=[]", "spawn_classes must be a non-empty list"),
    ("vehicles.blueprints=[[vehicle.x, car, sedan, 4.0, 1.8]]", r"blueprints\[0\] must be .*configs/sim.yaml"),
    ("vehicles.blueprints=[[vehicle.x, car, boat, 4.0, 1.8, 1.5]]", "unknown shape 'boat'"),
    ("vehicles.blueprints=[[vehicle.x, bus, bus, 10.0, 2.5, 3.5, 2.6]]", "body width 2.6 m exceeds the box width"),
    ("vehicles.blueprints=[[vehicle.x, car, sedan, 4, 1.8, 1.5], [vehicle.x, car, sedan, 4, 1.8, 1.5]]",
     "listed twice"),
    ("vehicles.blueprint_deck=2", "blueprint_deck must be true or false"),
])
def test_bad_blueprint_config_is_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError, match=message):
        load_sim_config("paper", [override])
