"""The LiDAR detection-ability study per rig (tools/analyze.py --rigs): the LDR cells of a height, per rig,
plus the near field (detbench.studies.near_field) and, with the small-object probe, the small objects' LDR.

Every rig sees the same simulated instants (one simulator run with all rigs), so rigs compare on the same
traffic. The report's "rigs" maps each rig's name to its LDR cells (range -> level -> total, detected, ldr,
as "heights" does for a height) and to its near field: "blind_zone_m", "self_hits" (rays the ego's body
takes from each sensor), "near_field" (LDR by distance ring and bearing sector, 0-30 m in the front half)
and, with the probe, "small_objects".
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

from detbench.data.frame import DEFAULT_LANE_WIDTH
from detbench.data.regions import LEVELS, RANGE_NAMES
from detbench.studies.ability import DEFAULT_THRESHOLDS, AbilityStudy
from detbench.studies.near_field import BLIND_ZONE_DIRECTIONS, NearFieldCounts, blind_zones
from detbench.utils.cli import UserError


@dataclass
class RigAbilityOptions:
    """tools/analyze.py --rigs: the rigs by name (of `rig_file`, configs/rigs.yaml by default) and the run."""

    simulate: int
    rigs: list[str]
    rig_file: str | None = None
    seed: int = 0
    preset: str = "paper"
    overrides: list[str] = field(default_factory=list)
    frames_per_scene: int | None = None
    thresholds: list[int] = field(default_factory=lambda: list(DEFAULT_THRESHOLDS))
    distance_bin: float = 10.0
    bootstrap: int = 1000
    small_objects: bool = False
    no_progress: bool = False


def load_selected_rigs(names: list[str], rig_file: str | None) -> list:
    """The named rigs of the rig file (`detbench.sim.run.run_rigs`); UserError names the file and the known rigs."""
    from detbench.sim.run import run_rigs

    try:
        return run_rigs(names, rig_file)
    except ValueError as e:  # ConfigError of the rig file included
        raise UserError(str(e)) from None


def _reference_body(rigs: list):
    """The body the blind zones are measured around: the rig file's (every rig of a file shares it)."""
    from detbench.sim.rigs import RIGS_CONFIG, load_rigs

    for r in rigs:
        if r.body is not None:
            return r.body
    shipped = next((r.body for r in load_rigs(RIGS_CONFIG).values() if r.body is not None), None)
    if shipped is None:
        raise UserError("no rig file body: section to measure the blind zones around")
    return shipped


def run_rig_ability(opts: RigAbilityOptions) -> tuple[dict, float]:
    """Simulate `opts.simulate` instants seen by every rig and count them: (the report, seconds)."""
    from tqdm import tqdm

    from detbench.config import ConfigError
    from detbench.data.layout import sim_calibration
    from detbench.sim import HighwaySimulator, load_sim_config

    if opts.simulate < 1:
        raise UserError("--simulate needs a positive number of frames")
    rigs = load_selected_rigs(opts.rigs, opts.rig_file)
    try:
        study = AbilityStudy(thresholds=opts.thresholds, distance_bin=opts.distance_bin, lane_width=DEFAULT_LANE_WIDTH,
                             keep_example=False, bootstrap=opts.bootstrap)
        cfg = load_sim_config(opts.preset, overrides=tuple(opts.overrides))
    except (ValueError, ConfigError) as e:
        raise UserError(str(e)) from None
    fps = opts.frames_per_scene if opts.frames_per_scene is not None else int(cfg["scene"]["frames_per_scene"])
    near = NearFieldCounts()
    probe = None
    if opts.small_objects:
        from detbench.studies.small_objects import SmallObjectCounts

        probe = SmallObjectCounts()
    names = [r.name for r in rigs]
    t0 = time.perf_counter()
    sim = HighwaySimulator(cfg, seed=opts.seed)
    stream = sim.run(opts.simulate, rigs, frames_per_scene=fps, with_points=False, small_objects=opts.small_objects)
    for frames in tqdm(stream, total=opts.simulate, desc="simulate+count", unit="frame", disable=opts.no_progress,
                       smoothing=0.05):
        study.add(frames, counts=[f.hit_counts for f in frames], keys=names)
        for name, f in zip(names, frames):
            near.add(name, f.boxes, f.hit_counts)
            if probe is not None:
                probe.add(name, f.probe_boxes, f.probe_kinds, f.probe_counts, f.probe_places)
    seconds = time.perf_counter() - t0
    body = _reference_body(rigs)
    source = {"kind": "simulator", "preset": opts.preset, "calibration": sim_calibration(cfg), "seed": opts.seed,
              "frames": opts.simulate, "overrides": list(opts.overrides), "frames_per_scene": fps,
              "counting": "simulator hit counts (no points)", "rig_file": opts.rig_file or "configs/rigs.yaml",
              "rigs": {r.name: r.describe() for r in rigs}, "small_objects": opts.small_objects,
              "sim_timings_s": {k: round(v, 2) for k, v in sim.timings.items()}}
    report = study.report(source=source)
    cells = report.pop("heights")
    report["extras"].pop("paper_table_iv", None)
    nf = near.report()
    per_rig = {}
    for r in rigs:
        zones = blind_zones(r, body)
        per_rig[r.name] = {**cells[r.name], "blind_zone_m": zones["blind_zone_m"], "self_hits": zones["self_hits"],
                           "per_sensor": zones["per_sensor"], "near_field": nf["rigs"][r.name]}
        if probe is not None:
            per_rig[r.name]["small_objects"] = probe.report(r.name)
    report = {"num_frames": report["num_frames"], "rigs": per_rig,
              "near_field_definitions": {k: v for k, v in nf.items() if k != "rigs"} | {
                  "blind_zone": "nearest noise-free ground return on an empty road, from the body's outline "
                                "(ahead: x of the nearest return in front within the car's width; front_left/"
                                "front_right: distance from the front corner; left/right: distance from the side "
                                "beside the car); null: no ground return there",
                  "body": dataclasses.asdict(body)},
              "extras": report["extras"]}
    if probe is not None:
        report["small_object_definitions"] = probe.definitions()
    report["extras"]["run"] = {"seconds": round(seconds, 2),
                               "frames_per_second": round(opts.simulate / seconds, 1) if seconds > 0 else None}
    return report, seconds


