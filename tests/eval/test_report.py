"""Reports: Markdown (Table VII layout), CSV, combining models x heights, figures."""
import csv
import io

import numpy as np
import pytest

from detbench.eval import EvalFrame, evaluate
from detbench.eval.report import (
    check_report,
    combine_reports,
    combined_csv,
    combined_markdown,
    label_variants,
    data_label,
    source_label,
    plot_by_height,
    plot_by_level,
    plot_by_range,
    report_rows,
    report_to_csv,
    report_to_markdown,
    report_variant,
    summary_lines,
)


def car(x, y=0.0):
    return [x, y, 0.8, 4.0, 2.0, 1.6, 0.0]


def make_report(model, height, found, extras=False):
    """Vehicles at x = 10, 20, 30 (ego lane) and 60 (moderate); one undetected (x = 30).
    The model finds the first `found` of the detected ones."""
    gt = [car(10), car(20), car(30), car(60)]
    pts = [5, 5, 0, 5]
    detected = [g for g, p in zip(gt, pts) if p][:found]
    rep = evaluate([EvalFrame(gt, pts, [0, 0, 0, 0], detected, [0.9] * len(detected))], extras=extras)
    return {"model": model, "height": height, "split": "test", **rep}


def test_markdown_single_report():
    rep = make_report("SECOND", 1.8, 2, extras=True)
    md = report_to_markdown(rep, title="T")
    assert md.startswith("# T\n")
    assert "model SECOND, height 1.8 m, split test, 1 frame." in md
    # Small / All: total 3 (x=10, 20, 30), LiDAR detected 2, LDR 0.667, TP 2, recall 1, FP 0, AP 1
    assert "| Small | All | 3 | 2 | 0.667 | 2 | 1.000 | 0 | 1.000 |" in md
    # Small / Top3: only the nearest (x=10) -> total 1, detected 1, TP 1 (the x=20 hit is ignored)
    assert "| Small | Top3 | 1 | 1 | 1.000 | 1 | 1.000 | 0 | 1.000 |" in md
    # Moderate / All: 4 vehicles, 3 detected, 2 found
    assert "| Moderate | All | 4 | 3 | 0.750 | 2 | 0.667 | 0 |" in md
    assert md.count("| Range | Level |") == 4  # main + 3 extras
    assert "## BEV IoU >= 0.7 (extra)" in md


def test_markdown_nulls():
    rep = evaluate([])
    md = report_to_markdown(rep)
    assert "| Small | All | 0 | 0 | n/a | 0 | n/a | 0 | n/a |" in md
    assert "nan" not in md.lower()


def test_csv_round_trip():
    rep = make_report("A", 1.0, 1, extras=True)
    rows = list(csv.DictReader(io.StringIO(report_to_csv(rep))))
    assert len(rows) == 4 * 9
    main = [r for r in rows if r["variant"] == "main"]
    assert len(main) == 9
    small_all = next(r for r in main if r["range"] == "small" and r["level"] == "all")
    assert (small_all["model"], float(small_all["height_m"]), int(small_all["tp"])) == ("A", 1.0, 1)
    assert float(small_all["recall"]) == pytest.approx(0.5)
    empty = list(csv.DictReader(io.StringIO(report_to_csv(evaluate([])))))
    assert empty[0]["recall"] == "" and empty[0]["model"] == ""
    assert len(report_rows(rep)) == 36


def test_summary_lines():
    lines = summary_lines(make_report("A", 1.0, 1))
    assert len(lines) == 4 and "model A" in lines[0] and "recall 0.500" in lines[1]


def reports_grid():
    out = []
    for h, base in ((0.5, 1), (1.0, 1), (1.8, 2)):
        for m, extra in (("PointRCNN", 0), ("CT3D", 1)):
            out.append(make_report(m, h, min(base + extra, 3)))
    return out


