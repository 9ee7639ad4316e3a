"""study.md rendered from study.json alone: no file is read and nothing is computed but the text.

`study_markdown(study)` takes the dict of detbench.studies.study_results (or study.json read back)
and returns the report: the summary (which height sees most, which detector finds most, over the
training seeds when there are several), the preset's caveat, the ability study with the splits held
against it, the detectors' table, the cross-height matrices, and the paths of the per-run reports
and figures. The ability study's and the combined report's own tables are embedded as their tools
wrote them, one heading level down, each heading followed by the line naming its data.
`cross_height_file_markdown(study)` is OUT/cross_height/cross_height.md. Every rule and figure the text
states comes from study.json: the evaluation's IoU and score thresholds from the reports, the range
extents from detbench.data.regions, the preset's frames and epochs from its config, the training
minutes and AP@R40 from the study's own results.
"""
from __future__ import annotations

from collections.abc import Mapping

from detbench.data.frame import key_label
from detbench.studies.cross_height import cross_height_markdown
from detbench.studies.seed_markdown import detector_table_markdown, pairwise_markdown, seed_markdown_lines
from detbench.studies.split_check import split_check_markdown
from detbench.studies.study_summary import detector_summary_markdown, height_summary_lines, unlearned_markdown

def _span(values, digits: int = 0) -> str:
    """"a-b" of the values (one figure when they agree to `digits`); "-" for none."""
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    lo, hi = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
    return lo if lo == hi else f"{lo}-{hi}"


def _epochs(per_model: Mapping[str, int]) -> str:
    return f"{_span(per_model.values())} epochs" + (
        "" if len(set(per_model.values())) < 2 else f" ({', '.join(f'{m} {n}' for m, n in per_model.items())})")


def preset_caveat(study: Mapping) -> str:
    """What the preset's detector figures can and cannot show, with the preset's epochs and frames from its
    config and the training minutes and AP@R40 from the study's own results."""
    preset, facts = study["preset"], study.get("preset_facts")
    if facts is None:
        return ""
    frames = (study.get("data_info") or {}).get("num_frames")
    minutes = _span(study["run_minutes"].values(), 1)
    paper = f"full models, {facts['paper_frames']} frames, {_span(facts['paper_epochs'].values())} epochs"
    if preset == "smoke":
        return (f"*Preset `smoke` proves that the pipeline runs end to end: {frames} frames, narrow models, "
                f"{_epochs(facts['epochs'])}. Its detectors are not trained to learn, so their recall and AP say "
                f"nothing about the models or the heights. Run `--preset quick` for figures that do.*")
    if preset == "quick":
        not_learned = study["not_learned"]["models"]
        aps = [ap for m, by_h in study["ap_r40_small"].items() if m not in not_learned for ap in by_h.values()]
        reach = (f"the detectors that learn at this budget reach AP@R40 {_span(aps, 2)} here (small range, all "
                 f"vehicles)" if aps else "no detector learns at this budget here")
        ability = (" The ability figures are at the paper's scale." if study.get("ability_frames") ==
                   facts["paper_frames"] else "")
        return (f"*Preset `quick` trains narrow models for {_epochs(facts['epochs'])} ({minutes} minutes per model "
                f"and height here) on {frames} simulated frames: {reach}, and their ranking per height is "
                f"meaningful within the intervals shown, but absolute figures are far below the paper's ({paper})."
                f"{ability}*")
    if preset == "cpu":
        return (f"*Preset `cpu` trains each detector {_epochs(facts['epochs'])} on one CPU core ({minutes} minutes "
                f"per model and height here): absolute figures are below the paper's scale ({paper}); differences "
                f"between heights and models hold within the intervals shown.*")
    if preset == "paper":
        return f"*Preset `paper`: the paper's data size and schedule ({paper}).*"
    return ""


