"""LiDAR scans for the benchmarks (tools/bench_sparse.py, tools/bench_points.py): the simulator's
1.8 m LiDAR, or a quick synthetic scan (flat road and car-sized boxes) when it is not wanted or
not usable."""
from __future__ import annotations

import numpy as np

from detbench.sim.lidar import lidar_preset
from detbench.sim.simulator import HighwaySimulator, load_sim_config


def synthetic_scan(seed: int, height: float = 1.8, vfov_deg=(-15.0, 10.0), hfov_deg: float = 180.0,
                   channels: int = 128, h_samples: int = 480, max_range: float = 150.0,
                   num_cars: int = 30) -> np.ndarray:
    """Fallback scan: flat road sampled by channels x h_samples beams from ``height`` metres plus
    car-sized axis-aligned boxes on six lanes; (N, 4) float32 x, y, z, intensity (ego ground frame)."""
    rng = np.random.default_rng(seed)
    el = np.deg2rad(np.linspace(vfov_deg[0], vfov_deg[1], channels))
    az = np.deg2rad(np.linspace(-hfov_deg / 2, hfov_deg / 2, h_samples))
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    origin = np.array([0.0, 0.0, height])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[:, 2] < 0, -height / d[:, 2], np.inf)
        lanes = np.array([-8.75, -5.25, -1.75, 1.75, 5.25, 8.75])
        for _ in range(num_cars):
            x = rng.uniform(6.0, max_range)
            y = rng.choice(lanes) + rng.normal(0, 0.25)
            length, width, tall = rng.uniform(4.0, 5.0), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.8)
            lo = np.array([x - length / 2, y - width / 2, 0.0])
            hi = np.array([x + length / 2, y + width / 2, tall])
            t1, t2 = (lo - origin) / d, (hi - origin) / d
            t_near = np.nanmax(np.minimum(t1, t2), axis=1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (t_near <= t_far) & (t_far > 0) & (t_near < t)
            t = np.where(hit, np.maximum(t_near, 0.0), t)
    ok = np.isfinite(t) & (t <= max_range)
    xyz = origin + d[ok] * t[ok, None] + rng.normal(0, 0.01, (int(ok.sum()), 3))
    return np.concatenate([xyz, rng.uniform(0, 1, (len(xyz), 1))], 1).astype(np.float32)


def load_scans(num: int, seed: int, source: str) -> tuple[list[np.ndarray], str]:
    """``num`` scans of the 1.8 m LiDAR and a description of their source: from the simulator
    when ``source`` is "sim" (errors raise) or "auto" (errors fall back to `synthetic_scan`,
    the description says why), the synthetic scan when it is "synthetic"."""
    note = ""
    if source in ("auto", "sim"):
        try:
            sim = HighwaySimulator(load_sim_config("paper"), seed=seed)
            lidar = lidar_preset("h3-1.8")
            scans = [frames[0].points[:, :4].astype(np.float32) for frames in sim.run(num, [lidar])]
            return scans, f"detbench.sim HighwaySimulator (preset paper, lidar h3-1.8, seed {seed})"
        except Exception as exc:  # the simulator is optional here (auto); say why it was not used
            if source == "sim":
                raise
            note = f" (detbench.sim not usable: {type(exc).__name__}: {exc})"
    scans = [synthetic_scan(seed + i) for i in range(num)]
    return scans, ("synthetic: flat road + 30 car boxes, 128 x 480 beams, vfov -15..10 deg, hfov 180 deg, "
                   f"from 1.8 m{note}")


__all__ = ["synthetic_scan", "load_scans"]