def test_combine_and_table_vii_layout():
    reps = reports_grid()
    comb = combine_reports(reps)
    assert comb["heights"] == [0.5, 1.0, 1.8] and comb["models"] == ["PointRCNN", "CT3D"]
    assert len(comb["entries"]) == 6
    md = combined_markdown(reps)
    header = next(line for line in md.splitlines() if line.startswith("| Range"))
    assert header.split(" | ")[4:7] == ["0.5 m LiDAR detected", "0.5 m PointRCNN", "0.5 m CT3D"]
    # Small / All row: Total 3, then per height LiDAR detected 2 and TPs
    assert "| Small | All | Number | 3 | 2 | 1 | 2 | 2 | 1 | 2 | 2 | 2 | 2 |" in md
    assert "|  |  | LDR / Recall |  | 0.67 | 0.50 | 1.00 | 0.67 | 0.50 | 1.00 | 0.67 | 1.00 | 1.00 |" in md
    rows = list(csv.DictReader(io.StringIO(combined_csv(reps))))
    assert len(rows) == 6 * 9 and {r["model"] for r in rows} == {"PointRCNN", "CT3D"}


def test_combine_rejects_inconsistent_reports():
    reps = reports_grid()
    with pytest.raises(ValueError, match="also in") as e:
        combine_reports(reps + [reps[0]])
    assert "training seeds" not in str(e.value)
    # the same model and height from two training seeds: the error says so and how to combine one seed
    with pytest.raises(ValueError, match="training seeds 0 and 1: combine one seed's reports"):
        combine_reports([dict(reps[0], train_seed=0), *reps[1:], dict(reps[0], train_seed=1)])
    no_model = dict(reps[0], model=None)
    with pytest.raises(ValueError, match="no 'model'"):
        combine_reports([no_model])
    no_height = {k: v for k, v in reps[0].items() if k != "height"}
    with pytest.raises(ValueError, match="no 'height'"):
        combine_reports([no_height], sources=["x/report.json"])
    other_thr = dict(reps[1], iou_threshold=0.5)
    with pytest.raises(ValueError, match="like with like"):
        combine_reports([reps[0], other_thr])
    # same height, different ground truth
    other_gt = make_report("X", 0.5, 1)
    other_gt["results"]["small"]["all"] = dict(other_gt["results"]["small"]["all"], lidar_detected=99)
    with pytest.raises(ValueError, match="different data"):
        combine_reports([reps[0], other_gt], sources=["a.json", "b.json"])
    with pytest.raises(ValueError, match="no reports"):
        combine_reports([])
    with pytest.raises(ValueError, match="missing key"):
        check_report({"results": {}})


def test_figures(tmp_path):
    reps = reports_grid()
    paths = [
        plot_by_height(reps, tmp_path / "fig8.png"),
        plot_by_range(reps, tmp_path / "fig9.png"),
        plot_by_level(reps, tmp_path / "fig10.png", metric="ap_r40"),
    ]
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert not list(tmp_path.glob(".tmp-*"))
    with pytest.raises(ValueError, match="metric"):
        plot_by_range(reps, tmp_path / "x.png", metric="precision")
    # reports with null recall (nothing evaluated) still plot
    empty = [{"model": "M", "height": 1.0, **evaluate([])}]
    assert plot_by_level(empty, tmp_path / "empty.png").exists()
    # figures from a single-height report set
    assert plot_by_height([make_report("M", 1.0, 1)], tmp_path / "one.png").exists()
    np.testing.assert_equal(sorted(p.name for p in tmp_path.glob("*.png")),
                            ["empty.png", "fig10.png", "fig8.png", "fig9.png", "one.png"])


