"""study.md and study.json of a finished study, written without running a job, against the expected files;
and the data behind each of study.md's tables checked against the evaluation reports they come from.

The finished study is tests/studies/data/study/out (made by tests/studies/data/make_study_fixture.py:
three models at three heights, two training seeds, the cross-height evaluations). study.md and study.json
must stay as tests/studies/data/study/expected/ holds them, figure for figure; the dataset's folder, which
depends on where the checkout is, reads DATA there.
"""
from __future__ import annotations

import json
import math
import shutil
from itertools import combinations
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.paper import paper_recall
from detbench.utils.atomic import read_json

FIXTURE = Path(__file__).resolve().parent / "data" / "study"
EXPECTED = FIXTURE / "expected"
MODELS = ["ct3d", "pointrcnn", "second"]
LEFT_OUT = ["pillarnet"]
HEIGHTS = [0.5, 1.0, 1.8]
SEEDS = [0, 1]
SECONDS = 150.0  # the study's wall time in this invocation, as the report states it


def _write_study(out: Path, monkeypatch, seeds=tuple(SEEDS), cross_height=True) -> tuple[str, dict]:
    """(study.md, study.json) of the finished study in `out`: its plan, the outputs read into study.json, and
    study.md rendered from study.json read back; no job runs."""
    import detbench.studies.study_plan as study_plan
    from detbench.studies.stage_inputs import FileHashes
    from detbench.studies.study_plan import build_plan
    from detbench.studies.study_report import study_markdown
    from detbench.studies.study_results import study_results
    from detbench.train.run_config import load_run_config

    root = FIXTURE / "dataset"
    monkeypatch.setattr(study_plan, "dataset_fingerprint", lambda _root, hs, _hashes: "fp " + " ".join(
        f"{h:g}" for h in hs))
    plan = build_plan(preset="smoke", models=MODELS, left_out=LEFT_OUT, heights=HEIGHTS, seeds=list(seeds),
                      base_cfg=load_run_config(MODELS[0], "smoke"), out=out, data_root=root,
                      data_info=read_json(root / "dataset.json"), hashes=FileHashes(out / "hashes.json"),
                      simulated=True, cross_height=cross_height)
    study = json.loads(json.dumps(study_results(plan, SECONDS)))
    (out / "study.json").write_text(json.dumps(study), encoding="utf-8")
    (out / "study.md").write_text(study_markdown(study), encoding="utf-8")
    return _normal(out / "study.md", root), json.loads(_normal(out / "study.json", root))


def _normal(path: Path, root: Path) -> str:
    return path.read_text(encoding="utf-8").replace(str(root), "DATA")


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("study") / "out"
    shutil.copytree(FIXTURE / "out", out)
    with pytest.MonkeyPatch.context() as mp:
        md, study = _write_study(out, mp)
    return SimpleNamespace(out=out, md=md, study=study)


@pytest.fixture(scope="module")
def one_seed(tmp_path_factory):
    """The same study with the config's seed alone and no cross-height evaluations."""
    out = tmp_path_factory.mktemp("study") / "out"
    shutil.copytree(FIXTURE / "out", out)
    with pytest.MonkeyPatch.context() as mp:
        md, study = _write_study(out, mp, seeds=SEEDS[:1], cross_height=False)
    return SimpleNamespace(out=out, md=md, study=study)


def _report(out: Path, model: str, trained: float, seed: int, tested: float | None = None) -> dict:
    run = out / (f"{model}_h{trained:.1f}" + ("" if seed == SEEDS[0] else f"_s{seed}"))
    return read_json(run / f"eval_h{trained if tested is None else tested:.1f}_test" / "report.json")


def _train_seconds(out: Path, model: str, height: float, seed: int) -> float:
    run = out / (f"{model}_h{height:.1f}" + ("" if seed == SEEDS[0] else f"_s{seed}"))
    return sum(e["seconds"] for e in read_json(run / "history.json")["epochs"])


def _same_lines(got: str, want: str) -> None:
    got, want = got.splitlines(), want.splitlines()
    first = next((i for i, (a, b) in enumerate(zip(got, want)) if a != b), min(len(got), len(want)))
    assert got == want, (f"study.md differs from line {first + 1}:\n  got:  {got[first:first + 1]}\n"
                         f"  want: {want[first:first + 1]}")


def _same_json(got: dict, want: dict) -> None:
    assert sorted(got) == sorted(want)
    for key in want:
        assert got[key] == want[key], key