def _fmt(v, digits=2) -> str:
    return "-" if v is None or v != v else f"{v:.{digits}f}"


def rig_markdown(report: dict) -> str:
    """Markdown of a rig report: LDR cells per rig, blind zones and self hits, the near field, small objects."""
    rigs = list(report["rigs"])
    out = ["# LiDAR detection ability per rig", "",
           f"{report['num_frames']} frames; rigs {', '.join(rigs)} (configs/rigs.yaml or the --rig-file), all on "
           f"the same simulated instants. Detected / total (LDR) per range and level.", ""]
    head = "| Range | Level | " + " | ".join(rigs) + " |"
    out += [head, "|" + "---|" * (len(rigs) + 2)]
    for r in RANGE_NAMES:
        for lv in LEVELS:
            cells = [report["rigs"][n][r][lv] for n in rigs]
            out.append(f"| {r} | {lv} | " + " | ".join(f"{c['detected']} / {c['total']} ({_fmt(c['ldr'])})"
                                                      for c in cells) + " |")
    out += ["", "## Ground blind zone (metres) and rays the body takes", "",
            "| Rig | " + " | ".join(BLIND_ZONE_DIRECTIONS) + " | self hits per sensor |",
            "|" + "---|" * (len(BLIND_ZONE_DIRECTIONS) + 2)]
    for n in rigs:
        z = report["rigs"][n]["blind_zone_m"]
        hits = ", ".join(f"{k} {v}" for k, v in report["rigs"][n]["self_hits"].items())
        out.append(f"| {n} | " + " | ".join(_fmt(z[d]) for d in BLIND_ZONE_DIRECTIONS) + f" | {hits} |")
    nf = report["near_field_definitions"]
    out += ["", f"## Near field: LDR by distance and bearing ({nf['region']})", ""]
    sectors = [f"{a:g}..{b:g} deg" for a, b in nf["sectors_deg"]]
    for n in rigs:
        cell = report["rigs"][n]["near_field"]
        out += [f"**{n}**", "", "| Distance (m) | " + " | ".join(sectors) + " |", "|" + "---|" * (len(sectors) + 1)]
        for i, (a, b) in enumerate(nf["rings_m"]):
            out.append(f"| {a:g}-{b:g} | " + " | ".join(
                f"{d}/{t} ({_fmt(q)})" for d, t, q in zip(cell["detected"][i], cell["total"][i], cell["ldr"][i]))
                + " |")
        out.append("")
    if "small_object_definitions" in report:
        from detbench.studies.small_objects import small_object_markdown

        out += small_object_markdown(report)
    return "\n".join(out) + "\n"


__all__ = ["RigAbilityOptions", "run_rig_ability", "rig_markdown", "load_selected_rigs"]
