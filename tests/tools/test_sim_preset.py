"""--sim-preset (a simulator calibration of configs/sim.yaml) and --preset (a training budget of
configs/presets/) are two flags with two meanings: the simulator tools take --sim-preset and accept
--preset as its deprecated spelling with a note on stderr; the training tools keep --preset."""
import pytest

import tools.analyze
import tools.bench_sim
import tools.benchmark
import tools.check_calibration
import tools.simulate
import tools.study
import tools.sweep
import tools.tradeoff
import tools.train

SIM_TOOLS = [tools.analyze, tools.bench_sim, tools.check_calibration, tools.simulate, tools.sweep]
TRAIN_TOOLS = [tools.benchmark, tools.study, tools.tradeoff, tools.train]
REQUIRED = {tools.simulate: ["--out", "x"], tools.analyze: ["--simulate", "8"]}


@pytest.mark.parametrize("tool", SIM_TOOLS, ids=lambda t: t.__name__)
def test_simulator_tools_take_sim_preset_and_keep_preset_as_deprecated(tool, capsys):
    parser = tool.build_parser()
    base = REQUIRED.get(tool, [])
    assert parser.parse_args(base).sim_preset == "paper"
    assert parser.parse_args([*base, "--sim-preset", "v1"]).sim_preset == "v1"
    assert capsys.readouterr().err == ""
    assert parser.parse_args([*base, "--preset", "v1"]).sim_preset == "v1"
    err = capsys.readouterr().err
    assert "--preset v1 is a deprecated spelling of --sim-preset v1" in err and "training budget" in err
    text = parser.format_help()
    assert "--sim-preset NAME" in text and "simulator calibration" in text and "deprecated" in text


@pytest.mark.parametrize("tool", TRAIN_TOOLS, ids=lambda t: t.__name__)
def test_training_tools_preset_is_a_training_budget(tool):
    text = tool.build_parser().format_help()
    assert "--sim-preset" not in text
    assert "configs/presets" in text, "the --preset help names where training budgets live"


def test_simulate_runs_with_the_deprecated_spelling(tmp_path, capsys):
    assert tools.simulate.main(["--out", str(tmp_path / "d"), "--frames", "2", "--heights", "1.8", "--preset", "v1",
                                "--no-progress"]) == 0
    assert "deprecated spelling of --sim-preset" in capsys.readouterr().err
    import json
    assert json.loads((tmp_path / "d" / "simulate_run.json").read_text())["preset"] == "v1"