def test_study_md_is_the_expected_one(written, one_seed):
    _same_lines(written.md, (EXPECTED / "study.md").read_text(encoding="utf-8"))
    _same_lines(one_seed.md, (EXPECTED / "study_one_seed.md").read_text(encoding="utf-8"))


def test_study_json_is_the_expected_one(written, one_seed):
    _same_json(written.study, read_json(EXPECTED / "study.json"))
    _same_json(one_seed.study, read_json(EXPECTED / "study_one_seed.json"))


def test_one_seed_has_no_seed_section_and_no_cross_height(one_seed, written):
    assert "seeds" not in one_seed.study and "cross_height" not in one_seed.study
    assert one_seed.study["summary"] == written.study["summary"]  # seed 0's reports, as with two seeds


def test_the_detector_table_holds_each_model_and_heights_seed_mean(written):
    """The detector table's cells: per model and height the mean over seeds of each report's figure, the
    seeds' own figures, two seeds, the training minutes as the mean over seeds of each run's epochs."""
    seeds = written.study["seeds"]
    assert seeds["seeds"] == SEEDS
    for h in HEIGHTS:
        models = seeds["by_height"][f"{h:g}"]["models"]
        assert sorted(models) == MODELS
        for m in MODELS:
            reps = [_report(written.out, m, h, s) for s in SEEDS]
            comb = models[m]
            assert comb["num_seeds"] == 2 and comb["seeds"] == SEEDS
            for r in RANGE_NAMES:
                for lv in LEVELS:
                    for metric in ("recall", "ap_r40"):
                        cell = comb["results"][r][lv][metric]
                        values = [rep["results"][r][lv][metric] for rep in reps]
                        assert cell["per_seed"] == [round(v, 6) for v in values]
                        assert cell["mean"] == pytest.approx(np.mean(values), abs=1e-6)
                        assert cell["ci95"][0] <= cell["mean"] + 1e-6 and cell["mean"] - 1e-6 <= cell["ci95"][1]
            minutes = sum(_train_seconds(written.out, m, h, s) / 60 for s in SEEDS) / len(SEEDS)
            assert seeds["train_minutes"][f"{m} {h:g}"] == round(minutes, 2)
            assert paper_recall(m, h)  # the table's Table VII column has a figure for every cell here


def test_the_seed_spread_is_pooled_over_each_models_heights(written):
    """sd is the pooled spread of a model's heights (df = heights x (seeds - 1)); each height's own sd beside it."""
    by_height = written.study["seeds"]["by_height"]
    for m in MODELS:
        for r in RANGE_NAMES:
            cells = [by_height[f"{h:g}"]["models"][m]["results"][r]["all"]["recall"] for h in HEIGHTS]
            own = [np.std(c["per_seed"], ddof=1) for c in cells]
            pooled = math.sqrt(sum(s * s for s in own) / len(own))
            for c, s in zip(cells, own):
                assert c["seed_df"] == len(HEIGHTS) and c["seed_pool"] == m
                assert c["sd"] == pytest.approx(pooled, abs=2e-6)
                assert c["sd_own"] == pytest.approx(s, abs=2e-6)


def test_the_pairs_rank_by_seed_mean_and_resolve_only_where_the_interval_excludes_0(written):
    pairs = written.study["seeds"]["pairs"]
    by_height = written.study["seeds"]["by_height"]
    resolved = 0
    for h in HEIGHTS:
        for r in RANGE_NAMES:
            for metric, other in (("recall", "ap_r40"), ("ap_r40", "recall")):
                entry = pairs[f"{h:g}"][r][metric]
                cells = {m: by_height[f"{h:g}"]["models"][m]["results"][r]["all"] for m in MODELS}
                order = sorted(MODELS, key=lambda m: (-cells[m][metric]["mean"], -cells[m][other]["mean"]))
                assert [e["model"] for e in entry["ranking"]] == order
                assert [(p["model"], p["over"]) for p in entry["pairs"]] == list(combinations(order, 2))
                for p in entry["pairs"]:
                    diff = cells[p["model"]][metric]["mean"] - cells[p["over"]][metric]["mean"]
                    assert p["diff"] == pytest.approx(diff, abs=2e-6)
                    lo, hi = p["ci95"]
                    assert lo <= p["diff"] + 1e-6 and p["diff"] - 1e-6 <= hi
                    assert p["ahead"] == (lo > 0 or hi < 0)
                    resolved += p["ahead"]
    assert resolved > 0  # the fixture's models differ enough for some leads to be resolved


