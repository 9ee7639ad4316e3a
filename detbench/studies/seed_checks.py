"""The checks that a study's evaluation reports can be combined over seeds and compared between models.

Reports of one group (model, height) and all models at one height must come from the same test
split (same scenes, same LiDAR-detected counts, same IoU and score thresholds, same bootstrap
settings); anything else is refused with a ValueError naming the group and seed. A report's
training seed is read from its "train_seed" key when present (else the seeds are numbered by
position: "#1", "#2", ...). `checked_groups` checks a whole study's {(model, height): [report of each
seed]} and returns it by height; the statistics of detbench.studies.seeds run on its output.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

from detbench.data.frame import height_or_rig, key_label, key_order
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.eval.report import check_report


def eval_settings(rep: dict) -> tuple:
    """(iou_kind, iou_threshold, score_threshold) of a report."""
    return (rep.get("iou_kind", "3d"), float(rep["iou_threshold"]), float(rep["score_threshold"]))


def bootstrap_settings(rep: dict) -> tuple | None:
    """(scenes, replicates, seed, confidence) of a report's scene bootstrap, None without one."""
    unc = rep.get("uncertainty")
    if not unc:
        return None
    return (int(unc["num_clusters"]), int(unc["replicates"]), int(unc["seed"]), float(unc.get("confidence", 0.95)))


def _split_signature(rep: dict) -> dict:
    """What two reports on the same test split share: frames, ground truth per range and level,
    and (when bootstrapped) the scenes and their LiDAR-detected counts."""
    sig = {"split": rep.get("split"), "num_frames": int(rep["num_frames"]),
           "ground truth (total, LiDAR detected)": [
               (rep["results"][r][lv]["total"], rep["results"][r][lv]["lidar_detected"])
               for r in RANGE_NAMES for lv in LEVELS]}
    unc = rep.get("uncertainty")
    if unc:
        sig["scenes"] = list(unc["clusters"])
        sig["LiDAR-detected vehicles per scene"] = [
            list(unc["per_cluster"][r][lv]["lidar_detected"]) for r in RANGE_NAMES for lv in LEVELS]
    return sig


def _other_height(a: float | str, b: float | str) -> bool:
    """True when two heights (metres) or rigs (names) differ."""
    if isinstance(a, str) or isinstance(b, str):
        return a != b
    return abs(a - b) > 1e-9


def _name(where: str, i: int, rep: dict) -> str:
    return f"{where} seed {seed_label(rep, i)}"


def seed_label(rep: dict, i: int):
    """The training seed of the `i`-th report of a group: its "train_seed", else "#i+1"."""
    s = rep.get("train_seed")
    return s if s is not None else f"#{i + 1}"


def _check_same(reports: Sequence[dict], where: Sequence[str]) -> None:
    """Raise ValueError unless every report shares the first one's evaluation and test split."""
    ref, ref_where = reports[0], where[0]
    ref_set, ref_boot, ref_sig = eval_settings(ref), bootstrap_settings(ref), _split_signature(ref)
    for rep, w in zip(reports[1:], where[1:]):
        if eval_settings(rep) != ref_set:
            raise ValueError(f"{w}: evaluated with (iou_kind, iou_threshold, score_threshold) = {eval_settings(rep)}, "
                             f"but {ref_where} with {ref_set}; evaluate every seed and model alike")
        boot = bootstrap_settings(rep)
        if (boot is None) != (ref_boot is None):
            has, lacks = (w, ref_where) if boot else (ref_where, w)
            raise ValueError(f"{lacks}: no scene bootstrap ('uncertainty'), but {has} has one; evaluate every "
                             f"seed and model with the same --bootstrap")
        if boot is not None and boot != ref_boot:
            raise ValueError(f"{w}: scene bootstrap (scenes, replicates, seed, confidence) = {boot}, but "
                             f"{ref_where} has {ref_boot}; evaluate every seed and model with the same settings")
        sig = _split_signature(rep)
        for key, value in ref_sig.items():
            if sig.get(key) != value:
                raise ValueError(f"{w} and {ref_where} are not on the same test split: their {key} differ "
                                 f"({_short(sig.get(key))} vs {_short(value)}); evaluate every seed and model on "
                                 f"the same test split of the same data")


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 80 else text[:77] + "..."


def checked_reports(reports: Sequence[dict], where: str) -> list[dict]:
    """The reports of one group (`where` names it), checked: eval reports, one per seed, on one test split."""
    if isinstance(reports, Mapping) or not isinstance(reports, Sequence) or not reports:
        raise ValueError(f"{where}: give a non-empty list of eval reports, one per training seed")
    names = []
    for i, rep in enumerate(reports):
        check_report(rep, f"{where} report {i}")
        names.append(_name(where, i, rep))
    labels = [seed_label(rep, i) for i, rep in enumerate(reports)]
    dup = sorted({str(s) for s in labels if labels.count(s) > 1})
    if dup:
        raise ValueError(f"{where}: training seed(s) {', '.join(dup)} appear more than once; give each seed's "
                         f"report once")
    _check_same(reports, names)
    return list(reports)


def checked_groups(groups: Mapping) -> dict[float, dict[str, list[dict]]]:
    """{height: {model: reports}} (heights sorted) of {(model, height): [report of each seed]}, checked: each
    group as `checked_reports`, each report of its group's model and height, every group evaluated alike, and
    every model at one height on the same test split."""
    if not isinstance(groups, Mapping) or not groups:
        raise ValueError("groups: give a non-empty dict {(model, height): [report of each training seed]}")
    by_height: dict[float, dict[str, list[dict]]] = {}
    first = None
    for key, reports in groups.items():
        try:
            model, height = key
            model, height = str(model), height_or_rig(height)
        except (TypeError, ValueError):
            raise ValueError(f"groups: key {key!r} must be a (model, height in metres) pair") from None
        where = f"{model} at {key_label(height)}"
        reports = checked_reports(reports, where)
        for i, rep in enumerate(reports):
            if rep.get("model") is not None and str(rep["model"]) != model:
                raise ValueError(f"{_name(where, i, rep)}: the report is of model {rep['model']!r}, not {model!r}; "
                                 f"group each model's reports under its own name")
            if rep.get("height") is not None and _other_height(height_or_rig(rep["height"]), height):
                raise ValueError(f"{_name(where, i, rep)}: the report is at height {key_label(rep['height'])}, not "
                                 f"{key_label(height)}; group each height's reports under its own height")
        if first is None:
            first = (where, eval_settings(reports[0]))
        elif eval_settings(reports[0]) != first[1]:
            raise ValueError(f"{where}: evaluated with (iou_kind, iou_threshold, score_threshold) = "
                             f"{eval_settings(reports[0])}, but {first[0]} with {first[1]}; evaluate every model and "
                             f"height alike")
        if model in by_height.setdefault(height, {}):
            raise ValueError(f"groups: {where} is given twice; give each (model, height) once")
        by_height[height][model] = reports
    for h, models in by_height.items():
        names = list(models)
        firsts = [models[m][0] for m in names]
        _check_same(firsts, [_name(f"{m} at {key_label(h)}", 0, models[m][0]) for m in names])
    return dict(sorted(by_height.items(), key=lambda hm: key_order(hm[0])))


__all__ = ["bootstrap_settings", "checked_groups", "checked_reports", "eval_settings", "seed_label"]
