"""Sizes that outgrow the small case: a simulation larger than the disk is refused before it starts, with
the estimate and the free space; figures of many heights give every height its own colour and a legend that
fits inside the saved figure."""
import os
import shutil

import numpy as np
import pytest

from tests.faults.faultkit import run_python


def test_simulation_larger_than_the_disk_is_refused_at_once(tmp_path):
    """A simulation larger than the disk (10^8 frames need hundreds of TB) is refused before it starts: one line
    naming --out's filesystem, the estimate, the free space and the fix, and nothing created."""
    out = tmp_path / "new" / "sim"
    proc = run_python(["tools/simulate.py", "--out", str(out), "--frames", "100000000", "--no-progress"],
                      timeout=60)
    assert proc.returncode == 2, proc.stderr[-3000:]
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: --out {out}: "), proc.stderr
    assert f"the filesystem of {tmp_path} has " in err[0] and " TB on disk" in err[0] and " free;" in err[0]
    assert "give --out on a larger filesystem, or simulate fewer --frames" in err[0]
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_dataset_size_estimate_matches_a_small_simulated_dataset(tmp_path):
    """The estimate is printed before simulating and is within 30 % above what is written (never below)."""
    from detbench.sim.dataset import estimate_dataset_bytes
    from detbench.sim.run import run_lidars

    out = tmp_path / "sim"
    proc = run_python(["tools/simulate.py", "--out", str(out), "--frames", "2", "--heights", "1.8", "--no-progress"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "simulating 2 frames x 1 heights into" in proc.stdout and " on disk (" in proc.stdout
    written = sum(f.stat().st_size for d in ("points", "labels", "meta") for f in (out / d).rglob("*") if f.is_file())
    estimate = estimate_dataset_bytes(run_lidars([1.8]), 2)
    assert written <= estimate <= 1.3 * written, (written, estimate)


def test_default_dataset_larger_than_the_disk_is_refused(tmp_path, monkeypatch):
    """A default dataset larger than the cache's disk is refused before simulating, naming the filesystem, its
    free space, DETBENCH_CACHE and data.frames, and leaves no temporary folder."""
    import detbench.sim.dataset as simds
    from detbench.utils.atomic import DiskFullError

    frames = shutil.disk_usage(tmp_path).free // 500_000 + 1  # three heights write about 1.7 MB per frame

    def boom(*a, **k):
        raise AssertionError("simulated although the disk cannot hold the dataset")

    monkeypatch.setattr(simds, "simulate_dataset", boom)
    cfg = {"frames": frames, "frames_per_scene": 2, "heights": [0.5, 1.0, 1.8], "cache_dir": str(tmp_path / "c")}
    with pytest.raises(DiskFullError, match=r"DETBENCH_CACHE .*lower data\.frames") as ei:
        simds.default_dataset(cfg, progress=False)
    assert f"the filesystem of {tmp_path}" in str(ei.value) and "free" in str(ei.value)
    assert not list((tmp_path / "c").glob(".tmp-*")) if (tmp_path / "c").exists() else True


# ------------------------------------------------------------------------------------------ figures

def _ability_report(heights: list[str]) -> dict:
    from detbench.data.regions import LEVELS, RANGE_NAMES

    rng = np.random.default_rng(0)
    cells = {h: {r: {lv: {"total": 20, "detected": int(d), "ldr": d / 20} for lv, d in
                     zip(LEVELS, rng.integers(0, 21, len(LEVELS)))} for r in RANGE_NAMES} for h in heights}
    edges = [0.0, 25.0, 50.0, 75.0, 100.0]
    dist = {"bin_m": 25.0, "edges_m": edges, "region": "test",
            "heights": {h: {"total": [10, 10, 10, 10], "detected": [9, 7, 5, 3], "ldr": list(rng.random(4))}
                        for h in heights}}
    return {"num_frames": 8, "heights": cells, "extras": {"ldr_vs_distance": dist}}


def _inside(fig, legend) -> bool:
    """Whether `legend` (or one of its texts) lies inside the figure as drawn (the Agg canvas save_figure uses)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    box, page = legend.get_window_extent(), fig.bbox
    return box.x0 >= page.x0 - 1 and box.y0 >= page.y0 - 1 and box.x1 <= page.x1 + 1 and box.y1 <= page.y1 + 1


def _figures(monkeypatch, tmp_path, n):
    """Run the ability figures on `n` heights; return the saved figures by name (save_figure captured)."""
    import detbench.studies.ability_plots as ap

    saved = {}

    def capture(fig, path, **kw):
        saved[os.path.basename(str(path))] = (fig, kw)
        return path

    monkeypatch.setattr(ap, "save_figure", capture)
    report = _ability_report([f"{0.3 + 0.05 * i:.2f}" for i in range(n)])
    ap.plot_ability_by_range(report, tmp_path / "range.png")
    ap.plot_ability_by_level(report, tmp_path / "level.png")
    ap.plot_ldr_vs_distance(report, tmp_path / "dist.png")
    return saved


@pytest.mark.slow  # about a minute on 2 CPU cores: it draws and saves the ability figures at 50 heights
def test_fifty_heights_get_fifty_colours_and_a_legend_inside_the_figure(monkeypatch, tmp_path):
    """The ability figures of 50 heights draw each height in its own colour, with a legend (in several columns
    where needed) that lies inside the saved figure."""
    from matplotlib.colors import to_hex

    saved = _figures(monkeypatch, tmp_path, 50)
    fig, kw = saved["dist.png"]
    ax = fig.axes[0]
    assert len({to_hex(line.get_color()) for line in ax.get_lines()}) == 50
    legend = ax.get_legend()
    assert len(legend.get_texts()) == 50 and _inside(fig, legend)
    for name in ("range.png", "level.png"):
        fig, kw = saved[name]
        bars = [p for p in fig.axes[1].patches]
        assert len({to_hex(p.get_facecolor()) for p in bars}) == 50, name
        legend = fig.legends[0]
        assert len(legend.get_texts()) == 51 and legend._ncols > 1 and _inside(fig, legend), name
        assert all(_inside(fig, t) for t in legend.get_texts()), name


def test_three_heights_keep_their_colours_and_legend(monkeypatch, tmp_path):
    """The ability figures of the paper's three heights keep matplotlib's first three colours, their figure
    sizes and a four-column legend."""
    from matplotlib.colors import to_hex

    saved = _figures(monkeypatch, tmp_path, 3)
    fig, _ = saved["dist.png"]
    assert [to_hex(line.get_color()) for line in fig.axes[0].get_lines()] == ["#1f77b4", "#ff7f0e", "#2ca02c"]
    assert fig.get_size_inches().tolist() == [8.0, 6.0]
    fig, _ = saved["range.png"]
    assert fig.legends[0]._ncols == 4 and fig.get_size_inches().tolist() == [11.0, 4.4]