def test_the_height_answer_holds_every_pair_of_each_models_heights_with_its_paired_interval(written):
    """study.json's "height_pairs": per model every pair of heights in AP@R40 (small) and recall (large), the
    higher seed mean first, the difference of the seed means, the AP@R40 scene interval from the paired scene
    bootstrap of the reports themselves, and the answer; study.md renders it as a table per model."""
    from detbench.eval.ap_bootstrap import paired_ap_difference
    from detbench.eval.bootstrap import percentile_interval
    from detbench.studies.seeds import LEAD_REPLICATES, LEAD_SEED

    seeds = written.study["seeds"]
    answer = seeds["height_pairs"]
    assert sorted(answer) == MODELS
    for m in MODELS:
        reps = {h: [_report(written.out, m, h, s) for s in SEEDS] for h in HEIGHTS}
        for metric, (r, lv) in (("recall", ("large", "all")), ("ap_r40", ("small", "all"))):
            entry = answer[m][metric]
            assert (entry["range"], entry["level"]) == (r, lv)
            means = {h: seeds["by_height"][f"{h:g}"]["models"][m]["results"][r][lv][metric]["mean"] for h in HEIGHTS}
            assert len(entry["pairs"]) == 3 and {frozenset((p["height"], p["over"])) for p in entry["pairs"]} == {
                frozenset(pair) for pair in combinations(HEIGHTS, 2)}
            for p in entry["pairs"]:
                assert means[p["height"]] >= means[p["over"]]
                assert p["diff"] == pytest.approx(means[p["height"]] - means[p["over"]], abs=2e-6)
                lo, hi = p["ci95"]
                if lo > 0 or hi < 0:
                    assert p["answer"] == "resolved" and p["leader"] in (p["height"], p["over"])
                else:
                    assert p["answer"] == "bounded" and p["margin"] == round(max(abs(lo), abs(hi)), 6)
                assert p["scene_method"].startswith("paired scene bootstrap"), p
                if metric == "ap_r40":
                    boot = paired_ap_difference(reps[p["height"]], reps[p["over"]], r, lv, LEAD_REPLICATES, LEAD_SEED)
                    assert p["scene_ci95"] == percentile_interval(boot)
                verdict = (f"resolved: {p['leader']:g} m leads" if p["answer"] == "resolved"
                           else f"bounded: the two differ by less than {p['margin']:.3f}")
                row = (f"| {'Recall large' if metric == 'recall' else 'AP@R40 small'} | {p['height']:g} m - "
                       f"{p['over']:g} m | {p['diff']:+.3f} [{lo:+.3f}, {hi:+.3f}] | {verdict} |")
                assert row in written.md, row
    section = written.md.split("**The height answer, per model**")[1].split("A model (or height) is called")[0]
    assert [ln for ln in section.splitlines() if ln.startswith("*") and ln.endswith("*")] == [f"*{m}*" for m in MODELS]


def test_the_seed_summary_names_the_leader_per_height_and_per_model(written):
    seeds = written.study["seeds"]
    for h in HEIGHTS:
        cell = seeds["by_height"][f"{h:g}"]
        for metric, (r, lv) in (("recall", ("large", "all")), ("ap_r40", ("small", "all"))):
            means = {m: c["results"][r][lv][metric]["mean"] for m, c in cell["models"].items()}
            assert (cell[metric]["range"], cell[metric]["level"]) == (r, lv)
            assert cell[metric]["best"] == max(means, key=lambda m: means[m])
            assert cell[metric]["ranking"][0]["mean"] == max(means.values())
    for m in MODELS:
        entry = seeds["by_model"][m]["recall"]
        means = {h: seeds["by_height"][f"{h:g}"]["models"][m]["results"]["large"]["all"]["recall"]["mean"]
                 for h in HEIGHTS}
        assert entry["best"] == max(means, key=lambda h: means[h])


def test_the_summary_tables_come_from_the_ability_study_and_the_primary_seeds_reports(written):
    summary = written.study["summary"]
    ability = read_json(written.out / "ability" / "ability.json")
    for r in RANGE_NAMES:
        for lv in LEVELS:
            ldr = {h: ability["heights"][h][r][lv]["ldr"] for h in ability["heights"]}
            assert summary["heights"][r][lv]["ldr"] == max(ldr.values())
    for h in HEIGHTS:
        recall = {m: _report(written.out, m, h, SEEDS[0])["results"]["large"]["all"]["recall"] for m in MODELS}
        cell = summary["detectors"][str(h)]
        assert [e["model"] for e in cell["ranking"]] == sorted(MODELS, key=lambda m: -recall[m])
        assert cell["ranking"][0]["recall"] == max(recall.values())


