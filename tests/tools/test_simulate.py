"""tools/simulate.py and tools/bench_sim.py (small runs), and the frame planning behind --frames / --scenes."""
import json

import numpy as np
import pytest

from detbench.sim.dataset import plan_frames
import tools.analyze
import tools.bench_sim
import tools.simulate


def test_plan_frames():
    assert plan_frames(10, None, None, 200) == (10, 200)
    assert plan_frames(None, 3, 5, 200) == (15, 5)
    assert plan_frames(100, 4, None, 200) == (100, 25)
    with pytest.raises(ValueError, match="--frames"):
        plan_frames(None, None, None, 200)
    with pytest.raises(ValueError, match="does not fit"):
        plan_frames(100, 2, 10, 200)


def test_simulate_writes_a_readable_dataset(tmp_path):
    from detbench.data import Height3Dataset

    sim = tools.simulate
    out = tmp_path / "ds"
    assert sim.main(["--out", str(out), "--scenes", "3", "--frames-per-scene", "2", "--heights", "0.5", "1.8",
                     "--seed", "5", "--no-progress", "--set", "traffic.density_per_km_lane=14"]) == 0
    report = json.loads((out / "simulate_run.json").read_text())
    assert report["frames"] == 6 and set(report["heights"]) == {"0.5", "1.8"}
    assert (out / "simulate_run.md").is_file()
    ds = Height3Dataset(out, 1.8, split="all")
    assert len(ds) == 6
    f = ds[0]
    assert f.points.shape[1] == 4 and f.points.shape[0] > 1000
    assert abs(f.sensor.pitch_deg - 2.5) < 1e-9
    # the written frame equals a fresh simulation of the same seed
    from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config

    cfg = load_sim_config("paper", ["traffic.density_per_km_lane=14"])
    first = next(HighwaySimulator(cfg, 5).run(1, [lidar_preset(0.5), lidar_preset(1.8)], frames_per_scene=2))
    g = ds.load(first[1].frame_id)
    np.testing.assert_array_equal(g.points, first[1].points)
    np.testing.assert_allclose(g.boxes, first[1].boxes, atol=1e-3)


def test_frame_stride_writes_the_presets_frames(tmp_path):
    """--frame-stride K writes what the presets' data (detbench.sim.dataset.simulate_dataset, frame_stride K)
    write for the same seed: the same points, frames K native frames apart, the stride in dataset.json."""
    from detbench.sim.dataset import simulate_dataset

    out = tmp_path / "tool"
    assert tools.simulate.main(["--out", str(out), "--frames", "4", "--frames-per-scene", "2", "--frame-stride", "3",
                                "--heights", "1.8", "--seed", "2", "--no-progress"]) == 0
    ref = simulate_dataset(tmp_path / "ref", frames=4, heights=[1.8], seed=2, frames_per_scene=2, frame_stride=3,
                           progress=False)
    src = json.loads((out / "dataset.json").read_text())["source"]
    assert src["frame_stride"] == 3 and src["overrides"] == ["scene.frame_rate_hz=0.6666666666666666"]
    files = sorted(p.name for p in (ref / "points" / "1.8").iterdir())
    assert len(files) == 4 and files == sorted(p.name for p in (out / "points" / "1.8").iterdir())
    for name in files:
        np.testing.assert_array_equal(np.load(out / "points" / "1.8" / name), np.load(ref / "points" / "1.8" / name))
    plain = tmp_path / "plain"  # stride 1: other instants of the same scenes
    tools.simulate.main(["--out", str(plain), "--frames", "4", "--frames-per-scene", "2", "--heights", "1.8",
                         "--seed", "2", "--no-progress"])
    assert not np.array_equal(np.load(plain / "points" / "1.8" / files[1]), np.load(out / "points" / "1.8" / files[1]))
    with pytest.raises(SystemExit, match="--frame-stride 0"):
        tools.simulate.main(["--out", str(tmp_path / "x"), "--frames", "2", "--frame-stride", "0"])


def test_simulate_rejects_bad_input(tmp_path):
    sim = tools.simulate
    with pytest.raises(SystemExit, match="density_per_km_lane"):
        sim.main(["--out", str(tmp_path / "x"), "--frames", "2", "--set", "traffic.density_per_km_lan=3"])
    with pytest.raises(SystemExit, match="heights must differ"):
        sim.main(["--out", str(tmp_path / "x"), "--frames", "2", "--lidars", "arcfox-as-hi", "avatr-3"])


