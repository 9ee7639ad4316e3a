"""Writers that meet: a cache shared by machines, two commands writing one folder. A build is alive while it
holds its destination's lock (not judged by its pid, which another pid namespace or machine cannot see), a
second writer of one folder is refused while the first runs, and a dataset whose files vanished while it was
written is never published."""
import json
from pathlib import Path
import subprocess
import sys
import time

import pytest

from tests.faults.faultkit import ROOT

# a process whose DatasetWriter stalls before its third frame until the file GO exists (MARKER is created when it
# stalls); then runs tools/simulate.py with ARGS, or (ARGS = ["default", CACHE]) builds the default dataset there
STALLING_WRITER = '''
import os, runpy, sys, time
marker, go = sys.argv[1:3]
sys.path.insert(0, ".")
from detbench.data.writer import DatasetWriter
real = DatasetWriter.add

def add(self, frames):
    if len(self) == 2 and not os.path.exists(go):
        open(marker, "w").close()
        while not os.path.exists(go):
            time.sleep(0.05)
    real(self, frames)

DatasetWriter.add = add
if sys.argv[3] == "default":
    from detbench.sim.dataset import default_dataset
    cfg = {"frames": 6, "frames_per_scene": 2, "heights": [1.8], "cache_dir": sys.argv[4]}
    print(default_dataset(cfg, progress=False))
else:
    sys.argv = ["tools/simulate.py", *sys.argv[3:]]
    runpy.run_module("tools.simulate", run_name="__main__", alter_sys=True)
'''