def test_the_cross_height_matrix_holds_each_reports_figure(written):
    mats = {(m["metric"], m["range"]): m for m in written.study["cross_height"]}
    assert sorted(mats) == [("ap_r40", "small"), ("recall", "large")]
    for (metric, r), mat in mats.items():
        assert mat["heights"] == HEIGHTS and mat["models"] == MODELS
        for m in MODELS:
            for i, trained in enumerate(HEIGHTS):
                for j, tested in enumerate(HEIGHTS):
                    rep = _report(written.out, m, trained, SEEDS[0], tested)
                    assert mat["values"][m][i][j] == rep["results"][r]["all"][metric]


def test_the_study_names_what_it_was_run_on(written):
    study = written.study
    assert study["preset"] == "smoke" and study["models"] == MODELS and study["left_out"] == LEFT_OUT
    assert study["heights"] == HEIGHTS and study["seconds_this_invocation"] == SECONDS
    first = _report(written.out, MODELS[0], HEIGHTS[0], SEEDS[0])
    assert study["test_frames"] == first["num_frames"]
    assert study["test_scenes"] == first["uncertainty"]["num_clusters"]
    assert study["train_seconds"] == {
        m: round(sum(_train_seconds(written.out, m, h, s) for h in HEIGHTS for s in SEEDS), 1) for m in MODELS}


def test_the_rules_the_report_states_come_from_the_reports_and_the_regions(written):
    """study.md's IoU and score rule is the reports' own, its range extents detbench.data.regions': another
    evaluation or another extent in study.json changes the text, not a sentence typed in the code."""
    from detbench.data.regions import RANGES
    from detbench.studies.study_report import study_markdown

    first = _report(written.out, MODELS[0], HEIGHTS[0], SEEDS[0])
    study = written.study
    assert study["evaluation"] == {k: first[k] for k in ("iou_kind", "iou_threshold", "score_threshold")}
    assert {r: (e["x_min"], e["x_max"], e["abs_y_max"]) for r, e in study["ranges"].items()} == RANGES
    assert "at 3D IoU >= 0.7 and score >= 0.1;" in written.md
    assert "(every vehicle within 150 m ahead, |y| <= 15 m)" in written.md
    assert "(seed means; small range 0-50 m, moderate 0-100 m, large 0-150 m;" in written.md
    other = json.loads(json.dumps(study))
    other["evaluation"] = {"iou_kind": "bev", "iou_threshold": 0.5, "score_threshold": 0.05}
    other["ranges"]["large"]["x_max"], other["ranges"]["large"]["abs_y_max"] = 120.0, 12.5
    md = study_markdown(other)
    assert "at BEV IoU >= 0.5 and score >= 0.05;" in md and "IoU >= 0.7" not in md.split("## 1.")[0]
    assert "(every vehicle within 120 m ahead, |y| <= 12.5 m)" in md and "large 0-120 m;" in md


def test_the_presets_caveat_takes_its_figures_from_the_config_and_the_studys_results(written):
    """The caveat's frames and epochs are the config's, its minutes and AP@R40 the study's own."""
    from detbench.studies.study_report import preset_caveat
    from detbench.train.run_config import load_run_config

    study = json.loads(json.dumps(written.study))
    epochs = {m: load_run_config(m, "smoke")["train"]["epochs"] for m in MODELS}
    assert study["preset_facts"]["epochs"] == epochs
    assert study["preset_facts"]["paper_frames"] == load_run_config(MODELS[0], "paper")["data"]["frames"]
    smoke = preset_caveat(study)
    assert f"{study['data_info']['num_frames']} frames" in smoke and f"{epochs['ct3d']} epochs" in smoke
    study["preset"] = "quick"
    study["preset_facts"]["epochs"] = {"ct3d": 5, "pointrcnn": 6, "second": 4}
    learned = [ap for m, by_h in study["ap_r40_small"].items() if m != "pointrcnn" for ap in by_h.values()]
    minutes = [v for v in study["run_minutes"].values()]
    quick = preset_caveat(study)
    assert f"reach AP@R40 {min(learned):.2f}-{max(learned):.2f} here" in quick  # pointrcnn has not learned
    assert f"4-6 epochs (ct3d 5, pointrcnn 6, second 4) ({min(minutes):.1f}-{max(minutes):.1f} minutes" in quick
    assert "The ability figures are at the paper's scale" not in quick  # the ability study ran on the data
    study["preset"] = "cpu"
    assert f"({min(minutes):.1f}-{max(minutes):.1f} minutes per model and height here)" in preset_caveat(study)
    assert not any(word in smoke + quick for word in ("a few", "near 0", "0.4-0.7", "7-16"))
