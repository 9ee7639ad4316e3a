"""The study and the benchmark end a user's mistake as every other tool does: one line, exit status 2,
nothing deleted or created; a failed stage keeps its own status (2 for the user's error, 1 for a bug)."""
from __future__ import annotations

import sys

import pytest



def test_study_refuses_bad_arguments_before_touching_its_folder(tool, tmp_path):
    """The study refuses a bad argument (an unknown model, a height of 0, an unknown config key, a missing
    --data, --jobs 0, --address without Ray, a negative seed) in one line naming it, before its folder is
    touched: --fresh deletes nothing and no new folder is made."""
    out = tmp_path / "study"
    out.mkdir()
    (out / "keep.txt").write_text("an earlier study's file")
    code, err = tool("study", "--models", "secnd", "--out", out, "--fresh")
    assert code == 2 and "unknown model 'secnd'; did you mean 'second'?" in err
    assert (out / "keep.txt").is_file()  # --fresh deletes nothing when the command is refused
    code, err = tool("study", "--heights", "0", "1.8", "--out", tmp_path / "s2")
    assert code == 2 and "--heights 0: a mounting height is a positive number of metres" in err
    code, err = tool("study", "--set", "train.epohcs=3", "--out", tmp_path / "s3")
    assert code == 2 and "unknown config key 'train.epohcs'" in err and "epochs" in err
    code, err = tool("study", "--data", tmp_path / "nope", "--out", tmp_path / "s4")
    assert code == 2 and f"--data {tmp_path / 'nope'}: no such folder" in err
    code, err = tool("study", "--jobs", "0", "--out", tmp_path / "s5")
    assert code == 2 and "--jobs 0: the number of jobs at once is at least 1" in err
    code, err = tool("study", "--address", "auto", "--out", tmp_path / "s6")
    assert code == 2 and "--address auto names a Ray cluster: add --executor ray" in err
    code, err = tool("study", "--seeds", "0", "-1", "--out", tmp_path / "s7")
    assert code == 2 and "--seeds -1: a training seed is a whole number >= 0" in err
    assert not any((tmp_path / s).exists() for s in ("s2", "s3", "s4", "s5", "s6", "s7"))


def test_the_ray_executor_without_ray_names_the_install_command(tool, tmp_path, monkeypatch):
    """--executor ray without Ray installed is refused naming the install command, and no study folder is made."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    code, err = tool("study", "--executor", "ray", "--out", tmp_path / "s")
    assert code == 2 and "pip install -e '.[cluster]'" in err and not (tmp_path / "s").exists()


@pytest.mark.parametrize("status, expected", [(2, 2), (1, 1), (3, 1)])
def test_a_failed_study_job_keeps_the_users_error_apart_from_a_bug(status, expected, tmp_path):
    """A failed job's exit status reaches the study's: 2 (the user's error) stays 2, any other is 1 (a bug),
    whose message names the job and says to run the same command again."""
    from detbench.studies.executor import LocalExecutor
    from detbench.studies.jobs import Job, run_graph
    from detbench.utils.cli import run_main

    def main(_argv):
        cmd = [sys.executable, "-c", f"import sys; sys.exit({status})"]
        run_graph([Job("train_second_h1.8", "train", "train second 1.8 m", lambda: cmd)], LocalExecutor(1), tmp_path)
        return 0

    try:
        code = run_main(main, [])
    except SystemExit as e:  # a bug's SystemExit is not caught by run_main: its code is the message
        assert "train second 1.8 m failed" in str(e.code) and "run the same command again" in str(e.code)
        code = 1
    assert code == expected


def test_benchmark_refuses_an_unknown_model_and_a_missing_study(tool, tmp_path):
    """The benchmark refuses an unknown model (suggesting the near name) and a --study folder that does not
    exist (saying what it must be)."""
    code, err = tool("benchmark", "--models", "secnd")
    assert code == 2 and "--models: unknown model 'secnd'; did you mean 'second'?" in err
    code, err = tool("benchmark", "--models", "second", "--study", tmp_path / "nope")
    assert code == 2 and "no such folder; give the --out folder of a tools/study.py run" in err


@pytest.mark.parametrize("name, argv, named", [
    ("bench_eval", ["--frames", "0"], "--frames 0: must be an integer >= 1"),
    ("bench_eval", ["--bootstrap", "-1"], "--bootstrap -1: must be an integer >= 0"),
    ("bench_eval", ["--out", "{file}"], "is a file, not a folder; choose another --out"),
    ("bench_sim", ["--frames", "0"], "--frames 0: must be an integer >= 1"),
    ("bench_sim", ["--set", "traffic.densty=3"], "unknown config key 'traffic.densty'"),
    ("bench_sim", ["--out", "{file}/sub"], "is a file, not a folder; choose another --out"),
    ("bench_sparse", ["--voxel-size", "0", "0.1", "0.1"], "--voxel-size / --range: voxel_size must be positive"),
    ("bench_sparse", ["--device", "gpu7"], "--device 'gpu7': not a torch device"),
    ("bench_points", ["--samples", "9", "--points", "8"], "--samples 9: more than the 8 points per scan"),
    ("bench_points", ["--rois", "-1"], "--rois -1: must be an integer >= 0"),
])
def test_bench_tools_end_a_bad_argument_with_one_line(name, argv, named, tool, tmp_path):
    """Each benchmark tool refuses a bad argument as every other tool does: one 'error:' line naming it, exit
    status 2, no usage text or traceback, and nothing written (a file given as --out stays as it was)."""
    file = tmp_path / "a_file"
    file.write_text("not a folder")
    out = tmp_path / "out"
    argv = [a.replace("{file}", str(file)) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(out)]
    code, err = tool(name, *argv)
    assert code == 2 and err.startswith("error: ") and named in err, err[-2000:]
    assert err.count("\n") == 1 and "Traceback" not in err and "usage:" not in err
    assert not out.exists() and file.read_text() == "not a folder"


@pytest.mark.parametrize("argv, named", [
    (["--frames-per-scene", "0"], "--frames-per-scene 0: must be an integer >= 1"),
    (["--lane-width", "-1"], "--lane-width -1.0: must be a positive number of metres"),
    (["--pitch", "1.8=abc"], "--pitch 1.8=abc: 'abc' is not a pitch in degrees"),
    (["--src", "1.8={missing}"], "{missing}: expected an OpenPCDet custom folder"),
])
def test_convert_ends_a_bad_argument_with_one_line(argv, named, fault_data, tool, tmp_path, capsys):
    """`python -m detbench.data.convert` (= tools/import_openpcdet.py) refuses a bad argument (a frames-per-scene
    or lane width that is not positive, a pitch that is not a number, a source that is not an OpenPCDet
    folder) in one line naming the flag."""
    from detbench.data.convert import main
    from detbench.utils.cli import run_main

    src = tmp_path / "opc"
    assert tool("export_openpcdet", fault_data, "--height", "1.8", "--out", src, "--no-progress")[0] == 0
    missing = tmp_path / "nope"
    argv = [a.replace("{missing}", str(missing)) for a in argv]
    if "--src" not in argv:
        argv = ["--src", f"1.8={src}", *argv]
    out = tmp_path / "imported"
    capsys.readouterr()
    code = run_main(main, [*argv, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and f"error: {named.replace('{missing}', str(missing))}" in err, err[-2000:]
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]
