"""A finished study's outputs read into one dict, written as study.json: everything study.md states.

`study_results(plan, seconds)` reads what the jobs of a `StudyPlan` wrote (the ability study, the
split counts, every evaluation report, the combined report, the runs' histories) and computes
once what the report shows of them: the summary (detbench.studies.study_summary), the splits held
against the ability study (detbench.studies.split_check), the cross-height matrices
(detbench.studies.cross_height) and, with several seeds, the seed statistics
(detbench.studies.seeds). study.md is rendered from that dict alone
(detbench.studies.study_report.study_markdown). Fractions in [0, 1]; heights in metres (as keys:
their text, e.g. "1.8"); times in seconds or minutes as the key says.

What it holds, besides the summary's and the statistics' own layouts: "data_info" (the dataset's
frames), "test_data" and "test_data_info" (the dataset whose test split the evaluations read, None for
the training data's own), "splits" (each split's frames and scenes), "evaluation" (the reports' IoU kind and
thresholds), "ranges" (the extents of detbench.data.regions), "preset_facts" (each model's epochs
at the preset, the paper preset's frames and epochs), "run_minutes" (each model and height's
training minutes, the mean over seeds), "ap_r40_small" (the primary seed's AP@R40 per model and
height, small range, all vehicles), "not_learned" (the models below NOT_LEARNED_AP at every
height), "markdown" (the ability study's and the combined report's own tables), "report_files"
and "figures" (paths relative to the study's folder).
"""
from __future__ import annotations

from pathlib import Path

from detbench.data.frame import key_text
from detbench.data.regions import RANGES
from detbench.studies.cross_height import cross_height_matrix
from detbench.studies.seeds import seed_statistics
from detbench.studies.split_check import compare_splits
from detbench.studies.study_plan import StudyPlan
from detbench.studies.study_summary import NOT_LEARNED_AP, detector_summary, height_summary, unlearned_models
from detbench.train.run_layout import training_seconds
from detbench.utils.atomic import read_json

SPLITS = ("train", "test")
CROSS_HEIGHT = (("ap_r40", "small"), ("recall", "large"))  # (metric, range) of each cross-height matrix


def cross_height_figure(out: Path, metric: str, range_name: str) -> Path:
    return out / "cross_height" / f"cross_height_{metric}_{range_name}.png"


