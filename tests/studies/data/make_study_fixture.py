"""Writes the finished study of tests/studies/data/study/out: the files the study's report reads.

Run from the checkout root: `python3 tests/studies/data/make_study_fixture.py`. The evaluation
reports come from the real evaluator (`detbench.eval.evaluate` with a scene bootstrap) on
hand-built frames: each model finds a share of the vehicles that depends on the model, the height
it was trained at, the height it is tested at and its training seed, and a lower height hides the
far vehicles from the LiDAR. The ability study and the split counts (out/ability/, out/splits/)
and dataset/dataset.json are a smoke study's own files, kept as they are; this script does not
touch them. Each run's history.json holds two epochs whose seconds the study sums.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent / "study"
sys.path.insert(0, str(HERE.parents[3]))

from detbench.eval.evaluate import EvalFrame, evaluate  # noqa: E402
from detbench.eval.run import combine_report_files  # noqa: E402
from detbench.train.run_layout import eval_report_path, study_run_dir  # noqa: E402
from detbench.utils.atomic import atomic_write_json  # noqa: E402

MODELS = {"ct3d": 0.8, "second": 0.6, "pointrcnn": 0.04}  # the share of vehicles each finds
HEIGHTS = (0.5, 1.0, 1.8)
SEEDS = (0, 1)  # seed 0 is the config's train.seed: its runs keep the folder <model>_h<height>
SCENES = ("0002", "0005", "0007", "0009")
# Vehicles of every frame: (x, y, lane); the small range holds the first three, the large range all.
VEHICLES = ((9.0, 0.0, 0), (21.0, 3.5, 1), (34.0, -3.5, -1), (62.0, 0.0, 0), (80.0, 3.5, 1), (110.0, -7.0, -2),
            (130.0, 0.0, 0))
HIDDEN = {0.5: (5, 6), 1.0: (6,), 1.8: ()}  # vehicles without a LiDAR point at that height
SIZE = (4.5, 1.8, 1.5)
REPLICATES = 1000


def _box(x: float, y: float) -> list[float]:
    return [x, y, SIZE[2] / 2, *SIZE, 0.0]


def report(model: str, trained: float, tested: float, seed: int) -> dict:
    skill = max(0.0, MODELS[model] - 0.15 * abs(trained - tested) + (0.06 if seed else 0.0))
    rng = np.random.default_rng([int(MODELS[model] * 1000), int(trained * 10), int(tested * 10), seed])
    frames = []
    for scene in SCENES:
        for k in range(2):
            gt = np.array([_box(x, y) for x, y, _ in VEHICLES])
            points = np.array([0 if i in HIDDEN[tested] else 25 for i in range(len(VEHICLES))])
            found = (rng.random(len(VEHICLES)) < skill) & (points > 0)
            pred = [_box(x, y) for (x, y, _), f in zip(VEHICLES, found) if f] + [_box(45.0, 0.0)]
            scores = np.concatenate([rng.uniform(0.3, 1.0, int(found.sum())), rng.uniform(0.1, 0.6, 1)])
            frames.append(EvalFrame(gt, points, np.array([v[2] for v in VEHICLES]), np.array(pred), scores,
                                    frame_id=f"{scene}_{k}", scene_id=scene))
    rep = evaluate(frames, bootstrap=REPLICATES, bootstrap_seed=0)
    run = study_run_dir(Path("OUT"), model, trained, None if seed == 0 else seed)
    return {"model": model, "height": tested, "split": "test", "data": "DATA",
            "data_source": {"kind": "simulator", "calibration": "v2", "seed": 0, "preset": "paper", "overrides": []},
            "predictions": f"{run}/checkpoints/epoch_002.pt", **rep, "trained_height": trained,
            "predictions_dir": f"{eval_report_path(run, tested).parent}/pred", "stage": "refined",
            "train_seed": seed, "train_preset": "smoke"}


def main() -> None:
    out = HERE / "out"
    primary = []
    for model in MODELS:
        for h in HEIGHTS:
            for seed in SEEDS:
                run = study_run_dir(out, model, h, None if seed == 0 else seed)
                minutes = 0.2 * (1 + list(MODELS).index(model)) + 0.05 * seed + 0.1 * h
                atomic_write_json(run / "history.json", {"epochs": [
                    {"epoch": e + 1, "seconds": round(30.0 * minutes, 3)} for e in range(2)]})
                for t in (HEIGHTS if seed == 0 else (h,)):
                    path = eval_report_path(run, t)
                    atomic_write_json(path, report(model, h, t, seed))
                    if seed == 0 and t == h:
                        primary.append(path)
    os.chdir(out)  # combined.json names its sources relative to the study's folder
    combine_report_files([p.relative_to(out) for p in primary], Path("combined"), figures=False)
    Path("combined/combined.csv").unlink()


if __name__ == "__main__":
    main()