def test_bench_sim_small_run(tmp_path):
    bench = tools.bench_sim
    assert bench.main(["--frames", "3", "--frames-per-scene", "3", "--heights", "1.0", "--out", str(tmp_path),
                       "--no-progress"]) == 0
    rep = json.loads((tmp_path / "bench_sim.json").read_text())
    assert len(rep["runs"]) == 2 and rep["runs"][0]["frames_per_s"] > 0
    assert "cast" in rep["runs"][1]["stages_ms_per_frame"]
    assert (tmp_path / "bench_sim.md").read_text().startswith("# Simulator benchmark")


# the keys only the blueprint world reads (vehicles.draw: blueprints); a world of types (v1, v2) is pinned without them
BLUEPRINT_KEYS = ("draw", "blueprint_deck", "spawn_classes", "blueprints")


def _types_config_digest(preset: str) -> str:
    import hashlib

    from detbench.sim import load_sim_config

    cfg = load_sim_config(preset)
    assert cfg["vehicles"]["draw"] == "types"
    for k in BLUEPRINT_KEYS:
        del cfg["vehicles"][k]
    return hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()


def test_v1_preset_is_the_former_default_key_for_key():
    # `--sim-preset v1` must reproduce calibration v1's data: its config is pinned by the digest of calibration v1's
    # config, so an edit of the v1 preset or of a top-level key it inherits fails here
    from detbench.sim import load_sim_config

    cfg = load_sim_config("v1")
    digest = _types_config_digest("v1")
    assert digest.startswith("3e93451adc39f91c"), digest
    assert cfg != load_sim_config("paper")
    assert _sim_digest("v1").startswith("3dc243b60e0eb195")


def _sim_digest(preset: str) -> str:
    """A digest of what a small run of the preset gives: per frame and LiDAR the integer outputs (hit counts, points
    per frame, classes, track ids, lanes), which change with any change of traffic, shapes or the order of draws,
    and no floats, whose last bits may differ between machines."""
    import hashlib

    from detbench.sim import HighwaySimulator, lidar_preset, load_sim_config

    lidars = [lidar_preset(0.5, channels=16, h_samples=120), lidar_preset(1.8, channels=16, h_samples=120)]
    h = hashlib.sha256()
    for step in HighwaySimulator(load_sim_config(preset), 7).run(4, lidars, frames_per_scene=2):
        for f in step:
            h.update(np.asarray(f.hit_counts, np.int64).tobytes() + np.int64(len(f.points)).tobytes())
            h.update(np.asarray(f.track_ids, np.int64).tobytes() + np.asarray(f.lanes, np.int64).tobytes())
            h.update("|".join(f.classes.tolist()).encode())
    return h.hexdigest()


def test_v2_preset_is_calibration_v2_key_for_key_and_by_its_data():
    # `--sim-preset v2` must reproduce calibration v2's data (the world of per-class size distributions): its config
    # is pinned by the digest of calibration v2's config, and a small run by the digest of its integer outputs, so an
    # edit of a key it reads, or of the code path it runs (the order of the random draws included), fails here
    from detbench.sim import load_sim_config

    assert load_sim_config("v2")["calibration"] == "v2"
    digest = _types_config_digest("v2")
    assert digest.startswith("6ed740dc3434e10a"), digest
    assert _sim_digest("v2").startswith("4d8d4664aa3d1df9")


def test_a_calibration_label_with_a_note_reads_as_its_bare_id(tmp_path):
    # datasets written with the long form of the label ("v2" and a note in parentheses) read as "v2", in the
    # dataset.json source and in the config it holds; the bare ids pass unchanged
    from detbench.data import read_info
    from detbench.data.layout import calibration_id, sim_calibration
    from detbench.sim.dataset import simulate_dataset

    long_label = f"v2 (issue {16})"
    assert calibration_id(long_label) == "v2" and calibration_id("v2") == "v2" and calibration_id("v1") == "v1"
    assert sim_calibration({"calibration": long_label}) == "v2"
    assert sim_calibration({"config": {"calibration": long_label}}) == "v2"
    root = simulate_dataset(tmp_path / "ds", frames=2, heights=[1.0], seed=0, frames_per_scene=2, progress=False)
    info = json.loads((root / "dataset.json").read_text())
    assert info["source"]["calibration"] == "v3"
    info["source"]["calibration"] = info["source"]["config"]["calibration"] = long_label
    (root / "dataset.json").write_text(json.dumps(info))
    assert sim_calibration(read_info(root).source) == "v2"


