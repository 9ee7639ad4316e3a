"""tools/analyze.py --rigs: the ability study per rig through the command (small runs) and its argument errors."""
import json

import pytest

from detbench.utils.cli import UserError
import tools.analyze


def test_rigs_write_cells_and_near_field_per_rig(tmp_path, capsys):
    out = tmp_path / "rigs"
    assert tools.analyze.main(["--simulate", "6", "--frames-per-scene", "3", "--rigs", "paper-1.8", "headlights",
                               "--small-objects", "--out", str(out), "--no-progress", "--bootstrap", "0"]) == 0
    report = json.loads((out / "ability.json").read_text())
    assert list(report["rigs"]) == ["paper-1.8", "headlights"]
    for cell in report["rigs"].values():
        assert set(cell) >= {"small", "moderate", "large", "blind_zone_m", "self_hits", "near_field", "small_objects"}
        assert set(cell["large"]) == {"all", "top3", "top6"}
    assert report["rigs"]["headlights"]["blind_zone_m"]["ahead"] < report["rigs"]["paper-1.8"]["blind_zone_m"]["ahead"]
    assert "| large | all |" in (out / "ability.md").read_text()
    assert "blind ahead" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--data", "x", "--rigs", "plate"], "--rigs needs --simulate"),
    (["--simulate", "2", "--rigs", "plate", "--heights", "1.0"], "give one of them"),
    (["--simulate", "2", "--small-objects"], "--small-objects needs --rigs"),
    (["--simulate", "2", "--rigs", "nowhere"], "known: paper-0.5"),
    (["--simulate", "2", "--rigs", "plate", "--points"], "not with --rigs"),
])
def test_rig_argument_errors(tmp_path, argv, message):
    with pytest.raises(UserError, match=message):
        tools.analyze.main([*argv, "--out", str(tmp_path / "o"), "--no-progress"])


def test_user_rig_file_unknown_key_is_one_line(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("rigs:\n  low:\n    sensors:\n      - {preset: h3-1.0, z: 0.3, colour: red}\n")
    with pytest.raises(UserError, match=r"mine.yaml: rigs.low.sensors\[0\].colour: unknown key"):
        tools.analyze.main(["--simulate", "2", "--rigs", "low", "--rig-file", str(f), "--out", str(tmp_path / "o")])
    f.write_text("rigs:\n  low:\n    sensors:\n      - {preset: h3-1.0, z: 0.3}\n")
    assert tools.analyze.main(["--simulate", "2", "--rigs", "low", "--rig-file", str(f), "--out",
                               str(tmp_path / "o"), "--no-progress", "--bootstrap", "0"]) == 0