def stalling_writer(tmp_path, *argv):
    """(process, marker, go) of a STALLING_WRITER run; waits until it stalls."""
    script, marker, go = tmp_path / "stalling_writer.py", tmp_path / "stalled", tmp_path / "go"
    script.write_text(STALLING_WRITER)
    proc = subprocess.Popen([sys.executable, str(script), str(marker), str(go), *map(str, argv)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not marker.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the writer ended (exit {proc.returncode}) before it stalled: "
                                 f"{proc.communicate()[1][-3000:]}")
        assert time.monotonic() - t0 < 120, "the writer never stalled"
        time.sleep(0.05)
    return proc, go


def finish(proc, go) -> str:
    go.write_text("")
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    return out


def test_a_live_build_in_a_shared_cache_survives_another_machines_clean_up(tmp_path, monkeypatch):
    """While one process builds the default dataset in the cache, another that cannot see its pid (another pid
    namespace or machine sharing the cache) cleans up abandoned builds: the live build is untouched, and the
    dataset it publishes holds every frame."""
    import detbench.sim.dataset as simds
    import detbench.utils.staged_folders as staged_folders
    from detbench.data.dataset import Height3Dataset

    cache = tmp_path / "cache"
    work = tmp_path / "work"
    work.mkdir()
    proc, go = stalling_writer(work, "default", cache)
    try:
        building = [p for p in cache.iterdir() if p.name.startswith(".tmp-")]
        assert building, "the build's folder"
        files = {p: sorted(q.relative_to(p) for q in p.rglob("*")) for p in building}
        monkeypatch.setattr(staged_folders, "pid_alive", lambda pid: False)  # the builder's pid is not visible here
        monkeypatch.setattr(simds, "pid_alive", lambda pid: False, raising=False)
        simds.remove_abandoned_builds(cache)
        assert {p: sorted(q.relative_to(p) for q in p.rglob("*")) for p in building if p.exists()} == files
    finally:
        out = finish(proc, go)
    final = cache / out.strip().splitlines()[-1].rsplit("/", 1)[-1]
    info = json.loads((final / "dataset.json").read_text())
    assert info["num_frames"] == 6
    frames = [f for split in ("train", "test") for f in Height3Dataset(final, 1.8, split)]
    assert len(frames) == 6 and all(len(f.points) for f in frames)


def test_a_dataset_whose_files_vanish_is_never_published(tmp_path):
    """A file of the dataset being built is deleted (by another process) before the build ends: the build
    fails naming the missing file, and nothing is published at the destination."""
    from detbench.data.errors import DatasetError
    from detbench.sim import HighwaySimulator, load_sim_config
    from detbench.sim.dataset import write_simulation
    from detbench.sim.lidar import lidar_preset

    out = tmp_path / "data"
    steps = []

    def delete_a_label(step):
        steps.append(step)
        if len(steps) == 3:
            staged = next(tmp_path.glob(".tmp-new-data-*"))
            (staged / "labels" / f"{steps[0][0].frame_id}.txt").unlink()

    sim = HighwaySimulator(load_sim_config("paper"), seed=0)
    with pytest.raises(DatasetError, match=r"1 file\(s\) written for its 4 frames vanished before the dataset was "
                                           r"finished \(e\.g\. .*/labels/0000_000\.txt\)"):
        write_simulation(out, sim, [lidar_preset(1.8)], 4, source={"kind": "test"}, frames_per_scene=2,
                         progress=False, on_step=delete_a_label)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_two_simulations_into_one_new_out(tmp_path, tool):
    """A second `tools/simulate.py` into the --out a first one is still writing is refused in one line naming
    the first's pid and host; the first finishes and its dataset is the one in --out."""
    out = tmp_path / "sim"
    work = tmp_path / "work"
    work.mkdir()
    proc, go = stalling_writer(work, "--out", out, "--frames", 4, "--heights", 1.8, "--seed", 0, "--no-progress")
    try:
        code, err = tool("simulate", "--out", out, "--frames", 2, "--heights", 1.8, "--seed", 1, "--no-progress")
    finally:
        finish(proc, go)
    assert code == 2 and f"error: {out}: in use by a simulation pid {proc.pid} on host " in err, err
    assert "wait for it to end, or choose another --out" in err and "Traceback" not in err
    assert "wrote " not in err
    info = json.loads((out / "dataset.json").read_text())
    assert info["source"]["seed"] == 0 and info["num_frames"] == 4


def test_an_export_into_a_folder_another_writer_holds_is_refused(fault_data, tmp_path, tool):
    """`tools/export_openpcdet.py` into an --out that another process is writing is refused in one line naming
    it, and writes nothing there."""
    out = tmp_path / "export"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom detbench.utils.staged_folders import hold_destination\n"
                               "with hold_destination(sys.argv[1], 'an OpenPCDet export'):\n"
                               "    open(sys.argv[2], 'w').close()\n    time.sleep(60)\n",
         str(out), str(tmp_path / "held")], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not (tmp_path / "held").exists():
            assert holder.poll() is None, holder.communicate()[1][-3000:]
            assert time.monotonic() - t0 < 60
            time.sleep(0.05)
        code, err = tool("export_openpcdet", fault_data, "--height", 1.8, "--out", out, "--no-progress")
    finally:
        holder.kill()
        holder.communicate()
    assert code == 2 and f"error: {out}: in use by an OpenPCDet export pid {holder.pid} on host " in err, err
    assert not out.exists()


def test_a_dataset_a_training_reads_is_not_replaced(data_copy, tmp_path, tool):
    """`simulate --overwrite` on the --data of a running training is refused in one line (the training holds a
    reader's lock on it), and the dataset stays as the training found it."""
    from tests.faults.faultkit import snapshot, stalling_trainer, train_argv

    before = snapshot(data_copy)
    proc, marker = stalling_trainer(tmp_path, "step", train_argv(data_copy, tmp_path / "run"))
    try:
        t0 = time.monotonic()
        while not marker.exists():
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            assert time.monotonic() - t0 < 240, "the training never reached its step"
            time.sleep(0.1)
        code, err = tool("simulate", "--out", data_copy, "--frames", 4, "--heights", 1.8, "--overwrite",
                         "--no-progress")
    finally:
        proc.kill()
        proc.communicate()
    assert code == 2, err[-3000:]
    assert f"error: {data_copy}: in use by processes that read it (a training, for one)" in err
    assert "Traceback" not in err
    def data(snap):  # the dataset's files (the training adds its ground-truth database)
        return {k: v for k, v in snap.items() if not k.startswith("gt_database")}

    assert data(snapshot(data_copy)) == data(before)


