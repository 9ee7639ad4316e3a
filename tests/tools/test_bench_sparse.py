"""tools/bench_sparse.py: command line and report files; the library parts it runs (the fallback scan of
detbench.sim.scans, the backbone topology of detbench.sparse.bench, the report of detbench.benchmarks.sparse)."""
import json

import numpy as np
import pytest
import torch

from detbench.benchmarks.sparse import sparse_bench_markdown
from detbench.sim.scans import synthetic_scan
from detbench.sparse import SparseConvTensor
from detbench.sparse.bench import backbone
from tools import bench_sparse as bench


def test_help_lists_options_with_units(capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for opt in ("--out", "--scans", "--repeats", "--threads", "--voxel-size", "--range", "--dense-crop-x"):
        assert opt in text
    assert "metres" in text and "milliseconds" in text.lower()


def test_synthetic_scan_geometry():
    pts = synthetic_scan(0)
    assert pts.dtype == np.float32 and pts.shape[1] == 4 and len(pts) > 10000
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert r.max() <= 150.5 and pts[:, 0].min() > -1.0  # 180 deg ahead, 150 m range
    ground = np.abs(pts[:, 2]) < 0.05
    assert 0.5 < ground.mean() < 1.0  # mostly road, some car returns above it
    assert pts[~ground, 2].max() < 1.9 and pts[:, 2].min() > -0.1


def test_backbone_shapes_and_rulebook_reuse():
    net = backbone(4).eval()
    g = torch.Generator().manual_seed(0)
    idx = torch.unique(torch.cat([torch.zeros(300, 1, dtype=torch.long),
                                  torch.randint(0, 41, (300, 1), generator=g),
                                  torch.randint(0, 40, (300, 2), generator=g)], 1), dim=0).int()
    x = SparseConvTensor(torch.randn(idx.shape[0], 4, generator=g), idx, [41, 40, 40], 1)
    with torch.no_grad():
        y = net(x)
    assert y.features.shape[1] == 128 and y.spatial_shape == [2, 5, 5]
    # 12 conv layers share 8 rule books (subm1 x2, subm2 x2, subm3 x2, subm4 x2 reuse).
    assert len(y.indice_dict) == 8
    assert len([m for m in net.modules() if hasattr(m, "indice_key")]) == 12


def test_markdown_report():
    r = {"source": "synthetic", "scans": 1, "points": [10], "voxel_size_m": [0.1, 0.1, 0.15],
         "range_m": [0, -15, -1, 150, 15, 4], "grid_xyz": [1500, 300, 33], "spatial_shape_zyx": [34, 300, 1500],
         "active_sites": 5, "device": "cpu", "threads": 2, "torch": "x", "repeats": 1, "flop_convention": "2/MAC",
         "spconv": "not installed",
         "cases": [{"case": "a", "ms": 1.234, "ms_best": 1.0, "gflops": 2.5, "sites": 5}]}
    md = sparse_bench_markdown(r)
    assert "| a | 1.23 | 1.00 | 2.5 | sites=5 |" in md and "spconv: not installed" in md


@pytest.mark.slow
def test_full_run_writes_reports(tmp_path):
    assert bench.main(["--out", str(tmp_path), "--source", "synthetic", "--repeats", "1", "--threads", "1",
                       "--dense-crop-x", "5"]) == 0
    data = json.loads((tmp_path / "bench_sparse.json").read_text())
    assert data["active_sites"] > 1000
    assert data["spconv"] == "not installed" or isinstance(data["spconv"], dict)
    assert all(c["ms"] > 0 for c in data["cases"])
    assert (tmp_path / "bench_sparse.md").read_text().startswith("# Sparse convolution benchmark")


def test_markdown_report_idle_and_loaded():
    r = {"source": "synthetic", "scans": 1, "points": [10], "voxel_size_m": [0.1, 0.1, 0.15],
         "range_m": [0, -15, -1, 150, 15, 4], "grid_xyz": [1500, 300, 33], "spatial_shape_zyx": [34, 300, 1500],
         "active_sites": 5, "device": "cpu", "threads": 2, "torch": "x", "repeats": 1, "flop_convention": "2/MAC",
         "spconv": "not installed", "load": {"processes": 1, "busy_cores_used": 0.9, "wall_s": 3.0},
         "cases": [{"case": "a", "ms": 1.0, "ms_best": 1.0, "loaded_ms": 2.5, "loaded_ms_best": 2.0,
                    "loaded_ratio": 2.5, "sites": 5}]}
    md = sparse_bench_markdown(r)
    assert "| case | median ms | best ms | loaded median ms | x idle |" in md
    assert "| a | 1.00 | 1.00 | 2.50 | 2.50 |  | sites=5 |" in md and "1 busy-loop process" in md


def test_sparse_bench_results_are_pinned(monkeypatch, capsys):
    """run_sparse_bench on a fixed small scan, idle and 'loaded', with the clock replaced by a counter: every
    case, its counts (voxels, sites, rule-book pairs, shapes), GFLOP/s from the given times, the printed lines
    and the Markdown. Machine facts (threads, torch, cpu, thread runtimes) are blanked."""
    import sys

    from detbench.benchmarks import sparse as sb
    from tests.helpers import assert_golden

    clock = iter(range(1, 1000))

    def fake_timed(fn, repeats, sync):
        fn()
        sync()
        ms = float(next(clock))
        return {"ms": ms, "ms_best": ms / 2}

    def fake_idle_and_loaded(measure, load):
        idle = measure()
        return (idle, None, None) if load <= 0 else (idle, measure(), {"processes": load})

    monkeypatch.setattr(sb, "timed", fake_timed)
    monkeypatch.setattr(sb, "idle_and_loaded", fake_idle_and_loaded)
    monkeypatch.setitem(sys.modules, "spconv", None)  # as when spconv is not installed
    scan = synthetic_scan(0)
    scan = scan[(scan[:, 0] < 24) & (np.abs(scan[:, 1]) < 8)]
    settings = sb.SparseBenchSettings(range=[0.0, -8.0, -1.0, 24.0, 8.0, 3.0], repeats=3, dense_crop_x=6.0, load=1)
    results = sb.run_sparse_bench([scan, scan[::2]], "synthetic (cropped)", settings, torch.device("cpu"))
    printed = capsys.readouterr().out
    for key in ("threads", "torch", "cpu"):
        results[key] = "-"
    assert set(results.pop("runtime")) >= {"env", "torch_threads"}
    text = "\n".join(["--- printed", printed, "--- bench_sparse.md", sparse_bench_markdown(results),
                      "--- bench_sparse.json", json.dumps(results, indent=1)]) + "\n"
    assert_golden("bench_sparse.txt", text)
