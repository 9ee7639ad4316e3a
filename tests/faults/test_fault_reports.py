"""Report folders: a report-writing tool writes only into a folder that is new, empty or its own (the
folder-ownership rule), so it never replaces a report.md, .json or .csv it did not write; an evaluation's
predictions folder is replaced whole, so two evaluations into one --out never mix their files."""
import pytest

from tests.faults.faultkit import snapshot

CASES = {  # tool: (arguments besides --out, a file of the user's named like the tool's own)
    "eval": (["--data", "{data}", "--height", "1.8", "--pred", "{empty}"], "report.md"),
    "eval-combine": (["--combine", "{empty}/report.json"], "combined.csv"),
    "analyze": (["--simulate", "2", "--heights", "1.8", "--no-figures", "--no-progress"], "ability.md"),
    "sweep": (["--frames", "2", "--heights", "1.8", "--no-figures", "--no-progress"], "sweep.md"),
    "benchmark": (["--models", "second", "--frames", "1", "--warmup", "0"], "benchmark.md"),
    "check_calibration": (["--seeds", "0", "--frames", "2", "--no-progress"], "calibration.md"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_report_the_tool_did_not_write_is_never_replaced(case, fault_data, tmp_path, tool):
    """--out holds the user's own file of the name the tool writes (and nothing that shows detbench wrote the
    folder): refused in one line naming the folder, before any work, and the folder is unchanged."""
    argv, name = CASES[case]
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "mine"
    out.mkdir()
    (out / name).write_text("the user's own notes")
    before = snapshot(out)
    argv = [a.format(data=fault_data, empty=empty) for a in argv]
    code, err = tool(case.split("-")[0], *argv, "--out", out)
    assert code == 2, err[-3000:]
    assert f"--out {out}: the folder is not empty ({name}) and nothing in it shows that detbench wrote it as " in err
    assert "Traceback" not in err
    assert snapshot(out) == before


def test_an_evaluation_writes_again_into_its_own_folder(fault_data, tmp_path, tool):
    """The rule refuses nothing of the tool's own: an evaluation's folder takes the next evaluation."""
    empty = tmp_path / "pred"
    empty.mkdir()
    out = tmp_path / "eval"
    for _ in range(2):
        code, err = tool("eval", "--data", fault_data, "--height", 1.8, "--pred", empty, "--out", out)
        assert code == 0, err[-3000:]
    assert {"report.json", "report.md", "report.csv"} <= {p.name for p in out.iterdir()}


def test_two_evaluations_into_one_out_never_mix_predictions(trained_run, fault_data, tmp_path, tool):
    """A checkpoint evaluated on the test split, then on the train split, into one --out: pred/ holds the
    second evaluation's frames alone; an evaluation of saved predictions then removes the pred/ the
    checkpoint's evaluation left, which its report does not describe."""
    from detbench.data import Height3Dataset

    ckpt = trained_run / "checkpoints" / "epoch_002.pt"
    out = tmp_path / "eval"
    for split in ("test", "train"):
        code, err = tool("eval", "--ckpt", ckpt, "--data", fault_data, "--split", split, "--out", out,
                         "--no-progress")
        assert code == 0, err[-3000:]
    train_ids = sorted(Height3Dataset(fault_data, 1.8, "train").frame_ids)
    assert sorted(p.stem for p in (out / "pred").iterdir()) == train_ids
    saved = tmp_path / "saved"
    saved.mkdir()
    code, err = tool("eval", "--data", fault_data, "--height", 1.8, "--pred", saved, "--out", out)
    assert code == 0, err[-3000:]
    assert not (out / "pred").exists()
