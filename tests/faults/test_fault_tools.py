"""The study and the benchmark end a user's mistake as every other tool does: one line, exit status 2,
nothing deleted or created; a failed stage keeps its own status (2 for the user's error, 1 for a bug)."""
from __future__ import annotations

import sys

import pytest


def test_study_refuses_bad_arguments_before_touching_its_folder(tool, tmp_path):
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
    assert not any((tmp_path / s).exists() for s in ("s2", "s3", "s4"))


@pytest.mark.parametrize("status, expected", [(2, 2), (1, 1), (3, 1)])
def test_a_failed_study_stage_keeps_the_users_error_apart_from_a_bug(load_tool, status, expected):
    from detbench.utils.cli import run_main

    study = load_tool("study")

    def main(_argv):
        study.run([sys.executable, "-c", f"import sys; sys.exit({status})"], "train second at 1.8 m")
        return 0

    try:
        code = run_main(main, [])
    except SystemExit as e:  # a bug's SystemExit is not caught by run_main: its code is the message
        assert "train second at 1.8 m failed" in str(e.code) and "run the same command again" in str(e.code)
        code = 1
    assert code == expected


def test_benchmark_refuses_an_unknown_model_and_a_missing_study(tool, tmp_path):
    code, err = tool("benchmark", "--models", "secnd")
    assert code == 2 and "--models: unknown model 'secnd'; did you mean 'second'?" in err
    code, err = tool("benchmark", "--models", "second", "--study", tmp_path / "nope")
    assert code == 2 and "no such folder; give the --out folder of a tools/study.py run" in err