def _rules(study: Mapping) -> tuple[str, str, str]:
    """(the large range's extent, the evaluation's IoU and score rule, every range's x extent) as study.md says
    them: "every vehicle within 150 m ahead, |y| <= 15 m", "3D IoU >= 0.7 and score >= 0.1", "small range
    0-50 m, moderate 0-100 m, large 0-150 m"."""
    ranges, ev = study["ranges"], study["evaluation"]
    large = ranges["large"]
    extent = f"every vehicle within {large['x_max']:g} m ahead, |y| <= {large['abs_y_max']:g} m"
    kind = str(ev.get("iou_kind") or "3d").upper()
    rule = f"{kind} IoU >= {ev['iou_threshold']:g} and score >= {ev['score_threshold']:g}"
    spans = ", ".join(f"{r}{' range' if i == 0 else ''} {e['x_min']:g}-{e['x_max']:g} m"
                      for i, (r, e) in enumerate(ranges.items()))
    return extent, rule, spans


def _data_words(study: Mapping, which: str = "data") -> str:
    """The detection data ("data") or the test data ("test_data"): "`ROOT` (N frames, K per scene)"."""
    info = study.get(f"{which}_info")
    words = f"`{study[which]}`"
    if info:
        words += f" ({'?' if info.get('num_frames') is None else info['num_frames']} frames"
        words += f", {info['frames_per_scene']} per scene)" if info.get("frames_per_scene") else ")"
    return words


def _ability_words(study: Mapping) -> str:
    src = (study["ability"].get("extras") or {}).get("source") or {}
    if src.get("kind") == "simulator":
        return (f"{src.get('frames')} frames simulated by the `{src.get('preset')}` simulator preset, seed "
                f"{src.get('seed')}, {src.get('frames_per_scene')} per scene (hit counts, no points)")
    return f"every frame of {_data_words(study)}"


def _detect_source(study: Mapping, tested: str = "tested on the test split") -> str:
    scenes = study.get("test_scenes")
    where = (f"trained on the train split and {tested} of {_data_words(study)}" if not study.get("test_data") else
             f"trained on the train split of {_data_words(study)} and {tested} of {_data_words(study, 'test_data')}")
    return (f"*Preset `{study['preset']}`; {where}: {study['test_frames']} test frames"
            + (f" from {scenes} scenes" if scenes else "") + ".*")


def _embed(markdown: str, source: str) -> str:
    """A tool's Markdown one level below the study's sections, its source under every heading."""
    lines = []
    for ln in markdown.splitlines():
        if ln.startswith("#"):
            lines += ["##" + ln, "", source]
        else:
            lines.append(ln)
    return "\n".join(lines)


def _headline(study: Mapping) -> str:
    seeds = study["train_seeds"]
    train_s = study["train_seconds"]
    train_words = (f"Training time (the runs' epochs, summed over heights{' and seeds' if len(seeds) > 1 else ''}; "
                   "a resumed training counts every invocation; evaluation excluded): "
                   + ", ".join(f"{m} {t / 60:.1f} min" for m, t in train_s.items())
                   + f"; {sum(train_s.values()) / 60:.1f} min in all.")
    return (f"Heights: {', '.join(key_label(h) for h in study['heights'])}. Models: {', '.join(study['models'])}. "
            f"Detection data: {_data_words(study)}."
            + (f" Test data: {_data_words(study, 'test_data')}." if study.get("test_data") else "")
            + f" Ran {study['seconds_this_invocation'] / 60:.1f} min in this "
            f"invocation. {train_words}")


def _seed_lines(study: Mapping) -> list[str]:
    """The section over the training seeds (none with one seed)."""
    seeds = study.get("seeds")
    if not seeds:
        return []
    return [f"**Over the training seeds** {', '.join(map(str, study['train_seeds']))} (the lines above are seed "
            f"{study['primary_seed']}'s alone): each model and height's mean over seeds, its interval holding both "
            f"the test-scene bootstrap and the seed-to-seed spread.", "",
            f"**Which detector** (seed means; {_rules(study)[2]}; training minutes: the mean over seeds of each "
            f"run's training epochs):", "",
            *detector_table_markdown(seeds["table"]), "", *pairwise_markdown(seeds["pairs"]), "",
            *seed_markdown_lines(seeds["by_height"], seeds["by_model"], seeds.get("height_pairs")), ""]


