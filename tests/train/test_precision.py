"""Inference at reduced precision against float32: detbench.train.precision and tools/precision.py.

- `box_differences` on hand-made detections: a known shift, a heading flip, a lost detection;
- `compare_precision` with a detector that behaves differently under autocast (boxes moved by a
  known amount, NaN in one frame's outputs): the report must show exactly that (the metric can fail);
- a real detector (SECOND, smoke sizes, seeded random initialisation) in bfloat16 autocast on the
  CPU against float32: finite, no NaN/inf, and the bfloat16 run really computes in bfloat16;
- sparse convolution under autocast (features cast once, products in the autocast dtype), forward and backward;
- float16 / bfloat16 on CUDA where it exists;
- the tool on a checkpoint: JSON + Markdown with units.
"""
from __future__ import annotations

import json
import math
from typing import NamedTuple

import numpy as np
import pytest
import torch
from torch import nn

import models
from detbench.data.batch import Batch, Detections
from detbench.data.frame import Frame, Sensor
from detbench.train.precision import (
    available_precisions, autocast_for, box_differences, compare_precision, float32_settings, precision_markdown,
    run_at_precision, strict_float32,
)
from tests.helpers import box_points
import tools.precision


def _car(x, y, heading=0.0):
    return np.array([x, y, 0.8, 4.5, 1.9, 1.6, heading])


# ---------------------------------------------------------------- box_differences
def test_box_differences_measure_shift_flip_and_lost_detections():
    a = np.stack([_car(20, 0), _car(40, 3.5, 0.3), _car(60, -3.5, math.pi - 0.01)])
    s = np.array([0.9, 0.8, 0.7])
    b = a.copy()
    b[0, 0] += 0.10  # 10 cm forward
    b[1, 6] += math.pi  # direction flipped: the same solid
    b[2, 6] = -math.pi + 0.01  # across +-pi: 0.02 rad apart
    ref = {"f0": (a, s), "f1": (a[:1], s[:1])}
    other = {"f0": (b, s - 0.01), "f1": (np.zeros((0, 7)), np.zeros(0))}
    d = box_differences(ref, other, score_threshold=0.1, match_iou=0.5)
    assert d["matched"] == 3 and d["unmatched_reference"] == 1 and d["unmatched_other"] == 0
    assert d["heading_flips"] == 1 and d["worst_frame"] == "f0"
    assert d["max_centre_diff_m"] == pytest.approx(0.10, abs=1e-9)
    assert d["max_heading_diff_rad"] == pytest.approx(0.02, abs=1e-9)
    # corners: 0.10 m for the shifted car, 0 for the flipped one (the same solid), and for the car turned by
    # 0.02 rad up to 2 x half its diagonal x sin(0.01)
    turned = 2 * math.hypot(2.25, 0.95) * math.sin(0.01)
    assert d["max_corner_diff_m"] == pytest.approx(0.10, abs=1e-9)
    assert d["mean_corner_diff_m"] == pytest.approx((0.10 + 0.0 + turned) / 3, rel=1e-6)
    assert d["max_score_diff"] == pytest.approx(0.01)
    # below the score threshold nothing is compared; identical runs differ by nothing
    assert box_differences(ref, other, score_threshold=0.95)["matched"] == 0
    same = box_differences(ref, ref)
    assert same["matched"] == 4 and same["max_corner_diff_m"] == 0.0 and same["unmatched_reference"] == 0


# ---------------------------------------------------------------- compare_precision, a detector with known faults
class OracleOut(NamedTuple):
    boxes: torch.Tensor  # (B, Kmax, 7)
    scores: torch.Tensor  # (B, Kmax)


