"""Settings and places that used to end in a traceback: each is one line naming what is wrong and the fix
(exit status 2), and a read-only dataset trains (its ground-truth database goes to the cache)."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from tests.faults.faultkit import ROOT, run_python

TRAIN = ["tools/train.py", "--model", "second", "--height", "1.8", "--preset", "smoke", "--no-progress"]


def _one_error_line(proc) -> str:
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1, proc.stderr[-3000:]
    return lines[0]


@pytest.mark.parametrize("name,value,said", [
    ("NUMBA_NUM_THREADS", "0", "error: NUMBA_NUM_THREADS=0: numba's thread count is a whole number >= 1"),
    ("DETBENCH_MAX_TENSOR_GB", "nan", "error: DETBENCH_MAX_TENSOR_GB=nan: the largest tensor a model may allocate "
                                      "is a positive number of GiB"),
    ("NUMBA_THREADING_LAYER", "fastest", "error: NUMBA_THREADING_LAYER=fastest: one of default, safe"),
])
def test_an_environment_setting_the_libraries_stop_on(name, value, said, fault_data, tmp_path):
    proc = run_python([*TRAIN, "--data", str(fault_data), "--out", str(tmp_path / "run")],
                      env={**os.environ, name: value})
    assert _one_error_line(proc).startswith(said)
    assert not (tmp_path / "run").exists()


def test_a_threading_layer_numba_cannot_load(fault_data, tmp_path):
    import importlib

    try:
        importlib.import_module("numba.np.ufunc.tbbpool")
        pytest.skip("Intel TBB is installed here: the tbb layer loads")
    except ImportError:
        pass
    proc = run_python([*TRAIN, "--data", str(fault_data), "--out", str(tmp_path / "run")],
                      env={**os.environ, "NUMBA_THREADING_LAYER": "tbb"})
    assert "NUMBA_THREADING_LAYER=tbb: numba cannot load this layer here (it needs Intel TBB" in _one_error_line(proc)


def test_a_cache_that_is_a_file(tmp_path, tool, monkeypatch):
    (tmp_path / "afile").write_text("")
    monkeypatch.setenv("DETBENCH_CACHE", str(tmp_path / "afile"))
    code, err = tool("train", *TRAIN[1:], "--out", tmp_path / "run")
    assert code == 2 and f"DETBENCH_CACHE={tmp_path / 'afile'}: {tmp_path / 'afile'} is a file, not a folder" in err


def test_a_data_root_yaml_reads_as_true(tmp_path, tool):
    code, err = tool("train", *TRAIN[1:], "--out", tmp_path / "run", "--set", "data.root=yes")
    assert code == 2 and "data.root is True, not a folder path (YAML reads yes, no, on and off as true" in err


def test_a_number_too_long_to_read(fault_data, tmp_path, tool):
    code, err = tool("train", *TRAIN[1:], "--data", fault_data, "--out", tmp_path / "run", "--set",
                     "train.lr=" + "1" * 5000)
    assert code == 2 and "--set 'train.lr': the value is a number 5000 characters long, too long to read" in err


# runs inside a user and mount namespace in which argv[1] (an output folder) and argv[2] (a dataset) are
# read-only: each command as a user runs it, with what it said
IN_READ_ONLY = '''
import json, subprocess, sys
ro, data, empty, rw = sys.argv[1:5]
train = ["tools/train.py", "--model", "second", "--height", "1.8", "--preset", "smoke", "--no-progress"]
cases = {
    "eval": ["tools/eval.py", "--data", data, "--height", "1.8", "--pred", empty, "--out", ro + "/eval"],
    "simulate": ["tools/simulate.py", "--out", ro + "/sim", "--frames", "2", "--heights", "1.8", "--no-progress"],
    "analyze": ["tools/analyze.py", "--data", data, "--out", ro + "/ability", "--no-figures", "--no-progress"],
    "export": ["tools/export_openpcdet.py", data, "--height", "1.8", "--out", ro + "/export", "--no-progress"],
    "train_out": [*train, "--data", data, "--out", ro + "/run"],
    "study": ["tools/study.py", "--preset", "smoke", "--models", "second", "--heights", "1.8", "--data", data,
              "--out", ro + "/study", "--no-progress"],
    "train_data": [*train, "--data", data, "--out", rw + "/run", "--set", "train.epochs=1"],
}
out = {}
for name, argv in cases.items():
    p = subprocess.run([sys.executable, *argv], capture_output=True, text=True)
    out[name] = {"code": p.returncode, "stderr": p.stderr[-3000:]}
p = subprocess.run([sys.executable, *train, "--out", rw + "/run_cache"], capture_output=True, text=True,
                   env={**__import__("os").environ, "DETBENCH_CACHE": ro + "/cache"})
out["cache"] = {"code": p.returncode, "stderr": p.stderr[-3000:]}
print(json.dumps(out))
'''


def test_read_only_folders(fault_data, tmp_path):
    """An output folder, a dataset and a cache on a read-only file system: each command says so in one line
    naming the folder; a read-only dataset trains, its ground-truth database built in the cache."""
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-rm", "true"]).returncode != 0:
        pytest.skip("this system does not let a user make a mount namespace (unshare -rm)")
    ro, rw, empty = tmp_path / "ro", tmp_path / "rw", tmp_path / "empty"
    for d in (ro, rw, empty):
        d.mkdir()
    data = shutil.copytree(fault_data, tmp_path / "data", ignore=shutil.ignore_patterns("gt_database"))
    script = tmp_path / "in_read_only.py"
    script.write_text(IN_READ_ONLY)
    bind = " && ".join(f'mount --bind "${i}" "${i}" && mount -o remount,bind,ro "${i}"' for i in (1, 2))
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", f'{bind} && exec "$5" "$6" "$1" "$2" "$3" "$4"', "sh",
                           str(ro), str(data), str(empty), str(rw), sys.executable, str(script)],
                          cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "DETBENCH_CACHE": str(tmp_path / "cache")})
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    for name in ("eval", "simulate", "analyze", "export", "train_out", "study", "cache"):
        r = res[name]
        assert r["code"] == 2 and "Traceback" not in r["stderr"], (name, r)
        assert "cannot be written (the file system is read-only); choose a folder you can write to" in r["stderr"]
    assert res["train_data"]["code"] == 0, res["train_data"]
    assert not (data / "gt_database").exists() and list((tmp_path / "cache" / "gt_database").rglob("*.json"))