def _summary(study: Mapping) -> list[str]:
    source_ability = f"*Preset `{study['preset']}`; data: {_ability_words(study)}.*"
    left_out = study["left_out"]
    add_left_out = f"--models {' '.join(sorted(set(study['models']) | set(left_out)))}"
    not_learned = study["not_learned"]
    extent, rule, _ = _rules(study)
    facts = study.get("preset_facts") or {}
    paper_scale = (f" ({facts['paper_frames']} frames, full models, {_span(facts['paper_epochs'].values())} epochs; "
                   f"a GPU)" if facts else "")
    return ["## Summary", "",
            "**Which height sees the most vehicles?** LiDAR detection rate (LDR: vehicles with >= 1 point / all "
            "vehicles), best height per importance level and range, and its paired lead over the next height "
            "(95 % scene-bootstrap interval).", "", source_ability, "",
            *height_summary_lines(study["ability"]), "",
            f"**Which detector finds the most LiDAR-detected vehicles?** Per height, the model with the highest "
            f"recall of the LiDAR-detected vehicles in the large range ({extent}), at {rule}; intervals from a "
            f"bootstrap over test scenes, the lead paired over the same scenes.", "", _detect_source(study), "",
            *detector_summary_markdown(study["summary"]["detectors"]), "",
            *_seed_lines(study),
            *unlearned_markdown(not_learned["models"], not_learned["below_ap_r40"]),
            *([f"*Not in this study: {', '.join(left_out)} (the preset's `study.models`, "
               f"configs/presets/{study['preset']}.yaml, says why); add it with `{add_left_out}`.*", ""]
              if left_out else []),
            preset_caveat(study), "",
            f"Paper-scale figures{paper_scale}: `python tools/study.py --preset paper --device cuda`.", ""]


def _ability_section(study: Mapping) -> list[str]:
    source_ability = f"*Preset `{study['preset']}`; data: {_ability_words(study)}.*"
    lines = ["## 1. LiDAR detection ability", "", _embed(study["markdown"]["ability"], source_ability), "",
             "### The splits against the ability study", "",
             "The detection dataset's splits counted like the ability study (all vehicles; 95 % scene-bootstrap "
             "intervals): a test split that holds other traffic than the ability study scores the detectors on "
             "another world.", "",
             f"*Preset `{study['preset']}`; the train and test splits of {_data_words(study)}"
             + (f" (the test split of {_data_words(study, 'test_data')})" if study.get("test_data") else "")
             + f", against the ability study ({_ability_words(study)}).*", ""]
    for name, result in study["split_check"].items():
        split = study["splits"][name]
        lines += [f"**{name.capitalize()} split** ({split['num_frames']} frames, {split['num_scenes']} scenes)", "",
                  *split_check_markdown(result, f"{name} split", "ability study"), ""]
    return lines


def _cross_height_lines(study: Mapping) -> list[str]:
    """The cross-height matrices under the line naming their data (none without cross-height evaluations)."""
    mats = study.get("cross_height")
    if not mats:
        return []
    return [_detect_source(study, "tested on the test split at each height"), "",
            *[ln for mat in mats for ln in cross_height_markdown(mat)]]


def cross_height_file_markdown(study: Mapping) -> str:
    """OUT/cross_height/cross_height.md."""
    return "\n".join(["# Cross-height matrix", "", *_cross_height_lines(study)])


def study_markdown(study: Mapping) -> str:
    """study.md of `study` (study.json's content)."""
    cross = _cross_height_lines(study)
    lines = [f"# Height3 study ({study['preset']} preset)", "", _headline(study), "",
             *_summary(study),
             *_ability_section(study),
             "## 2. Detectors on the LiDAR-detected vehicles (test split)", "",
             _embed(study["markdown"]["detection"], _detect_source(study)), "",
             *(["## 3. Cross-height matrix", "", *cross] if cross else []),
             "Per-run reports with 95 % intervals: " + ", ".join(f"`{p}`" for p in study["report_files"]), "",
             "Figures: " + ", ".join(f"`{p}`" for p in study["figures"]), ""]
    return "\n".join(lines)


__all__ = ["cross_height_file_markdown", "preset_caveat", "study_markdown"]
