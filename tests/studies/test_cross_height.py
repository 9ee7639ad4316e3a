"""The cross-height matrix (rows trained at, columns tested at) of the study's --cross-height."""
from __future__ import annotations

import pytest

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies.cross_height import cross_height_markdown, cross_height_matrix, plot_cross_height


def _rep(model, trained, tested, ap):
    res = {r: {lv: {"ap_r40": ap, "recall": ap + 0.1} for lv in LEVELS} for r in RANGE_NAMES}
    return {"model": model, "trained_height": trained, "height": tested, "results": res}


def _reports():
    out = []
    for m, bonus in (("second", 0.0), ("ct3d", 0.1)):
        for tr in (0.5, 1.8):
            for te in (0.5, 1.8):
                out.append(_rep(m, tr, te, (0.6 if tr == te else 0.2) + bonus))
    return out


def test_matrix_rows_are_training_heights_and_columns_test_heights():
    reps = _reports() + [_rep("second", 1.0, 1.8, 0.33)]
    mat = cross_height_matrix(reps, "ap_r40", "small", "all")
    assert mat["heights"] == [0.5, 1.0, 1.8] and mat["models"] == ["second", "ct3d"]
    v = mat["values"]["second"]
    assert v[0][0] == 0.6 and v[0][2] == 0.2 and v[2][2] == 0.6
    assert v[1][2] == 0.33 and v[1][0] is None and v[2][1] is None  # trained at 1.0, tested at 1.8 only
    rec = cross_height_matrix(reps, "recall", "large", "all")
    assert rec["values"]["ct3d"][0][0] == pytest.approx(0.8)


def test_markdown_bolds_the_diagonal_and_the_figure_is_written(tmp_path):
    mat = cross_height_matrix(_reports())
    md = "\n".join(cross_height_markdown(mat))
    assert "| 0.5 m | **0.600** | 0.200 |" in md and "| 1.8 m | 0.300 | **0.700** |" in md
    path = plot_cross_height(mat, tmp_path / "x.png")
    assert path.is_file() and path.stat().st_size > 1000
    assert mat["data"] == "data source not recorded"


def test_the_figure_title_names_the_data_source(tmp_path, monkeypatch):
    import detbench.studies.cross_height as ch

    sim = {"kind": "simulator", "calibration": "v2", "seed": 0, "preset": "paper"}
    mat = cross_height_matrix([{**r, "data_source": sim} for r in _reports()])
    assert mat["data"] == "simulator calibration v2, seed 0"
    titles = []
    real_save = ch.save_figure
    monkeypatch.setattr(ch, "save_figure", lambda fig, path: titles.append(fig.get_suptitle()) or real_save(fig, path))
    plot_cross_height(mat, tmp_path / "y.png")
    assert titles == ["AP@R40, small range, all level (red: same height; simulator calibration v2, seed 0)"]
    # reports of checkpoints that record their training preset (as tools/eval.py writes them): named first
    trained = cross_height_matrix([{**r, "data_source": sim, "train_preset": "cpu"} for r in _reports()])
    assert trained["data"] == "cpu preset; simulator calibration v2, seed 0"
    plot_cross_height(trained, tmp_path / "z.png")
    assert titles[-1] == ("AP@R40, small range, all level (red: same height; cpu preset; simulator calibration v2, "
                          "seed 0)")


def test_bad_reports_are_refused():
    with pytest.raises(ValueError, match="trained_height"):
        cross_height_matrix([{"model": "second", "height": 1.8, "results": {}}])
    with pytest.raises(ValueError, match="two reports"):
        cross_height_matrix([_rep("a", 0.5, 0.5, 0.1), _rep("a", 0.5, 0.5, 0.2)])
    with pytest.raises(ValueError, match="metric"):
        cross_height_matrix(_reports(), metric="f1")
