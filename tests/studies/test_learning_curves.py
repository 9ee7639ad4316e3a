"""Learning curves over training seeds (detbench.studies.learning_curves, tools/curves.py)."""
import json

import pytest

import tools.curves
from detbench.studies.learning_curves import collect_curves
from detbench.utils.cli import run_main


def _run(root, name, model, seed, epochs):
    """A finished run folder: epochs [(cpu_seconds, ap_r40_small or None)]."""
    run = root / name
    run.mkdir(parents=True)
    (run / "train_summary.json").write_text(json.dumps({"model": model, "preset": "cpu"}))
    (run / "config.yaml").write_text(f"train:\n  seed: {seed}\n")
    hist = [{"epoch": i + 1, "seconds": 2 * cpu, "cpu_seconds": cpu,
             "metrics": {} if ap is None else {"ap_r40_small": ap, "recall_small": ap + 0.1, "recall_large": ap / 2}}
            for i, (cpu, ap) in enumerate(epochs)]
    (run / "history.json").write_text(json.dumps({"epochs": hist}))
    return run


def test_a_curve_is_the_mean_over_seeds_at_the_epochs_every_seed_evaluated(tmp_path):
    a = _run(tmp_path, "second_s0", "second", 0, [(60, 0.1), (60, None), (60, 0.5)])
    b = _run(tmp_path, "second_s1", "second", 1, [(120, 0.3), (120, 0.4), (120, 0.7)])
    c = _run(tmp_path, "pillarnet_s0", "pillarnet", 0, [(30, 0.2)])
    curves = {x.model: x for x in collect_curves([a, b, c])}
    s = curves["second"]
    assert s.clock == "cpu" and s.seeds == (0, 1) and [p.epoch for p in s.points] == [1, 3]  # epoch 2: seed 0 none
    p1, p3 = s.points
    assert p1.minutes == pytest.approx((1 + 2) / 2) and p3.minutes == pytest.approx((3 + 6) / 2)
    assert p3.mean["ap_r40_small"] == pytest.approx(0.6)
    assert (p3.low["ap_r40_small"], p3.high["ap_r40_small"]) == (0.5, 0.7)
    assert curves["pillarnet"].points[0].mean["recall_large"] == pytest.approx(0.1)


def test_the_tool_writes_json_markdown_and_figure_and_names_a_run_without_evaluations(tmp_path, capsys):
    a = _run(tmp_path, "second_s0", "second", 0, [(60, 0.1), (60, 0.5)])
    out = tmp_path / "out"
    assert run_main(tools.curves.main, [str(a), "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} >= {"curves.json", "curves.md", "curves.png"}
    assert "| 2 | 2.0 | 0.500 | 0.600 | 0.250 |" in (out / "curves.md").read_text()
    bare = _run(tmp_path, "bare", "second", 0, [(60, None)])
    assert run_main(tools.curves.main, [str(bare), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "holds no epoch evaluated" in err and "train.eval_every" in err and not (tmp_path / "o2").exists()