class PrecisionSensitiveOracle(nn.Module):
    """Predicts each frame's true boxes (looked up by frame id) with score 0.9 in float32; under autocast it
    moves them by `shift` metres along x and puts NaN in the outputs of frame `nan_frame`."""

    def __init__(self, truth: dict[str, np.ndarray], shift: float, nan_frame: str):
        super().__init__()
        self.truth, self.shift, self.nan_frame = truth, shift, nan_frame
        self.scale = nn.Parameter(torch.ones(()))
        self.autocast_seen: list[bool] = []

    def forward(self, batch: Batch) -> OracleOut:
        low = torch.is_autocast_enabled("cpu") if hasattr(torch, "is_autocast_enabled") else False
        self.autocast_seen.append(bool(low))
        k = max(len(self.truth[f]) for f in batch.frame_ids)
        boxes = torch.zeros(batch.batch_size, k, 7)
        scores = torch.zeros(batch.batch_size, k)
        for i, f in enumerate(batch.frame_ids):
            t = torch.as_tensor(self.truth[f], dtype=torch.float32)
            boxes[i, :len(t)] = t
            scores[i, :len(t)] = 0.9
            if low:
                boxes[i, :, 0] += self.shift
                if f == self.nan_frame:
                    scores[i, 0] = float("nan")
        return OracleOut(boxes * self.scale, scores)

    def predict(self, out: OracleOut, batch: Batch) -> list[Detections]:
        dets = []
        for i, f in enumerate(batch.frame_ids):
            n = len(self.truth[f])
            b, s = out.boxes[i, :n].float(), out.scores[i, :n].float()
            keep = torch.isfinite(s) & torch.isfinite(b).all(1)
            dets.append(Detections(b[keep], s[keep], torch.zeros(int(keep.sum()), dtype=torch.int64)))
        return dets


def _frames():
    out = []
    for k, xs in enumerate([(12.0, 30.0), (45.0,), (20.0, 70.0, 110.0), ()]):
        boxes = np.array([_car(x, 0.0) for x in xs]).reshape(-1, 7).astype(np.float32)
        pts = np.concatenate([box_points(b, 64, margin=0.1) for b in boxes]) if len(boxes) else np.zeros((0, 4))
        m = len(boxes)
        out.append(Frame(f"0000_{k:03d}", "0000", pts.astype(np.float32), boxes, np.array(["car"] * m),
                         np.arange(m, dtype=np.int64), np.zeros(m, dtype=np.int64), Sensor(height=1.8)).check())
    return out


def test_compare_precision_reports_what_the_reduced_precision_changed():
    frames = _frames()
    truth = {f.frame_id: np.asarray(f.boxes) for f in frames}
    model = PrecisionSensitiveOracle(truth, shift=0.3, nan_frame="0000_002")
    rep = compare_precision(model, frames, [0.0, -16.0, -0.6, 153.6, 16.0, 4.2], ["bfloat16"], batch_size=2)
    assert list(rep["precisions"]) == ["float32", "bfloat16"] and rep["num_frames"] == 4
    assert model.autocast_seen == [False, False, True, True]
    f32, bf = rep["precisions"]["float32"], rep["precisions"]["bfloat16"]
    assert f32["nonfinite_values"] == 0 and f32["ap_r40"]["small"] == pytest.approx(1.0)
    assert f32["detections"] == 6
    # frame 0000_002's outputs hold one NaN: counted (values, frames), its NaN detection dropped
    assert bf["nonfinite_values"] == 1 and bf["nonfinite_frames"] == 2 and bf["nonfinite_frame_ids"][:2] == [
        "0000_002", "0000_003"]
    assert bf["detections"] == 5
    b = bf["boxes"]
    assert b["matched"] == 5 and b["unmatched_reference"] == 1 and b["unmatched_other"] == 0
    assert (b["max_centre_diff_m"] == pytest.approx(0.3, abs=1e-5)
            and b["max_corner_diff_m"] == pytest.approx(0.3, abs=1e-5))
    # a 0.3 m shift along a 4.5 m car: 3D IoU 4.2 / 4.8 = 0.875 >= 0.7, still true positives; AP changes only by the
    # lost detection (the far one in frame 0000_002 is not among the first: recall drops in the range that held it)
    assert bf["ap_r40_diff"]["small"] == pytest.approx(bf["ap_r40"]["small"] - f32["ap_r40"]["small"])
    assert bf["max_abs_ap_r40_diff"] > 0
    assert any(v < 0 for v in bf["recall_diff"].values() if v is not None)
    md = precision_markdown(rep)
    assert "| bfloat16 |" in md and "1 (2)" in md and "(metres)" in md
    # a larger shift turns true positives into false ones: AP@R40 falls to 0
    rep2 = compare_precision(PrecisionSensitiveOracle(truth, 2.0, "none"), frames, [0, -16, -0.6, 153.6, 16, 4.2],
                             ["bfloat16"], batch_size=4)
    assert rep2["precisions"]["bfloat16"]["ap_r40"]["small"] == 0.0
    assert rep2["precisions"]["bfloat16"]["max_abs_ap_r40_diff"] == pytest.approx(1.0)


