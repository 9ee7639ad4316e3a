"""A simulation run as tools/simulate.py makes it: the LiDARs it simulates, the provenance written into
dataset.json, and the run's summary (simulate_run.json and .md) written into the finished dataset."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from detbench.data.frame import height_key
from detbench.data.layout import sim_calibration
from detbench.sim.lidar import LidarConfig, lidar_preset
from detbench.sim.rigs import Rig, load_rigs
from detbench.utils.atomic import atomic_write_json, atomic_write_text

__all__ = ["RunSummary", "run_lidars", "run_rigs", "simulation_source"]

DEFAULT_HEIGHTS = [0.5, 1.0, 1.8]  # the paper's Table II sensors


def run_lidars(names=None, *, range_noise: float | None = None, dropout: float | None = None) -> list[LidarConfig]:
    """LiDAR presets by name or height (default the paper's three heights), with a range noise (metres) and a
    dropout probability for every one when given. ValueError when two share a height (one points folder per
    height)."""
    changes = {}
    if range_noise is not None:
        changes["range_noise_m"] = range_noise
    if dropout is not None:
        changes["dropout"] = dropout
    lidars = [lidar_preset(n, **changes) for n in (names or DEFAULT_HEIGHTS)]
    keys = [height_key(lid.height) for lid in lidars]
    if len(set(keys)) != len(keys):
        raise ValueError(f"LiDAR heights must differ (one points folder per height), got {keys} m")
    return lidars


def run_rigs(names, rig_file=None) -> list[Rig]:
    """Rigs by name from a rig file (configs/rigs.yaml by default); ValueError names the unknown ones."""
    known = load_rigs(rig_file)
    missing = [n for n in names if n not in known]
    if missing:
        raise ValueError(f"--rigs {' '.join(missing)}: not in {rig_file or 'configs/rigs.yaml'}; known: "
                         f"{', '.join(known)}")
    if len(set(names)) != len(names):
        raise ValueError(f"--rigs {' '.join(names)}: each rig once")
    return [known[n] for n in names]


def _key(lid) -> str:
    return lid.name if isinstance(lid, Rig) else height_key(lid.height)


def _described(lid) -> dict:
    return lid.describe() if isinstance(lid, Rig) else lid.to_dict()


def simulation_source(cfg: dict, lidars: list, *, preset: str, seed: int, overrides, frames: int,
                      frames_per_scene: int) -> dict:
    """The `source` of dataset.json: what simulated the data, with which config and LiDARs (or rigs)."""
    src = {"kind": "simulator", "preset": preset, "calibration": sim_calibration(cfg), "seed": seed,
           "overrides": list(overrides), "frames": frames, "frames_per_scene": frames_per_scene}
    rigs = [lid for lid in lidars if isinstance(lid, Rig)]
    src["lidars"] = [lid.to_dict() for lid in lidars if not isinstance(lid, Rig)]
    if rigs:
        src["rigs"] = {r.name: r.describe() for r in rigs}
    src["config"] = cfg
    return src


class RunSummary:
    """Counts what a simulation writes (`tally`, the `on_step` of write_simulation) and writes the summary
    into the finished dataset (`write`, its `finish`); the wall time runs from construction."""

    def __init__(self, out: Path, lidars: list[LidarConfig], *, frames: int, frames_per_scene: int, seed: int,
                 preset: str, overrides=()):
        self.out, self.lidars = Path(out), lidars
        self.frames, self.fps, self.seed, self.preset, self.overrides = frames, frames_per_scene, seed, preset, \
            list(overrides)
        self.t0 = time.perf_counter()
        self.n_points = np.zeros(len(lidars))
        self.n_boxes = 0
        self.n_detected = np.zeros(len(lidars))

    def tally(self, step) -> None:
        """One instant: its frames, one per LiDAR."""
        self.n_boxes += step[0].num_boxes
        for i, f in enumerate(step):
            self.n_points[i] += f.points.shape[0]
            self.n_detected[i] += int((f.hit_counts >= 1).sum())

    def write(self, folder: Path) -> None:
        """simulate_run.json and simulate_run.md in `folder`."""
        frames, fps, out = self.frames, self.fps, self.out
        seconds = time.perf_counter() - self.t0
        scenes = math.ceil(frames / fps)
        report = {
            "out": str(out), "frames": frames, "scenes": scenes, "frames_per_scene": fps, "seed": self.seed,
            "preset": self.preset, "overrides": list(self.overrides), "seconds": round(seconds, 2),
            "frames_per_second": round(frames / max(seconds, 1e-9), 2),
            "boxes_per_frame": round(self.n_boxes / max(frames, 1), 3),
            "heights": {_key(lid): {
                "lidar": _described(lid),
                "points_per_frame": round(float(self.n_points[i]) / max(frames, 1), 1),
                "hit_boxes_per_frame": round(float(self.n_detected[i]) / max(frames, 1), 3),
            } for i, lid in enumerate(self.lidars)},
        }
        atomic_write_json(Path(folder) / "simulate_run.json", report)
        lines = [f"# Simulated dataset: {out}", "",
                 f"{frames} frames in {scenes} scene(s) of {fps}, seed {self.seed}, preset `{self.preset}`"
                 + (f", overrides {', '.join(self.overrides)}" if self.overrides else "") + ".",
                 f"Wall time {seconds:.1f} s ({report['frames_per_second']} frames/s, all heights), "
                 f"{report['boxes_per_frame']} vehicle boxes per frame.", "",
                 "| height (m) | LiDAR | points per frame | boxes with >= 1 point per frame |", "|---|---|---|---|"]
        for hk, h in report["heights"].items():
            lines.append(f"| {hk} | {h['lidar']['name']} | {h['points_per_frame']} | {h['hit_boxes_per_frame']} |")
        atomic_write_text(Path(folder) / "simulate_run.md", "\n".join(lines) + "\n")