def test_figure_titles_name_the_data_source(tmp_path, monkeypatch):
    import detbench.eval.report as rep_mod

    sim = {"kind": "simulator", "calibration": "v2", "seed": 0, "preset": "paper"}
    assert data_label([{"data_source": sim}]) == "simulator calibration v2, seed 0"
    assert data_label([{"data_source": {"kind": "dataset"}}]) == "data on disk"
    assert data_label([{}]) == "data source not recorded"
    mixed = [{"data_source": sim}, {"data_source": {**sim, "seed": 7}}, {"data_source": sim}]
    assert data_label(mixed) == "simulator calibration v2, seed 0 + simulator calibration v2, seed 7"
    other = {**sim, "preset": "v1", "overrides": ["traffic.density_per_km_lane=20"]}
    assert data_label([{"data_source": other}]) == "simulator calibration v2, seed 0, preset v1, --set overrides"
    titles = []
    real_save = rep_mod.save_figure

    def keep_title(fig, path):
        titles.append(fig.get_suptitle())
        return real_save(fig, path)

    monkeypatch.setattr(rep_mod, "save_figure", keep_title)
    reps = [{**r, "data_source": sim} for r in reports_grid()]
    plot_by_height(reps, tmp_path / "a.png")
    plot_by_range(reps, tmp_path / "b.png")
    plot_by_level(reps, tmp_path / "c.png")
    assert len(titles) == 3 and all(t.endswith("(simulator calibration v2, seed 0)") for t in titles)
    assert "simulator calibration v2, seed 0" in report_to_markdown(reps[0])
    assert combine_reports(reps)["data"] == "simulator calibration v2, seed 0"
    assert "Frames: simulator calibration v2, seed 0." in combined_markdown(reps)
    # reports of checkpoints that record their training preset: the titles name it before the world
    trained = [dict(r, train_preset="cpu") for r in reps]
    plot_by_range(trained, tmp_path / "d.png")
    assert titles[-1].endswith("(cpu preset; simulator calibration v2, seed 0)")
    assert source_label(trained[:1] + [dict(reps[1], train_preset="quick")]).startswith("cpu + quick presets; ")
    assert "trained at the cpu preset" in report_to_markdown(trained[0])


def test_combine_refuses_cross_height_and_first_stage_reports_unless_labelled():
    """A checkpoint tested at another height, or a two-stage model's first stage alone, is not a Table VII cell:
    combining it silently would put it in its model's column at the test height. It is refused, naming the
    file and the flag; label_variants makes each a model of its own."""
    reps = reports_grid()
    diag = dict(reps[0], trained_height=0.5, stage="refined")          # PointRCNN trained and tested at 0.5 m
    cross = dict(reps[2], model="CT3D", trained_height=1.8)             # CT3D trained at 1.8 m, tested at 1.0 m
    first = dict(reps[5], stage="proposals", trained_height=1.8)        # CT3D's first stage at 1.8 m
    assert report_variant(diag) is None and report_variant(reps[0]) is None
    assert report_variant(cross) == "trained at 1.8 m"
    assert report_variant(first) == "first stage alone"
    assert report_variant(dict(cross, stage="proposals")) == "trained at 1.8 m; first stage alone"
    kept = [diag, reps[1], reps[3], reps[4]]
    with pytest.raises(ValueError) as e:
        combine_reports(kept + [cross, first], sources=["a", "b", "c", "d", "x/cross.json", "y/first.json"])
    msg = str(e.value)
    assert "x/cross.json (trained at 1.8 m)" in msg and "y/first.json (first stage alone)" in msg
    assert "--with-variants" in msg and "2 of the 6 reports" in msg
    with pytest.raises(ValueError, match="--with-variants"):
        combined_markdown([cross])
    labelled = label_variants(kept + [cross, first])
    assert labelled[0] is diag                                           # the diagonal is unchanged
    comb = combine_reports(labelled)
    assert comb["models"] == ["PointRCNN", "CT3D", "CT3D [trained at 1.8 m]", "CT3D [first stage alone]"]
    assert labelled[4]["variant_of"] == {"model": "CT3D", "trained_height": 1.8, "stage": "refined"}
    header = next(line for line in combined_markdown(labelled).splitlines() if line.startswith("| Range"))
    assert "1.0 m CT3D [trained at 1.8 m]" in header and "1.8 m CT3D [first stage alone]" in header
