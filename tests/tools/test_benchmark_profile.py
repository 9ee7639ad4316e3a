"""tools/benchmark.py --profile: where a detector's time goes, by stage and by kind of torch op."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from detbench.benchmarks.profile import OP_KINDS, op_kind, profile_markdown
from tests.helpers import ROOT


@pytest.mark.parametrize("name, kind", [
    ("aten::mkldnn_convolution", "dense convolution"), ("aten::convolution_backward", "dense convolution"),
    ("aten::addmm", "matrix products"), ("aten::mm", "matrix products"),
    ("aten::index_select", "gather / scatter"), ("aten::scatter_add_", "gather / scatter"),
    ("aten::index_add_", "gather / scatter"), ("aten::searchsorted", "rule books and sorting"),
    ("aten::nonzero", "rule books and sorting"), ("aten::native_batch_norm", "normalisation"),
    ("aten::add_", "element-wise and copies"), ("aten::copy_", "element-wise and copies"),
    ("Optimizer.step#AdamW.step", "optimiser"), ("aten::empty_strided", "other torch ops")])
def test_ops_are_grouped_by_what_they_do(name, kind):
    assert op_kind(name) == kind
    assert kind == "other torch ops" or kind in dict(OP_KINDS)


def test_profile_accounts_for_the_time_of_every_stage(tmp_path):
    """Each model's profile: the data steps add up to their total, the training step's parts to (nearly) its
    total, the op table's shares to 1 with the time outside torch ops as a row, and the stages of the model
    (SECOND: voxelize, backbone3d, bev, head) each timed."""
    out = tmp_path / "b"
    proc = subprocess.run([sys.executable, "tools/benchmark.py", "--preset", "smoke", "--models", "second",
                           "--frames", "2", "--warmup", "1", "--train-steps", "2", "--profile", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (res,) = json.loads((out / "benchmark.json").read_text())["results"]
    p = res["profile"]
    data = p["data_ms_per_sample"]
    assert data["total"] == pytest.approx(sum(v for k, v in data.items() if k not in ("total", "points_per_sample")),
                                          abs=0.05)
    step = p["train_step_ms"]
    parts = sum(v for k, v in step.items() if k != "total")
    assert {f"forward: {s}" for s in ("voxelize", "backbone3d", "bev", "head")} <= set(step)
    assert 0.5 * step["total"] < parts <= 1.05 * step["total"]
    for table in (p["train_ops"], p["inference_ops"]):
        assert sum(r["share"] for r in table) == pytest.approx(1.0, abs=0.02)
        assert table[-1]["kind"].startswith("outside torch ops")
        assert any(r["kind"] == "dense convolution" and r["gflops"] for r in table)
    assert p["machine"]["matmul_gflops"] > 0 and p["machine"]["copy_gb_per_s"] > 0
    md = (out / "benchmark.md").read_text()
    assert "## Where the time goes" in md and "### second" in md and "| dense convolution |" in md
    assert profile_markdown([{"model": "x"}]) == profile_markdown([])  # a result without a profile adds nothing