def study_results(plan: StudyPlan, seconds: float) -> dict:
    """study.json's content for the finished study of `plan` (see the module's docstring); `seconds`: this
    invocation's wall time."""
    out = plan.out
    ability = read_json(out / "ability" / "ability.json")
    splits = {name: read_json(out / "splits" / f"{name}.json") for name in SPLITS}
    by_run = {(m, h): read_json(plan.report(m, h, plan.primary)) for m in plan.models for h in plan.heights}
    reports = list(by_run.values())
    # training time per model: the epochs' own seconds from each run's history.json, so a training that was
    # stopped and resumed counts every invocation's epochs; per model and height the minutes of each seed
    train_min = {(m, h): [training_seconds(plan.run_dir(m, h, s)) / 60.0 for s in plan.seeds]
                 for m in plan.models for h in plan.heights}
    train_s = {m: 60.0 * sum(sum(train_min[(m, h)]) for h in plan.heights) for m in plan.models}
    first = reports[0] if reports else {}
    info = plan.data_info
    study = {"preset": plan.preset, "data": str(plan.data_root), "heights": list(plan.heights),
             "models": list(plan.models), "left_out": list(plan.left_out),
             "data_fingerprints": {str(h): fp for h, fp in plan.data_fingerprints.items()},
             "ability_frames": plan.ability.frames or None, "test_frames": first.get("num_frames", 0),
             "test_scenes": (first.get("uncertainty") or {}).get("num_clusters"),
             "seconds_this_invocation": round(seconds, 1),
             "train_seconds": {m: round(t, 1) for m, t in train_s.items()},
             "summary": {"heights": height_summary(ability),
                         "detectors": {str(h): c for h, c in detector_summary(reports).items()}},
             "ability": ability, "detection": read_json(out / "combined" / "combined.json"),
             "split_check": {name: compare_splits(rep, ability) for name, rep in splits.items()}}
    if plan.cross_height:
        cross = [read_json(plan.report(m, h, plan.primary, t))
                 for m in plan.models for h in plan.heights for t in plan.heights]
        study["cross_height"] = [cross_height_matrix(cross, metric, r, "all") for metric, r in CROSS_HEIGHT]
    if len(plan.seeds) > 1:
        study["seeds"] = _seed_section(plan, train_min)
    figures = set(out.glob("*/*.png")) | ({cross_height_figure(out, *c) for c in CROSS_HEIGHT}
                                          if plan.cross_height else set())
    facts = plan.facts
    study.update({
        "primary_seed": plan.primary, "train_seeds": list(plan.seeds),
        "data_info": _info_words(info), "test_data": None if plan.test_root is None else str(plan.test_root),
        "test_data_info": _info_words(plan.test_info),
        "splits": {name: {"num_frames": rep["num_frames"],
                          "num_scenes": ((rep.get("extras") or {}).get("uncertainty") or {}).get("num_clusters")}
                   for name, rep in splits.items()},
        "evaluation": {k: first.get(k) for k in ("iou_kind", "iou_threshold", "score_threshold")},
        "ranges": {r: {"x_min": x0, "x_max": x1, "abs_y_max": y} for r, (x0, x1, y) in RANGES.items()},
        "preset_facts": None if facts is None else {"epochs": dict(facts.epochs), "paper_frames": facts.paper_frames,
                                                    "paper_epochs": dict(facts.paper_epochs)},
        "run_minutes": {f"{m} {key_text(h)}": round(sum(v) / len(v), 2) for (m, h), v in train_min.items()},
        "ap_r40_small": {m: {key_text(h): by_run[(m, h)]["results"]["small"]["all"]["ap_r40"] for h in plan.heights}
                         for m in plan.models},
        "not_learned": {"below_ap_r40": NOT_LEARNED_AP, "models": unlearned_models(reports)},
        "markdown": {"ability": (out / "ability" / "ability.md").read_text(encoding="utf-8"),
                     "detection": (out / "combined" / "combined.md").read_text(encoding="utf-8")},
        "report_files": [str((plan.report(m, h, plan.primary).parent / "report.md").relative_to(out))
                         for m in plan.models for h in plan.heights],
        "figures": [str(p.relative_to(out)) for p in sorted(figures)]})
    return study


def _info_words(info) -> dict | None:
    """What study.md states of a dataset.json: its frames and frames per scene (None without one)."""
    if not info:
        return None
    return {"num_frames": info.get("num_frames"), "frames_per_scene": info.get("frames_per_scene")}


def _seed_section(plan: StudyPlan, train_min: dict) -> dict:
    """study["seeds"]: the seed statistics of detbench.studies.seeds (computed once), keyed by height text."""
    groups = {}
    for m in plan.models:
        for h in plan.heights:
            groups[(m, h)] = []
            for seed in plan.seeds:
                rep = read_json(plan.report(m, h, seed))
                rep.setdefault("train_seed", seed)  # how the seed statistics name each run
                groups[(m, h)].append(rep)
    minutes = {k: sum(v) / len(v) for k, v in train_min.items()}
    stats = seed_statistics(groups, minutes)
    return {"seeds": list(plan.seeds), "by_height": {f"{key_text(h)}": c for h, c in stats["by_height"].items()},
            "by_model": stats["by_model"], "pairs": {f"{key_text(h)}": c for h, c in stats["pairs"].items()},
            "height_pairs": stats["height_pairs"],
            "train_minutes": {f"{m} {key_text(h)}": round(t, 2) for (m, h), t in minutes.items()},
            "table": stats["table"]}


__all__ = ["CROSS_HEIGHT", "SPLITS", "cross_height_figure", "study_results"]