class SettingsRecorder(PrecisionSensitiveOracle):
    """The oracle, recording the float32 matmul and cuDNN settings in force at each forward pass."""

    def forward(self, batch):
        self.settings_seen = [*getattr(self, "settings_seen", []), float32_settings()]
        return super().forward(batch)


def test_the_float32_reference_runs_without_tf32_and_says_so():
    """cuDNN computes float32 convolutions in TensorFloat-32 by default (Ampere and later): the comparison turns
    TF32 off for matrix products and cuDNN while it runs, records the settings, and puts them back after."""
    frames = _frames()
    truth = {f.frame_id: np.asarray(f.boxes) for f in frames}
    before = float32_settings()
    assert before["cudnn_conv"] == "tf32"  # torch's default
    model = SettingsRecorder(truth, shift=0.0, nan_frame="none")
    rep = compare_precision(model, frames, [0.0, -16.0, -0.6, 153.6, 16.0, 4.2], ["bfloat16"], batch_size=2)
    assert len(model.settings_seen) == 4
    assert all(s["cuda_matmul"] == "ieee" and s["cudnn_conv"] == "ieee" for s in model.settings_seen)
    assert rep["float32"]["cuda_matmul"] == rep["float32"]["cudnn_conv"] == "ieee"
    assert "float32 matrix products ieee, cuDNN convolutions ieee" in precision_markdown(rep)
    assert float32_settings() == before
    with strict_float32():
        assert float32_settings()["cudnn_conv"] == "ieee" and torch.get_float32_matmul_precision() == "highest"
    assert float32_settings() == before


def test_precision_names_and_contexts():
    assert available_precisions("cpu") == ["float32", "bfloat16"]
    with autocast_for("bfloat16", "cpu"):
        assert torch.mm(torch.ones(2, 2), torch.ones(2, 2)).dtype == torch.bfloat16
    with autocast_for("float32", "cpu"):
        assert torch.mm(torch.ones(2, 2), torch.ones(2, 2)).dtype == torch.float32
    with pytest.raises(ValueError, match="unknown precision 'float8'"):
        autocast_for("float8", "cpu")


# ---------------------------------------------------------------- a real detector
def _second_smoke():
    from detbench.train.run_config import load_run_config

    cfg = load_run_config("second", "smoke", overrides=["model.post.score_threshold=0.0"])  # untrained: keep all
    model_cfg = models.prepare_model_config("second", cfg["model"], np.stack([_car(20, 0), _car(40, 3.5)]))
    torch.manual_seed(0)
    return models.build_model("second", model_cfg).eval(), model_cfg