def test_an_evaluation_says_when_its_data_changed_since_the_training(trained_run, fault_data, tmp_path, tool):
    """The dataset a checkpoint was trained on is re-split (simulated again with another --test-fraction):
    evaluating the checkpoint on it warns that the dataset changed and that training frames are among those
    evaluated, on stderr and in report.json; on the data it was trained with, no such warning."""
    import shutil

    data = Path(shutil.copytree(fault_data, tmp_path / "data"))
    src = json.loads((data / "dataset.json").read_text())["source"]
    code, err = tool("simulate", "--out", data, "--frames", src["frames"], "--frames-per-scene", 4, "--heights",
                     0.5, 1.8, "--seed", src["seed"], "--test-fraction", 0.67, "--overwrite", "--no-progress")
    assert code == 0, err[-3000:]
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    code, err = tool("eval", "--ckpt", ckpt, "--data", data, "--out", tmp_path / "eval", "--no-progress")
    assert code == 0, err[-3000:]
    assert f"{data} is not the dataset this checkpoint was trained on: its dataset.json changed since" in err
    assert "frames of the test split were training frames of this checkpoint" in err
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert any("were training frames of this checkpoint" in w for w in report["warnings"])
    code, err = tool("eval", "--ckpt", ckpt, "--data", fault_data, "--out", tmp_path / "eval0", "--no-progress")
    assert code == 0 and "training frames of this checkpoint" not in err and "is not the dataset" not in err


def test_an_evaluation_on_another_simulated_world_is_a_held_out_test(trained_run, fault_data, tmp_path, tool):
    """A dataset simulated with another seed (tools/study.py --test-data, a held-out set) names its frames as the
    training data does (0000_000, ...) but holds other scenes: evaluating on it warns of neither a changed dataset
    nor training frames among the test frames, while the same seed re-split does (the test above)."""
    src = json.loads((fault_data / "dataset.json").read_text())["source"]
    other = tmp_path / "other"
    code, err = tool("simulate", "--out", other, "--frames", src["frames"], "--frames-per-scene", 4, "--heights",
                     0.5, 1.8, "--seed", int(src["seed"]) + 1, "--test-fraction", 0.67, "--no-progress")
    assert code == 0, err[-3000:]
    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    code, err = tool("eval", "--ckpt", ckpt, "--data", other, "--out", tmp_path / "eval", "--no-progress")
    assert code == 0, err[-3000:]
    assert "training frames of this checkpoint" not in err and "is not the dataset" not in err, err[-3000:]
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert report["warnings"] == []


def test_a_checkpoint_without_the_scene_record_reads_its_training_datasets_source(fault_data, tmp_path):
    """A checkpoint written before it recorded what drew its scenes (`dataset_scenes`) is compared through its
    training dataset's dataset.json while that file is the one it was trained on: another seed's world is a
    held-out test, the same seed's re-split is not; once the training dataset.json changed, ids decide."""
    import shutil

    from detbench.train.run import dataset_identity, training_data_warnings

    info = {"source": str(fault_data), **dataset_identity(fault_data, [])}
    assert json.loads(info.pop("dataset_scenes"))["seed"] == 3
    test_ids = (fault_data / "ImageSets" / "test.txt").read_text().split()
    train_ids = (fault_data / "ImageSets" / "train.txt").read_text().split()
    info["train_frames"] = "\n".join(train_ids)
    other = Path(shutil.copytree(fault_data, tmp_path / "other"))
    meta = json.loads((other / "dataset.json").read_text())
    (other / "ImageSets" / "test.txt").write_text("\n".join(train_ids + test_ids) + "\n")
    meta["source"]["seed"] = 4
    (other / "dataset.json").write_text(json.dumps(meta))
    assert training_data_warnings(info, other, "test", train_ids + test_ids) == []
    meta["source"]["seed"] = 3
    meta["split"] = {**meta.get("split", {}), "note": "re-split"}
    (other / "dataset.json").write_text(json.dumps(meta))
    warned = training_data_warnings(info, other, "test", train_ids + test_ids)
    assert len(warned) == 2 and f"{len(train_ids)} of the {len(train_ids) + len(test_ids)} frames" in warned[1]
    moved = {**info, "source": str(tmp_path / "gone")}
    meta["source"]["seed"] = 4
    (other / "dataset.json").write_text(json.dumps(meta))
    assert len(training_data_warnings(moved, other, "test", train_ids + test_ids)) == 2