def test_calibration_id_is_written_and_old_datasets_read_as_v1(tmp_path):
    from detbench.data import read_info
    from detbench.sim import load_sim_config
    from detbench.data.layout import PREVIOUS_CALIBRATION, sim_calibration
    from detbench.sim.dataset import simulate_dataset

    v3 = load_sim_config("paper")["calibration"]  # the default is v3; v2 and v1 are presets
    assert v3 == "v3" and load_sim_config("carla-tm") == load_sim_config("paper")
    assert load_sim_config("v1")["calibration"] == PREVIOUS_CALIBRATION == "v1"
    root = simulate_dataset(tmp_path / "ds", frames=4, heights=[1.0], seed=0, frames_per_scene=2, progress=False)
    info = read_info(root)
    assert info.source["calibration"] == v3 and sim_calibration(info.source) == v3
    assert info.source["config"]["traffic"]["platoon"]["ego_in_platoon"] is True
    assert info.source["config"]["vehicles"]["draw"] == "blueprints"
    v2 = simulate_dataset(tmp_path / "ds2", frames=2, heights=[1.0], seed=0, frames_per_scene=2, progress=False,
                          preset="v2")
    assert read_info(v2).source["calibration"] == "v2" and sim_calibration(read_info(v2).source) == "v2"
    assert read_info(v2).source["config"]["vehicles"]["draw"] == "types"
    v1 = simulate_dataset(tmp_path / "ds1", frames=2, heights=[1.0], seed=0, frames_per_scene=2, progress=False,
                          preset="v1")
    assert read_info(v1).source["calibration"] == "v1"
    assert read_info(v1).source["config"]["traffic"]["platoon"]["ego_in_platoon"] is False
    # a dataset.json written before the id existed (no `calibration`, a config without it) reads as v1
    old = json.loads((root / "dataset.json").read_text())
    del old["source"]["calibration"], old["source"]["config"]["calibration"]
    assert sim_calibration(old["source"]) == "v1" and sim_calibration({}) == "v1" and sim_calibration(None) == "v1"
    (root / "dataset.json").write_text(json.dumps(old))
    out = tmp_path / "ab"
    assert tools.analyze.main(["--data", str(root), "--split", "all", "--no-figures", "--no-progress",
                                      "--bootstrap", "0", "--out", str(out)]) == 0
    assert json.loads((out / "ability.json").read_text())["extras"]["source"]["calibration"] == "v1"


def test_run_lidars_default_to_the_papers_heights_and_refuse_a_shared_height():
    from detbench.sim.run import run_lidars

    assert [lid.height for lid in run_lidars()] == [0.5, 1.0, 1.8]
    noisy = run_lidars([1.8], range_noise=0.02, dropout=0.1)
    assert noisy[0].range_noise_m == 0.02 and noisy[0].dropout == 0.1
    with pytest.raises(ValueError, match="heights must differ"):
        run_lidars([1.8, "h3-1.8"])


def test_simulate_rigs_writes_rig_folders_and_sensor_indices(tmp_path):
    from detbench.data import Height3Dataset, read_info
    from detbench.data.layout import sensor_index_path
    from detbench.sim import HighwaySimulator, load_sim_config
    from detbench.sim.rigs import load_rigs

    out = tmp_path / "rigs"
    assert tools.simulate.main(["--out", str(out), "--scenes", "2", "--frames-per-scene", "2", "--rigs", "headlights",
                                "paper-1.8", "--seed", "4", "--no-progress"]) == 0
    info = read_info(out)
    assert list(info.heights) == ["headlights", "paper-1.8"]
    rig = info.heights["headlights"].rig
    assert [s["name"] for s in rig["sensors"]] == ["left", "right"] and rig["ego_body"] is True
    assert set(json.loads((out / "dataset.json").read_text())["source"]["rigs"]) == {"headlights", "paper-1.8"}
    ds = Height3Dataset(out, "headlights", split="all")
    assert len(ds) == 4 and ds.heights == ["headlights", "paper-1.8"]
    rigs = load_rigs()
    fresh = list(HighwaySimulator(load_sim_config(), 4).run(1, [rigs["headlights"]], frames_per_scene=2))[0][0]
    f = ds.load(fresh.frame_id)
    assert f.points.tobytes() == fresh.points.tobytes()
    index = np.load(sensor_index_path(out, "headlights", fresh.frame_id))
    assert np.array_equal(index, fresh.sensor_index) and set(np.unique(index)) == {0, 1}
    # the paper's rig under its name holds the single sensor's points
    assert Height3Dataset(out, "paper-1.8", split="all").load(fresh.frame_id).points.shape[1] == 4


def test_simulate_rigs_argument_errors(tmp_path):
    from detbench.utils.cli import UserError

    with pytest.raises(UserError, match="one of --heights, --lidars and --rigs"):
        tools.simulate.main(["--out", str(tmp_path / "a"), "--frames", "2", "--rigs", "plate", "--heights", "1.0"])
    with pytest.raises(UserError, match="known: paper-0.5"):
        tools.simulate.main(["--out", str(tmp_path / "b"), "--frames", "2", "--rigs", "bonnet"])
