"""Folders the tools do not own, and two processes on one folder: a tool deletes or writes into only a folder
it can prove it wrote (its owner file, or a layout it recognises entirely as its own), and a run or a study
locks its folder while it runs (a second one is refused naming the holder's pid and host; a lock left by a
kill -9 is taken over with a note)."""
import json
import os
import socket
import time

import pytest

from tests.faults.faultkit import kill_when_stalled, snapshot, stalling_trainer, train_argv


def _wait_stalled(proc, marker, timeout: float = 240) -> None:
    t0 = time.monotonic()
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() - t0 < timeout, "the trainer never reached its hook"
        time.sleep(0.05)


def _thesis(folder):
    folder.mkdir(parents=True)
    (folder / "chapter1.tex").write_text("three years of work")
    (folder / "figures").mkdir()
    (folder / "figures" / "fig1.pdf").write_bytes(b"%PDF-1.4 ...")
    return snapshot(folder)


def _study(tool, out, data, *extra):
    return tool("study", "--preset", "smoke", "--models", "second", "--heights", "1.8", "--data", data,
                "--out", out, "--no-progress", *extra)


def test_study_deletes_or_writes_into_only_a_study_folder(data_copy, tool, tmp_path):
    """--fresh on the user's own folder, or on the dataset itself, is refused naming the folder; without
    --fresh the study does not write into them either. A study folder holding a file of the user's, or a
    folder named like a run that is not one, is refused by --fresh too."""
    thesis = tmp_path / "thesis"
    before = _thesis(thesis)
    for extra in (["--fresh"], []):
        code, err = _study(tool, thesis, data_copy, *extra)
        assert code == 2, err
        assert f"error: --out {thesis}: the folder is not empty (chapter1.tex, figures)" in err
        assert "nothing in it shows that detbench wrote it as a study" in err and "choose an empty or new --out" in err
        assert snapshot(thesis) == before

    data_before = snapshot(data_copy)
    code, err = _study(tool, data_copy, data_copy, "--fresh")
    assert code == 2 and f"--out {data_copy}: holds a detbench dataset" in err and "not a study" in err
    assert snapshot(data_copy) == data_before

    study = tmp_path / "study"
    (study / "ability").mkdir(parents=True)
    (study / ".detbench-owner.json").write_text(json.dumps({"kind": "study"}))
    (study / "ability" / "ability.json").write_text("{}")
    (study / "my_h2").mkdir()  # named like a run (model my, height 2), but not one
    (study / "my_h2" / "notes.txt").write_text("mine")
    (study / "notes.txt").write_text("mine too")
    study_before = snapshot(study)
    code, err = _study(tool, study, data_copy, "--fresh")
    assert code == 2 and f"--out {study}: holds my_h2, notes.txt, which are not written by a study" in err
    assert snapshot(study) == study_before


def test_fresh_empties_a_study_folder_and_nothing_else(tmp_path):
    """What --fresh removes: a folder proven to be a study (owner file, or a finished study's study.json) holding
    only a study's entries, its runs proven to be runs; the folder itself and its owner file stay."""
    from detbench.train.run_layout import STUDY_FOLDER
    from detbench.utils.folder_locks import clear_folder
    from detbench.utils.folder_ownership import FolderNotReplaceable

    study = tmp_path / "study"
    (study / "second_h1.8" / "checkpoints").mkdir(parents=True)
    (study / "second_h1.8" / "checkpoints" / "epoch_001.pt").write_bytes(b"x")  # a run of before owner files
    (study / "ability").mkdir()
    (study / "study.json").write_text("{}")
    removed = clear_folder(study, STUDY_FOLDER, flag="--fresh")
    assert sorted(os.path.basename(p) for p in removed) == ["ability", "second_h1.8", "study.json"]
    assert study.is_dir() and not list(study.iterdir())

    (study / "ability").mkdir()  # no study.json and no owner file: names alone prove nothing
    with pytest.raises(FolderNotReplaceable, match="nothing in it shows that detbench wrote it as a study"):
        clear_folder(study, STUDY_FOLDER, flag="--fresh")
    assert (study / "ability").is_dir()