def test_second_in_bfloat16_is_finite_and_runs_in_bfloat16():
    model, cfg = _second_smoke()
    frames = _frames()
    dtypes = []
    conv = next(m for m in model.backbone2d.modules() if isinstance(m, nn.Conv2d))
    hook = conv.register_forward_hook(lambda m, i, o: dtypes.append(o.dtype))
    rep = compare_precision(model, frames, cfg["point_cloud_range"], ["bfloat16"], score_threshold=0.0, batch_size=2)
    hook.remove()
    assert dtypes[:2] == [torch.float32] * 2 and dtypes[2:] == [torch.bfloat16] * 2  # the reduced run is reduced
    for name, e in rep["precisions"].items():
        assert e["nonfinite_values"] == 0 and e["nonfinite_detections"] == 0, name
        assert e["detections"] > 0 and e["seconds_per_frame"] > 0
    b = rep["precisions"]["bfloat16"]["boxes"]
    # an untrained model's scores are near-ties, so NMS may keep other anchors' boxes; the matched ones are close
    assert b["matched"] > 0 and math.isfinite(b["max_corner_diff_m"]) and b["p99_corner_diff_m"] < 1.0
    run = run_at_precision(model, frames, cfg["point_cloud_range"], "float32")
    again = run_at_precision(model, frames, cfg["point_cloud_range"], "float32")
    assert all(np.array_equal(run.predictions[k][0], again.predictions[k][0]) for k in run.predictions)


def test_sparse_conv_under_autocast_forward_and_backward():
    """Left to autocast, the sparse conv's float16 output met float32 saved features in backward (a crash for
    SECOND and CT3D under mixed precision); its weight gradient over many sites overflowed float16."""
    from detbench.sparse import SparseConvTensor, SubMConv3d

    torch.manual_seed(0)
    n = 4000
    idx = torch.unique(torch.randint(0, 40, (n, 3)), dim=0)
    coords = torch.cat([torch.zeros(len(idx), 1, dtype=torch.int32), idx.int()], 1)
    feats = torch.randn(len(idx), 16) * 30
    conv = SubMConv3d(16, 32, 3, bias=False)
    x = SparseConvTensor(feats, coords, [40, 40, 40], 1)
    ref = conv(x).features.detach()
    for dtype in (torch.float16, torch.bfloat16):
        conv.zero_grad()
        with torch.autocast("cpu", dtype=dtype):
            out = conv(SparseConvTensor(feats, coords, [40, 40, 40], 1)).features
        assert out.dtype == dtype
        tol = 1e-2 if dtype == torch.float16 else 5e-2
        assert float((out.detach().float() - ref).abs().max() / ref.abs().max()) < tol
        (out.float() * 64).sum().backward()
        g = conv.weight.grad
        assert g.dtype == torch.float32 and torch.isfinite(g).all() and float(g.abs().max()) > 65504


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_second_in_float16_on_cuda():
    model, cfg = _second_smoke()
    model = model.cuda()
    rep = compare_precision(model, _frames(), cfg["point_cloud_range"], None, device="cuda", score_threshold=0.0)
    assert "float16" in rep["precisions"]
    for name, e in rep["precisions"].items():
        assert e["nonfinite_values"] == 0 and e["nonfinite_detections"] == 0, name


# ---------------------------------------------------------------- the tool
def test_precision_tool_writes_json_and_markdown(tmp_path, capsys):
    from detbench.sim.dataset import simulate_dataset
    from detbench.train import CheckpointManager, TrainState

    data = simulate_dataset(tmp_path / "data", frames=6, heights=[1.8], seed=2, frames_per_scene=3, progress=False)
    model, cfg = _second_smoke()
    run_config = {"model": cfg, "train": {}}
    path = CheckpointManager(tmp_path / "run" / "checkpoints").save(
        TrainState(1, 0, 1, 0), model=model, model_name="second", config=run_config,
        data={"source": str(data), "height": 1.8})
    from detbench.utils.cli import run_main

    code = run_main(tools.precision.main, ["--ckpt", str(path), "--split", "all", "--frames", "3",
                                                  "--no-progress", "--out", str(tmp_path / "p")])
    out = capsys.readouterr()
    assert code == 0, out.err
    rep = json.loads((tmp_path / "p" / "precision.json").read_text())
    assert rep["model"] == "second" and rep["num_frames"] == 3 and set(rep["precisions"]) == {"float32", "bfloat16"}
    assert "largest box difference" in out.out
    md = (tmp_path / "p" / "precision.md").read_text()
    assert "s/frame" in md and "(metres)" in md and "max heading (rad)" in md
    code = run_main(tools.precision.main, ["--ckpt", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "q")])
    assert code == 2 and "nope.pt" in capsys.readouterr().err
