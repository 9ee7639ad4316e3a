"""What the report-writing tools' `--out` folders hold, for the one folder-ownership rule
(detbench.utils.folder_ownership): a tool writes its reports only into a folder that is new, empty or
proven to be its kind's (its owner file, or, for a folder written before owner files existed, its
marker and nothing but its own entries), so a report.md, .json or .csv it did not write is never
replaced. `detbench.utils.cli.output_folder` applies it to a tool's --out.
"""
from __future__ import annotations

from detbench.utils.folder_ownership import FolderKind

__all__ = ["ABILITY_FOLDER", "BENCHMARK_FOLDER", "CALIBRATION_FOLDER", "COMBINED_FOLDER", "CURVES_FOLDER",
           "EVAL_FOLDER", "SWEEP_FOLDER"]

FIGURE = r"[A-Za-z0-9_.-]+\.png"  # the figures a report folder holds

# tools/eval.py: one evaluation (and with --ckpt, its predictions in pred/)
EVAL_FOLDER = FolderKind(name="an evaluation", marker="report.json", entries=("report.json", "report.md", "report.csv",
                                                                               "pred", "misses.json", "misses.md"),
                         foreign="written by tools/eval.py", key="eval", patterns=(FIGURE,))

# tools/eval.py --combine: reports merged into one table, with the paper's Fig. 8-10
COMBINED_FOLDER = FolderKind(name="a combined report", marker="combined.json",
                             entries=("combined.json", "combined.md", "combined.csv"),
                             foreign="written by tools/eval.py --combine", key="combined", patterns=(FIGURE,))

# tools/analyze.py: the LiDAR detection ability study
ABILITY_FOLDER = FolderKind(name="an ability study", marker="ability.json",
                            entries=("ability.json", "ability.md", "split_check.json", "split_check.md"),
                            foreign="written by tools/analyze.py", key="ability", patterns=(FIGURE,))

# tools/sweep.py: the height sweep
SWEEP_FOLDER = FolderKind(name="a height sweep", marker="sweep.json", entries=("sweep.json", "sweep.md"),
                          foreign="written by tools/sweep.py", key="sweep", patterns=(FIGURE,))

# tools/check_calibration.py: the simulator against the paper's tables
CALIBRATION_FOLDER = FolderKind(name="a calibration check", marker="calibration.json",
                                entries=("calibration.json", "calibration.md"),
                                foreign="written by tools/check_calibration.py", key="calibration")

# tools/benchmark.py: latency, memory and size of the detectors
BENCHMARK_FOLDER = FolderKind(name="a benchmark", marker="benchmark.json", entries=("benchmark.json", "benchmark.md"),
                              foreign="written by tools/benchmark.py", key="benchmark")

# tools/curves.py: learning curves over training seeds
CURVES_FOLDER = FolderKind(name="learning curves", marker="curves.json", entries=("curves.json", "curves.md"),
                           foreign="written by tools/curves.py", key="curves", patterns=(FIGURE,))
