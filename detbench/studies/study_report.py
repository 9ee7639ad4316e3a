"""study.md rendered from study.json alone: no file is read and nothing is computed but the text.

`study_markdown(study)` takes the dict of detbench.studies.study_results (or study.json read back)
and returns the report: the summary (which height sees most, which detector finds most, over the
training seeds when there are several), the preset's caveat, the ability study with the splits held
against it, the detectors' table, the cross-height matrices, and the paths of the per-run reports
and figures. The ability study's and the combined report's own tables are embedded as their tools
wrote them, one heading level down, each heading followed by the line naming its data.
`cross_height_file_markdown(study)` is OUT/cross_height/cross_height.md.
"""
from __future__ import annotations

from collections.abc import Mapping

from detbench.studies.cross_height import cross_height_markdown
from detbench.studies.seed_markdown import detector_table_markdown, pairwise_markdown, seed_markdown_lines
from detbench.studies.split_check import split_check_markdown
from detbench.studies.study_summary import detector_summary_markdown, height_summary_lines, unlearned_markdown

# What each preset's detector figures can and cannot show (printed in the study's summary).
PRESET_CAVEATS = {
    "smoke": "*Preset `smoke` proves that the pipeline runs end to end: a few frames, narrow models, two epochs. "
             "Its detectors have not learned; their recall and AP (near 0) say nothing about the models or the "
             "heights. Run `--preset quick` for figures that do.*",
    "quick": "*Preset `quick` trains narrow models for a few minutes each on a small simulated dataset: the "
             "detectors that learn at this budget reach AP@R40 0.4-0.7 and their ranking per height is meaningful "
             "within the intervals shown, but absolute figures are far below the paper's (full models, 8000 frames, "
             "80 epochs). The ability figures are at the paper's scale.*",
    "cpu": "*Preset `cpu` trains each detector 7-16 minutes on one CPU core: absolute "
           "figures are below the "
           "paper's scale; differences between heights and models hold within the intervals shown.*",
    "paper": "*Preset `paper`: the paper's data size and schedule.*",
}


def _data_words(study: Mapping) -> str:
    """The detection data: "`ROOT` (N frames, K per scene)"."""
    info = study.get("data_info")
    words = f"`{study['data']}`"
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
    return (f"*Preset `{study['preset']}`; trained on the train split and {tested} of {_data_words(study)}: "
            f"{study['test_frames']} test frames" + (f" from {scenes} scenes" if scenes else "") + ".*")


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
    return (f"Heights: {', '.join(f'{h:g} m' for h in study['heights'])}. Models: {', '.join(study['models'])}. "
            f"Detection data: {_data_words(study)}. Ran {study['seconds_this_invocation'] / 60:.1f} min in this "
            f"invocation. {train_words}")


def _seed_lines(study: Mapping) -> list[str]:
    """The section over the training seeds (none with one seed)."""
    seeds = study.get("seeds")
    if not seeds:
        return []
    return [f"**Over the training seeds** {', '.join(map(str, study['train_seeds']))} (the lines above are seed "
            f"{study['primary_seed']}'s alone): each model and height's mean over seeds, its interval holding both "
            f"the test-scene bootstrap and the seed-to-seed spread.", "",
            "**Which detector** (seed means; small range 0-50 m, moderate 0-100 m, large 0-150 m; training "
            "minutes: the mean over seeds of each run's training epochs):", "",
            *detector_table_markdown(seeds["table"]), "", *pairwise_markdown(seeds["pairs"]), "",
            *seed_markdown_lines(seeds["by_height"], seeds["by_model"]), ""]


def _summary(study: Mapping) -> list[str]:
    source_ability = f"*Preset `{study['preset']}`; data: {_ability_words(study)}.*"
    left_out = study["left_out"]
    add_left_out = f"--models {' '.join(sorted(set(study['models']) | set(left_out)))}"
    not_learned = study["not_learned"]
    return ["## Summary", "",
            "**Which height sees the most vehicles?** LiDAR detection rate (LDR: vehicles with >= 1 point / all "
            "vehicles), best height per importance level and range, and its paired lead over the next height "
            "(95 % scene-bootstrap interval).", "", source_ability, "",
            *height_summary_lines(study["ability"]), "",
            "**Which detector finds the most LiDAR-detected vehicles?** Per height, the model with the highest "
            "recall of the LiDAR-detected vehicles in the large range (every vehicle within 150 m ahead, "
            "|y| <= 15 m), at 3D IoU >= 0.7 and score >= 0.1; intervals from a bootstrap over test scenes, the "
            "lead paired over the same scenes.", "", _detect_source(study), "",
            *detector_summary_markdown(study["summary"]["detectors"]), "",
            *_seed_lines(study),
            *unlearned_markdown(not_learned["models"], not_learned["below_ap_r40"]),
            *([f"*Not in this study: {', '.join(left_out)} (the preset's `study.models`, "
               f"configs/presets/{study['preset']}.yaml, says why); add it with `{add_left_out}`.*", ""]
              if left_out else []),
            PRESET_CAVEATS.get(study["preset"], ""), "",
            "Paper-scale figures (8000 frames, full models, 80 epochs; a GPU): "
            "`python tools/study.py --preset paper --device cuda`.", ""]


def _ability_section(study: Mapping) -> list[str]:
    source_ability = f"*Preset `{study['preset']}`; data: {_ability_words(study)}.*"
    lines = ["## 1. LiDAR detection ability", "", _embed(study["markdown"]["ability"], source_ability), "",
             "### The splits against the ability study", "",
             "The detection dataset's splits counted like the ability study (all vehicles; 95 % scene-bootstrap "
             "intervals): a test split that holds other traffic than the ability study scores the detectors on "
             "another world.", "",
             f"*Preset `{study['preset']}`; the train and test splits of {_data_words(study)}, against the ability "
             f"study ({_ability_words(study)}).*", ""]
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


__all__ = ["PRESET_CAVEATS", "cross_height_file_markdown", "study_markdown"]
