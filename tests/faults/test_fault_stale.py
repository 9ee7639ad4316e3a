"""Results that go stale without a word: a resume on data re-simulated in place, a study rerun with other
data, settings or heights on the same folder, and dataset metadata that misreads the points (the frame they
are in, their dtype, their byte order). Each is refused or recomputed with the reason named."""
import shutil

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

