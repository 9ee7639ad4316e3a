"""Replacing a folder whole (`tools/simulate.py --overwrite`, `python -m detbench.data.convert --overwrite`,
`tools/export_openpcdet.py --overwrite`): the new folder is built beside the old one and swapped in when
complete, so a kill -9, a failure or a refusal at any moment leaves the old folder as it was, and the next
run removes what the interrupted one left."""
import json
import signal
import subprocess
import sys
import time

import pytest

from tests.faults.faultkit import ROOT, snapshot


def _siblings(folder):
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith(".tmp-"))


def test_kill_during_simulate_overwrite_keeps_the_old_dataset(data_copy, tmp_path):
    """kill -9 while `simulate --overwrite` builds the new dataset leaves the old one whole (same files, sizes,
    times and digests); the next run removes the half-built folder and replaces the old dataset entirely."""
    before = snapshot(data_copy)
    assert "dataset.json" in before and "points/1.8/0000_000.npy" in before
    cmd = [sys.executable, "tools/simulate.py", "--out", str(data_copy), "--frames", "400", "--frames-per-scene",
           "10", "--heights", "1.8", "--seed", "5", "--overwrite", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    staged = data_copy.parent / f".tmp-new-{data_copy.name}-{proc.pid}"
    t0 = time.monotonic()
    while len(list((staged / "points" / "1.8").glob("*.npy"))) < 3:
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() - t0 < 120, "the simulation never wrote 3 frames"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert snapshot(data_copy) == before  # the old dataset is whole: same files, sizes, times and digests
    assert staged.is_dir()  # what the killed run left

    cmd[cmd.index("400")] = "4"
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"note: {staged}: removed (left by an interrupted write" in done.stderr
    assert _siblings(data_copy) == []
    info = json.loads((data_copy / "dataset.json").read_text())
    assert info["source"]["seed"] == 5 and info["num_frames"] == 4
    assert sorted(p.name for p in (data_copy / "points").iterdir()) == ["1.8"]  # nothing of the old one is left
    assert (data_copy / "simulate_run.json").is_file()


def test_refused_simulate_changes_nothing(data_copy, tool):
    """simulate into an existing dataset is refused without --overwrite, and with it when the folder holds a
    file of the user's; both refusals change nothing and leave nothing beside the folder."""
    (data_copy / "notes.txt").write_text("the user's own file")
    before = snapshot(data_copy)
    code, err = tool("simulate", "--out", data_copy, "--frames", "2", "--heights", "1.8", "--no-progress")
    assert code == 2 and f"{data_copy / 'dataset.json'}: a dataset already exists here" in err and "--overwrite" in err
    code, err = tool("simulate", "--out", data_copy, "--frames", "2", "--heights", "1.8", "--no-progress",
                     "--overwrite")
    assert code == 2 and f"{data_copy}: holds notes.txt, which is not part of a dataset" in err
    assert snapshot(data_copy) == before and _siblings(data_copy) == []


def test_a_swap_interrupted_between_its_renames_is_repaired(tmp_path, monkeypatch):
    """Where the system has no atomic exchange, a swap is two renames; a kill between them leaves the old
    folder aside and none at `dest`: the next run puts the old one back. After the swap, a leftover old
    folder is removed."""
    import detbench.utils.staged_folders as staged_folders

    dead = 999999999  # no process has this id
    dest = tmp_path / "data"
    old = tmp_path / f".tmp-old-data-{dead}"
    old.mkdir()
    (old / "dataset.json").write_text("{}")
    new = tmp_path / f".tmp-new-data-{dead}"
    new.mkdir()
    notes = staged_folders.recover_staged(dest)
    assert (dest / "dataset.json").read_text() == "{}" and not old.exists() and not new.exists()
    assert len(notes) == 2 and "put back" in notes[0]
    old.mkdir()
    staged_folders.recover_staged(dest)
    assert not old.exists() and (dest / "dataset.json").is_file()

    monkeypatch.setattr(staged_folders, "_exchange", lambda a, b: False)  # the two-rename path
    with staged_folders.staged_folder(dest) as staged:
        (staged / "dataset.json").write_text('{"new": 1}')
    assert (dest / "dataset.json").read_text() == '{"new": 1}' and _siblings(dest) == []
    with pytest.raises(RuntimeError), staged_folders.staged_folder(dest) as staged:
        (staged / "dataset.json").write_text('{"newer": 1}')
        raise RuntimeError("failed half-way")
    assert (dest / "dataset.json").read_text() == '{"new": 1}' and _siblings(dest) == []


def _export(tool, data, out, *extra):
    return tool("export_openpcdet", data, "--height", "1.8", "--out", out, "--no-progress", *extra)


def test_failed_export_and_import_with_overwrite_keep_the_earlier_ones(data_copy, tool, tmp_path):
    """A bad frame stops export and import with --overwrite before the existing folder is deleted or overwritten."""
    export = tmp_path / "opc"
    assert _export(tool, data_copy, export)[0] == 0
    imported = tmp_path / "imported"
    code, err = tool("import_openpcdet", "--src", f"1.8={export}", "--out", imported, "--no-progress")
    assert code == 0, err
    exp_before, imp_before = snapshot(export), snapshot(imported)

    # a bad frame late in the source: the export stops there, the earlier export stays whole
    test_ids = (data_copy / "ImageSets" / "test.txt").read_text().split()
    bad = data_copy / "points" / "1.8" / f"{test_ids[-1]}.npy"
    bad.write_bytes(b"")
    code, err = _export(tool, data_copy, export, "--overwrite")
    assert code == 2 and f"{bad}: the file is empty" in err
    assert snapshot(export) == exp_before and _siblings(export) == []

    # the same for the import from a damaged OpenPCDet folder (copy, so the export stays as it was)
    import shutil

    src = shutil.copytree(export, tmp_path / "opc_damaged")
    last = sorted((src / "points").glob("*.npy"))[-1]
    last.write_bytes(b"")
    code, err = tool("import_openpcdet", "--src", f"1.8={src}", "--out", imported, "--overwrite", "--no-progress")
    assert code == 2 and str(last) in err
    assert snapshot(imported) == imp_before and _siblings(imported) == []

    # an export folder holding a foreign file, or an import over its own source, is refused
    (export / "my_notes.txt").write_text("keep me")
    code, err = _export(tool, data_copy, export, "--overwrite")
    assert code == 2 and "holds my_notes.txt, which is not written by an export" in err
    code, err = tool("import_openpcdet", "--src", f"1.8={src}", "--out", src, "--overwrite", "--no-progress")
    assert code == 2 and "holds the source folder" in err
    assert (src / "points").is_dir() and (export / "my_notes.txt").is_file()
