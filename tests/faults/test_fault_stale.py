"""Results that go stale without a word: a resume on data re-simulated in place, a study rerun with other
data, settings or heights on the same folder, and dataset metadata that misreads the points (the frame they
are in, their dtype, their byte order). Each is refused or recomputed with the reason named."""
import shutil

import numpy as np
import pytest

from tests.faults.faultkit import snapshot, train_argv


def test_resume_compares_the_datas_content_not_its_path(trained_run, data_copy, tool, tmp_path):
    """The same frames at another path resume; frames re-simulated into the same folder are refused before
    the run changes, naming the data, not the config."""
    from detbench.sim.dataset import simulate_dataset

    run = shutil.copytree(trained_run, tmp_path / "run")
    code, err = tool("train", *train_argv(data_copy, run, "--resume"))
    assert code == 0 and "already complete" in err, err[-3000:]
    simulate_dataset(data_copy, frames=12, heights=[0.5, 1.8], seed=1, frames_per_scene=4, overwrite=True,
                     progress=False)
    before = snapshot(run)
    code, err = tool("train", *train_argv(data_copy, run, "--resume"))
    assert code == 2 and f"the training frames at {data_copy} are not the ones this run was trained on" in err
    assert "re-simulated or edited in place" in err and "another config" not in err and "Traceback" not in err
    assert snapshot(run) == before


def _edit_info(root, key, **values):
    import json

    info = json.loads((root / "dataset.json").read_text())
    info["heights"][key].update(values)
    (root / "dataset.json").write_text(json.dumps(info, indent=2))


def test_points_frame_that_contradicts_the_road_is_named(data_copy, tool):
    """Ground-frame points declared `points_frame: sensor` are raised by the height once more on load; validation
    finds the road off z = 0 in the declared frame and names the setting and its fix."""
    _edit_info(data_copy, "1.8", points_frame="sensor")
    before = snapshot(data_copy)
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{data_copy / 'dataset.json'}: heights.1.8.points_frame is 'sensor', but the points are " \
                         f"in the ground frame" in err
    assert "set heights.1.8.points_frame to 'ground'" in err and "1 problem(s)" in err
    code, err = tool("analyze", "--data", data_copy, "--out", data_copy.parent / "a", "--no-figures",
                     "--no-progress")
    assert code == 2 and "heights.1.8.points_frame is 'sensor', but the points are in the ground frame" in err
    assert not (data_copy.parent / "a").exists() and snapshot(data_copy) == before


@pytest.mark.parametrize("dtype, named", [("<f8", "float64"), (">f4", "big-endian float32")])
def test_bin_points_of_another_dtype_are_named_and_the_fix_keeps_the_values(dtype, named, data_copy, tool):
    """`.bin` points saved as float64 or big-endian are named as such (not as NaN points to drop), by validation
    and by every reader, and the conversion the message gives restores the very points."""
    folder = data_copy / "points" / "1.8"
    originals = {}
    for f in sorted(folder.glob("*.npy")):
        originals[f.stem] = np.load(f)
        originals[f.stem].astype("<f4").tofile(f.with_suffix(".bin"))
        f.unlink()
    _edit_info(data_copy, "1.8", points_ext=".bin")
    bad = folder / "0001_002.bin"
    originals["0001_002"].astype(dtype).tofile(bad)
    before = snapshot(data_copy)
    code, err = tool("validate", data_copy)
    assert code == 1 and f"{bad}: the bytes are {named} values" in err and "1 problem(s)" in err, err
    assert "drop them" not in err
    fix = next(ln for ln in err.splitlines() if str(bad) in ln).split(" with ", 1)[1]
    code, err = tool("analyze", "--data", data_copy, "--out", data_copy.parent / "a", "--no-figures",
                     "--no-progress")
    assert code == 2 and f"{bad}: the bytes are {named} values" in err
    assert snapshot(data_copy) == before
    exec(fix, {"np": np})
    code, err = tool("validate", data_copy)
    assert code == 0, err
    np.testing.assert_array_equal(np.fromfile(bad, "<f4").reshape(-1, 4), originals["0001_002"])


@pytest.mark.slow  # about a minute on 2 cores: four smoke studies
def test_study_rerun_with_other_inputs_does_not_report_the_old_figures(fault_data, data_copy, tool, tmp_path):
    """A finished study rerun on the same --out: with other data or other settings its training run is refused,
    naming the run and what changed, before anything runs or changes; with an added height the ability study
    (and so the headline) is computed again with it, and the unchanged run is kept."""
    from detbench.sim.dataset import simulate_dataset

    out = tmp_path / "study"

    def study(data, *extra):
        return tool("study", "--preset", "smoke", "--models", "second", "--data", data, "--out", out,
                    "--no-progress", "--set", "train.tensorboard=false", "--set", "train.epochs=1", *extra)

    code, log = study(fault_data, "--heights", "1.8")
    assert code == 0, log[-3000:]
    simulate_dataset(data_copy, frames=12, heights=[0.5, 1.8], seed=1, frames_per_scene=4, overwrite=True,
                     progress=False)
    before = snapshot(out)
    code, err = study(data_copy, "--heights", "1.8")
    assert code == 2 and f"the training run {out / 'second_h1.8'} (data_fingerprint: then " in err, err[-3000:]
    assert "run this study with another --out" in err and "Traceback" not in err
    code, err = study(fault_data, "--heights", "1.8", "--set", "train.epochs=2")
    assert code == 2 and f"the training run {out / 'second_h1.8'} (config train.epochs: 1 then, 2 now)" in err
    assert snapshot(out) == before
    code, log = study(fault_data, "--heights", "0.5", "1.8")
    assert code == 0, log[-3000:]
    assert "ability.json was computed from other inputs (" in log and "heights: then [1.8], now [0.5, 1.8]" in log
    assert "start train second 1.8 m" not in log and "start train second 0.5 m" in log
    ability = __import__("json").loads((out / "ability" / "ability.json").read_text())
    assert "0.5" in str(ability["heights"]) and "0.5 m" in (out / "study.md").read_text().split("## 1.")[0]