def test_simulate_overwrite_refuses_an_openpcdet_folder(tool, tmp_path):
    """An OpenPCDet custom folder (points/ labels/ ImageSets/, no dataset.json) is not an unfinished detbench
    dataset: --overwrite is refused and not suggested; an unfinished dataset the writer left is replaced."""
    opc = tmp_path / "opc"
    for sub in ("points", "labels", "ImageSets"):
        (opc / sub).mkdir(parents=True)
    (opc / "points" / "000000.bin").write_bytes(b"\0" * 64)
    (opc / "labels" / "000000.txt").write_text("1 2 3 4 5 6 0 Vehicle\n")
    (opc / "ImageSets" / "train.txt").write_text("000000\n")
    before = snapshot(opc)
    for extra in ([], ["--overwrite"]):
        code, err = tool("simulate", "--out", opc, "--frames", "2", "--heights", "1.8", "--no-progress", *extra)
        assert code == 2 and f"{opc}: the folder is not empty (ImageSets, labels, points)" in err, err
        assert "nothing in it shows that detbench wrote it as a dataset" in err and "pass --overwrite" not in err
        assert snapshot(opc) == before

    from detbench.data.writer import DatasetWriter

    unfinished = tmp_path / "unfinished"
    DatasetWriter(unfinished, [1.8], {}).open()  # a writer that never finished: its folders, no dataset.json
    code, err = tool("simulate", "--out", unfinished, "--frames", "2", "--heights", "1.8", "--no-progress")
    assert code == 2 and "pass --overwrite to replace it (an unfinished dataset)" in err
    code, err = tool("simulate", "--out", unfinished, "--frames", "2", "--frames-per-scene", "1", "--heights",
                     "1.8", "--no-progress", "--overwrite")
    assert code == 0, err
    assert (unfinished / "dataset.json").is_file()


def test_train_refuses_an_out_that_is_not_a_run(fault_data, tool, tmp_path):
    """--out a folder of the user's (its own config.yaml and history.json) is refused before anything is
    written; a refused start into a new folder leaves nothing behind."""
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "config.yaml").write_text("# the user's experiment config\nmodel:\n  name: second\n")
    (exp / "history.json").write_text('{"notes": "the user\'s own"}')
    before = snapshot(exp)
    code, err = tool("train", *train_argv(fault_data, exp))
    assert code == 2, err
    assert f"error: --out {exp}: the folder is not empty (config.yaml, history.json)" in err
    assert "nothing in it shows that detbench wrote it as a training run" in err
    assert snapshot(exp) == before

    new = tmp_path / "runs" / "new"
    code, err = tool("train", *train_argv(tmp_path / "no_such_data", new))
    assert code == 2 and not (tmp_path / "runs").exists()


def test_two_runs_on_one_out_then_a_kill(fault_data, tool, tmp_path):
    """A second training run on a folder a run is training in is refused naming the holder's pid and host,
    changing nothing; after that run is killed -9 its lock is taken over with a note and the run resumes."""
    out = tmp_path / "run"
    proc, marker = stalling_trainer(tmp_path, "step", train_argv(fault_data, out))
    try:
        _wait_stalled(proc, marker)
        before = snapshot(out)
        for extra in ([], ["--resume"]):
            code, err = tool("train", *train_argv(fault_data, out, *extra))
            assert code == 2, err
            assert f"error: --out {out}: in use by a training run pid {proc.pid} on host {socket.gethostname()}" in err
            assert snapshot(out) == before
    finally:
        kill_when_stalled(proc, marker)
    lock = out / ".detbench-lock"
    assert lock.is_file()  # left by the killed run
    code, err = tool("train", *train_argv(fault_data, out, "--resume"))
    assert code == 0, err
    assert f"note: {lock}: taken over from a training run pid {proc.pid} on host {socket.gethostname()}" in err
    assert not lock.exists() and (out / "checkpoints" / "epoch_002.pt").is_file()


def test_two_studies_on_one_out(data_copy, tool, tmp_path):
    """A study whose folder another study holds is refused naming the holder, --fresh included, before
    anything is deleted."""
    from detbench.train.run_layout import STUDY_FOLDER
    from detbench.utils.folder_locks import claim_folder

    out = tmp_path / "study"
    with claim_folder(out, STUDY_FOLDER, "a study"):
        (out / "ability").mkdir()
        (out / "ability" / "ability.json").write_text("{}")
        before = snapshot(out)
        code, err = _study(tool, out, data_copy, "--fresh")
        assert code == 2, err
        assert f"error: --out {out}: in use by a study pid {os.getpid()} on host {socket.gethostname()}" in err
        assert snapshot(out) == before
    assert not (out / ".detbench-lock").exists() and (out / ".detbench-owner.json").is_file()
