"""A thing named twice on a command line is refused in one line before any work: counted twice, every total
and pooled figure would double."""
import pytest

CASES = [
    ("analyze", ["--simulate", "2", "--heights", "1.8", "1.80", "--no-figures", "--no-progress"], "--heights",
     "1.8 is given twice; give each height once"),
    ("sweep", ["--frames", "2", "--heights", "1.0", "1", "--no-figures", "--no-progress"], "--heights",
     "1.0 is given twice; give each height once"),
    ("check_calibration", ["--seeds", "0", "0", "--frames", "2", "--no-progress"], "--seeds",
     "0 is given twice; give each seed once"),
    ("study", ["--preset", "smoke", "--heights", "1.8", "1.8", "--no-progress"], "--heights",
     "1.8 is given twice; give each height once"),
    ("study", ["--preset", "smoke", "--models", "second", "second", "--no-progress"], "--models",
     "second is given twice; give each model once"),
    ("study", ["--preset", "smoke", "--seeds", "1", "1", "--no-progress"], "--seeds",
     "1 is given twice; give each seed once"),
    ("benchmark", ["--models", "second", "second", "--frames", "1"], "--models",
     "second is given twice; give each model once"),
]


@pytest.mark.parametrize("name,argv,flag,said", CASES, ids=[f"{c[0]}{c[2]}" for c in CASES])
def test_a_duplicate_is_refused_before_any_work(name, argv, flag, said, tmp_path, tool):
    out = tmp_path / "out"
    code, err = tool(name, *argv, "--out", out)
    assert code == 2, err[-3000:]
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and lines[0].startswith(f"error: {flag} ") and said in lines[0], err[-3000:]
    assert "Traceback" not in err and not out.exists()
