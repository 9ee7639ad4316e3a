"""The evaluator's report on fixed frames against the report it wrote before (tests/eval/golden/): every count,
recall, AP@R40, extra variant and bootstrap interval stays what it was. A change of the evaluator that moves a
figure fails here; regenerate the file (`python -m tests.eval.test_evaluate_golden`) only when the change of
figures is the point, and say so in the commit."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from detbench.eval import EvalFrame, evaluate

GOLDEN = Path(__file__).with_name("golden") / "evaluate_report.json"


def golden_frames() -> list[EvalFrame]:
    """Four scenes of five frames: cars in three lanes out to 160 m, some without points, jittered hits,
    duplicates and false positives, scores on a coarse grid (ties) and around the 0.1 threshold."""
    rng = np.random.default_rng(2024)
    frames = []
    for s in range(4):
        for f in range(5):
            n = int(rng.integers(0, 10))
            lane = rng.choice([-1, 0, 0, 1, 2, 99], n)
            y = np.where(np.abs(lane) < 10, lane * 3.5, rng.uniform(-20, 20, n)) + rng.normal(0, 0.4, n)
            x = rng.uniform(-5, 160, n)
            dims = np.column_stack([rng.uniform(3.8, 11, n), rng.uniform(1.7, 2.5, n), rng.uniform(1.4, 3.5, n)])
            gt = np.column_stack([x, y, dims[:, 2] / 2, dims, rng.normal(0, 0.2, n)])
            points = np.where(rng.random(n) < 0.75, rng.integers(1, 60, n), 0)
            preds = []
            for i in range(n):
                for _ in range(int(rng.choice([0, 1, 1, 2]))):
                    b = gt[i].copy()
                    b[:3] += rng.normal(0, 0.15, 3)
                    b[3:6] *= rng.normal(1, 0.05, 3)
                    preds.append(b)
            for _ in range(int(rng.integers(0, 5))):
                preds.append(np.array([rng.uniform(0, 150), rng.uniform(-15, 15), 0.8, 4.5, 1.9, 1.6,
                                       rng.uniform(-np.pi, np.pi)]))
            scores = np.round(rng.uniform(0, 1, len(preds)) * 20) / 20
            scores[rng.random(len(preds)) < 0.1] = 0.1
            frames.append(EvalFrame(gt, points, lane, np.array(preds).reshape(-1, 7), scores,
                                    frame_id=f"{s:04d}_{f:03d}", scene_id=f"{s:04d}"))
    return frames


def golden_report() -> dict:
    return json.loads(json.dumps(evaluate(golden_frames(), extras=True, bootstrap=200, bootstrap_seed=3)))


def _same(got, want, where="report"):
    if isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(want), f"{where}: keys {sorted(got)} != {sorted(want)}"
        for k in want:
            _same(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), f"{where}: {got} != {want}"
        for i, (g, w) in enumerate(zip(got, want)):
            _same(g, w, f"{where}[{i}]")
    elif isinstance(want, float) and not isinstance(got, bool):
        assert isinstance(got, (int, float)) and (math.isnan(want) and math.isnan(got)
                                                   or got == pytest.approx(want, rel=1e-12, abs=1e-15)), \
            f"{where}: {got!r} != {want!r}"
    else:
        assert got == want, f"{where}: {got!r} != {want!r}"


def test_report_on_fixed_frames_is_the_golden_one():
    want = json.loads(GOLDEN.read_text(encoding="utf-8"))
    got = golden_report()
    assert got["results"]["large"]["all"]["tp"] > 20 and got["uncertainty"]["num_clusters"] == 4  # not vacuous
    _same(got, want)


if __name__ == "__main__":  # regenerate the golden file
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(golden_report(), indent=1, sort_keys=True) + "\n", encoding="utf-8")
