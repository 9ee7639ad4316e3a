"""The scene bootstrap: 95 % intervals of ratios summed over frames, with scenes (not frames) resampled.

Frames of one simulated scene are 0.5 s apart and strongly correlated, so the unit of resampling
is the scene. The evaluator (recall and AP@R40 intervals), the ability study, the height sweep,
the calibration check and the study's summary all draw with `scene_bootstrap_weights`, so the
same scene count and seed give the same replicates everywhere.
"""
from __future__ import annotations

import numpy as np


def scene_bootstrap_weights(num_clusters: int, replicates: int, seed: int) -> np.ndarray:
    """(replicates, num_clusters) float64: how often each scene is drawn in each bootstrap replicate.

    Scenes are resampled with replacement (a multinomial draw of `num_clusters` out of
    `num_clusters`), seeded, so the same counts and seed give the same intervals. Every
    sum over scenes of a replicate is `weights @ per_scene_values`; the ability study and the
    height sweep (detbench.studies.sweep) use the same draw, so their intervals agree."""
    rng = np.random.default_rng(seed)
    n = int(num_clusters)
    return rng.multinomial(n, np.full(n, 1.0 / n), size=int(replicates)).astype(np.float64)


def bootstrap_ratios(weights: np.ndarray, num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Ratio of resampled sums: (B, ...) = (weights @ num) / (weights @ den), NaN where the
    resampled denominator is 0. weights (B, C); num, den (C, ...) per-scene sums."""
    bn = np.tensordot(weights, np.asarray(num, dtype=np.float64), axes=(1, 0))
    bd = np.tensordot(weights, np.asarray(den, dtype=np.float64), axes=(1, 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(bd > 0, bn / np.where(bd > 0, bd, 1.0), np.nan)


def percentile_interval(samples: np.ndarray, confidence: float = 0.95) -> list | None:
    """[lo, hi] percentile interval (rounded to 6 digits) of the finite bootstrap samples, or None when
    fewer than 2 or fewer than half of them are finite."""
    samples = np.asarray(samples, dtype=np.float64).reshape(-1)
    good = samples[np.isfinite(samples)]
    if good.size < max(2, samples.size // 2):
        return None
    q = (100.0 * (1.0 - confidence) / 2.0, 100.0 * (1.0 + confidence) / 2.0)
    lo, hi = np.percentile(good, q)
    return [round(float(lo), 6), round(float(hi), 6)]


__all__ = ["scene_bootstrap_weights", "bootstrap_ratios", "percentile_interval"]
