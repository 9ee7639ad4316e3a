"""A study whose driver died: `--fresh` never deletes a run folder a surviving training still writes."""
import subprocess
import sys
import time

from tests.faults.faultkit import ROOT, snapshot

# holds the folder lock of argv[1] as a training run does, creates argv[2], then sleeps
HOLD_RUN_LOCK = ("import sys, time\nfrom detbench.utils.folder_locks import acquire_folder_lock\n"
                 "lock = acquire_folder_lock(sys.argv[1], 'a training run')\nopen(sys.argv[2], 'w').close()\n"
                 "time.sleep(120)\n")


def hold_lock(folder, flag):
    proc = subprocess.Popen([sys.executable, "-c", HOLD_RUN_LOCK, str(folder), str(flag)], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not flag.exists():
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() - t0 < 60
        time.sleep(0.05)
    return proc


def test_fresh_refuses_a_study_whose_training_still_runs(fault_data, tmp_path, tool):
    """A training of the study still holds its run folder (its study driver was killed): `study --fresh` is
    refused in one line naming the run folder and the training's pid, and deletes nothing; once the training
    has ended, --fresh empties the study."""
    from detbench.train.run_layout import STUDY_FOLDER

    study = tmp_path / "study"
    run = study / "second_h1.8"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "epoch_001.pt").write_bytes(b"x")
    (study / "ability").mkdir()
    (study / "study.json").write_text("{}")
    proc = hold_lock(run, tmp_path / "held")
    try:
        before = snapshot(study)
        code, err = tool("study", "--preset", "smoke", "--models", "second", "--heights", "1.8", "--data",
                         fault_data, "--out", study, "--no-progress", "--fresh")
        assert code == 2, err
        assert f"{run}: in use by a training run pid {proc.pid} on host " in err and "Traceback" not in err
        assert "--fresh would delete it under that process: stop it (or wait for it to end)" in err
        after = snapshot(study)
        after.pop(".detbench-owner.json", None)  # the study's claim marks its folder as a study's
        assert after == before
    finally:
        proc.kill()
        proc.communicate()
    from detbench.utils.folder_locks import clear_folder

    removed = clear_folder(study, STUDY_FOLDER, flag="--fresh")
    assert sorted(p.rsplit("/", 1)[-1] for p in removed) == ["ability", "second_h1.8", "study.json"]
    assert [p.name for p in study.iterdir()] == [".detbench-owner.json"]
