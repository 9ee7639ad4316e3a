"""Golden outputs of every registered detector, the ground-truth-poison rule and the two-stage output switch.

Each model is built from configs/<name>.yaml at the smoke preset, after `prepare_model_config` on fixed
training boxes, with torch seed 0; then its first-stage confidence bias (the prior-probability constant the
head starts from) is set to 0 and its BatchNorm statistics are those of the fixed two-frame batch
(`golden_batch`; one train-mode pass, torch seed 2), so the random weights give features of unit scale,
scores spread around 0.5 and `predict` returns boxes to compare instead of an empty list. On that batch:

- eval mode: every tensor `forward` returns (shape, sum, absolute sum and a sum weighted by a fixed
  pattern, which a reordering changes) and every frame's detections from `predict`;
- train mode, torch seed 1 before `forward` (point sampling, dropout and jitter draw from it): the total
  loss and each loss term.

`test_golden_outputs` compares them with tests/models/expected/<name>.json: shapes and detection counts
exactly, every number within RTOL of the magnitude it is a sum of plus ATOL, so the file holds on another
x86 CPU but any change of a model's outputs fails. After a change that is meant to change outputs,
regenerate the files with

    DETBENCH_REGEN_GOLDEN=1 python3 -m pytest -q tests/models/test_golden.py

and say in the commit why the outputs changed.

`test_torch_path_matches_the_numba_path` runs the same record, plus the gradient of every parameter, once
with every op on its torch path (the GPU's; `DETBENCH_OPS=torch`, with the numba kernels made to raise) and
once on the numba path, in float32 and under bfloat16 and float16 autocast (the CPU's autocast type and the
one mixed-precision training uses on CUDA), and compares them.
"""
from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

import models
from detbench.data.batch import Batch, Detections
from detbench.ops.backend import forced_backend
from detbench.train.run_config import load_run_config
from tests.helpers import batch_of, box_points

EXPECTED = Path(__file__).parent / "expected"
REGEN = os.environ.get("DETBENCH_REGEN_GOLDEN") == "1"
RTOL, ATOL = 1e-4, 1e-5

# vehicles of the fixed batch and the boxes `prepare_model_config` sizes anchors / the mean size from
CARS = [np.array([[20.0, 1.0, 0.8, 4.5, 1.9, 1.6, 0.3], [34.0, -4.0, 0.85, 4.8, 2.0, 1.7, -0.2]], np.float32),
        np.array([[12.0, -2.5, 0.75, 4.2, 1.8, 1.5, 1.4]], np.float32)]
TRAIN_BOXES = np.concatenate([CARS[0], CARS[1], CARS[0] * [1, 1, 1, 1.1, 1.05, 1, 1]])
# the first-stage confidence bias of each model (its prior-probability constant)
PRIOR_BIAS = {"second": "head.conv_cls.bias", "ct3d": "head.conv_cls.bias",
              "pillarnet": "head.branches.heatmap.3.bias", "pointrcnn": "point_head.cls.3.bias"}
TWO_STAGE = ("ct3d", "pointrcnn")


def golden_batch() -> Batch:
    """Two frames: road points, points on two / one vehicles with their boxes, and clutter over the whole
    region, so that no two BEV cells see the same (empty) input and tie in score: the order of tied scores
    is the sort's, which differs between thread counts and CPUs."""
    rng = np.random.default_rng(7)
    frames = []
    for i, cars in enumerate(CARS):
        road = rng.uniform([0, -12, -0.05, 0], [60, 12, 0.05, 1], (600, 4)).astype(np.float32)
        clutter = rng.uniform([0, -16, -0.5, 0], [153.6, 16, 4.0, 1], (6000, 4)).astype(np.float32)
        on = [box_points(c, 200 + 100 * k, rng=10 * i + k, on_faces=True, intensity=None) for k, c in enumerate(cars)]
        frames.append(np.concatenate([road, clutter, *on]))
    return batch_of(frames, CARS)


def golden_model(name: str) -> torch.nn.Module:
    cfg = models.prepare_model_config(name, load_run_config(name, "smoke")["model"], TRAIN_BOXES)
    torch.manual_seed(0)
    model = models.build_model(name, cfg)
    with torch.no_grad():
        dict(model.named_parameters())[PRIOR_BIAS[name]].zero_()
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.reset_running_stats()
                m.momentum = None  # a cumulative average: after one pass, that pass's statistics
        model.train()
        torch.manual_seed(2)
        model(golden_batch())
    return model.eval()


def _pattern(n: int) -> torch.Tensor:
    return torch.cos(torch.arange(n, dtype=torch.float64) * 0.7)


def tensor_summary(t: torch.Tensor) -> dict:
    v = t.detach().double().reshape(-1)
    return {"shape": list(t.shape), "sum": float(v.sum()), "abs": float(v.abs().sum()),
            "wsum": float((v * _pattern(v.numel())).sum())}


def output_summary(out, prefix: str = "") -> dict:
    """{dotted field: summary} of every tensor in a (nested) NamedTuple of outputs."""
    found = {}
    for field, value in zip(out._fields, out):
        name = prefix + field
        if isinstance(value, torch.Tensor):
            found[name] = tensor_summary(value)
        elif isinstance(value, tuple) and hasattr(value, "_fields"):
            found.update(output_summary(value, name + "."))
    return found


def detections_summary(dets: list[Detections]) -> list[dict]:
    return [{"count": int(d.scores.numel()), "boxes": tensor_summary(d.boxes), "scores": tensor_summary(d.scores),
             "top_scores": [float(s) for s in d.scores[:5]],
             "top_boxes": [[float(v) for v in b] for b in d.boxes[:3]]} for d in dets]


def golden_record(name: str) -> dict:
    model = golden_model(name)
    batch = golden_batch()
    model.eval()
    with torch.no_grad():
        out = model(batch)
        dets = model.predict(out, batch)
    model.train()
    torch.manual_seed(1)
    total, parts = model.loss(model(batch), batch)
    return {"model": name, "forward": output_summary(out), "predict": detections_summary(dets),
            "loss": {"total": float(total.detach()), **{k: float(v) for k, v in sorted(parts.items())}}}


def _close(got: float, want: float, scale: float, where: str) -> None:
    assert math.isfinite(got) == math.isfinite(want), f"{where}: {got} vs expected {want}"
    if math.isfinite(want):
        assert abs(got - want) <= RTOL * max(abs(scale), abs(want)) + ATOL, f"{where}: {got!r} vs expected {want!r}"


def _compare_summary(got: dict, want: dict, where: str) -> None:
    assert got["shape"] == want["shape"], f"{where}: shape {got['shape']} vs expected {want['shape']}"
    for key in ("sum", "abs", "wsum"):
        _close(got[key], want[key], want["abs"], f"{where}.{key}")


def compare(got: dict, want: dict) -> None:
    assert sorted(got["forward"]) == sorted(want["forward"]), "forward() returns other fields"
    for field, summary in want["forward"].items():
        _compare_summary(got["forward"][field], summary, f"forward.{field}")
    assert [d["count"] for d in got["predict"]] == [d["count"] for d in want["predict"]], "detection counts"
    for i, (g, w) in enumerate(zip(got["predict"], want["predict"])):
        for part in ("boxes", "scores"):
            _compare_summary(g[part], w[part], f"predict[{i}].{part}")
        for j, (a, b) in enumerate(zip(g["top_scores"], w["top_scores"])):
            _close(a, b, 1.0, f"predict[{i}].top_scores[{j}]")
        for j, (a, b) in enumerate(zip(g["top_boxes"], w["top_boxes"])):
            for k, (x, y) in enumerate(zip(a, b)):
                _close(x, y, 1.0, f"predict[{i}].top_boxes[{j}][{k}]")
    assert sorted(got["loss"]) == sorted(want["loss"]), "loss terms"
    for key, value in want["loss"].items():
        _close(got["loss"][key], value, 1.0, f"loss.{key}")


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_golden_outputs(name):
    path = EXPECTED / f"{name}.json"
    got = golden_record(name)
    if REGEN:
        EXPECTED.mkdir(exist_ok=True)
        path.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    assert path.is_file(), f"{path} missing: regenerate with DETBENCH_REGEN_GOLDEN=1 (see this module's docstring)"
    want = json.loads(path.read_text())
    assert sum(d["count"] for d in want["predict"]) > 0, f"{name}: the golden batch gives no detection to compare"
    compare(got, want)


# ---------------------------------------------------------------- the ops' torch path (the GPU's) on the CPU
def _forbid_numba(monkeypatch) -> list[str]:
    """Make every numba kernel of detbench.ops raise when called; returns their names."""
    names = []
    for modname in sorted(m for m in sys.modules if m.startswith("detbench.ops.")):
        mod = sys.modules[modname]
        for attr, value in list(vars(mod).items()):
            if isinstance(value, numba.core.registry.CPUDispatcher):
                def called(*args, _name=f"{modname}.{attr}", **kwargs):
                    raise AssertionError(f"{_name}: a numba kernel ran while every op should take its torch path")
                monkeypatch.setattr(mod, attr, called)
                names.append(f"{modname}.{attr}")
    return names


def path_record(name: str, backend: str, precision: str) -> dict:
    """`golden_record` with the ops on `backend` ("auto": numba on the CPU, "torch") under `precision`'s
    autocast ("float32": none), with the total loss's gradient: its sum of absolute values per parameter."""
    dtype = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}[precision]
    with forced_backend(backend):
        model = golden_model(name)
        batch = golden_batch()
        with torch.no_grad(), torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
            out = model(batch)
            dets = model.predict(out, batch)
        model.train()
        torch.manual_seed(1)
        with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
            total, parts = model.loss(model(batch), batch)
        total.backward()
    grads = {n: None if p.grad is None else float(p.grad.double().abs().sum()) for n, p in model.named_parameters()}
    return {"forward": output_summary(out), "predict": detections_summary(dets),
            "loss": {"total": float(total.detach()), **{k: float(v) for k, v in sorted(parts.items())}},
            "grads": grads}


@pytest.mark.parametrize("precision", ["float32", "bfloat16", "float16"])
@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_torch_path_matches_the_numba_path(name, precision, monkeypatch):
    """Forward, predict, loss and backward of every detector with every op on its torch path (no numba kernel
    runs) give the numba path's outputs and gradients, and every parameter gets a finite gradient."""
    want = path_record(name, "auto", precision)
    assert _forbid_numba(monkeypatch)
    got = path_record(name, "torch", precision)
    monkeypatch.undo()
    assert sum(d["count"] for d in got["predict"]) > 0
    compare(got, want)
    missing = [n for n, g in got["grads"].items() if g is None or not math.isfinite(g)]
    assert not missing, f"{name} ({precision}): parameters without a finite gradient on the torch path: {missing}"
    for n, g in want["grads"].items():
        _close(got["grads"][n], g, abs(g), f"grad {n}")


# ---------------------------------------------------------------- evaluation reads no ground truth
def _equal_outputs(a, b) -> bool:
    return all((x is None and y is None) or (torch.equal(x, y) if isinstance(x, torch.Tensor) else _equal_outputs(x, y))
               for x, y in zip(a, b))


def poisoned(batch: Batch) -> Batch:
    """`batch` with ground truth that would change any prediction made from it: NaN boxes, every slot marked
    real, and more slots than the frames have."""
    b, m = batch.gt_mask.shape
    return Batch(batch.points.clone(), torch.full((b, m + 3, 7), math.nan), torch.ones(b, m + 3, dtype=torch.bool),
                 list(batch.frame_ids), batch.batch_size)


class _GroundTruthRead(Exception):
    pass


class SealedBatch(Batch):
    """A Batch whose ground truth raises when read."""

    @property
    def gt_boxes(self):
        raise _GroundTruthRead("gt_boxes")

    @property
    def gt_mask(self):
        raise _GroundTruthRead("gt_mask")


def sealed(batch: Batch) -> Batch:
    out = object.__new__(SealedBatch)
    out.__dict__.update(points=batch.points.clone(), frame_ids=list(batch.frame_ids), batch_size=batch.batch_size)
    return out


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_evaluation_reads_no_ground_truth(name):
    """In eval mode, forward() and predict() never read the batch's ground truth: with poisoned ground truth
    they give the same outputs, and a batch whose ground truth raises on access goes through."""
    model = golden_model(name).eval()
    clean = golden_batch()
    with torch.no_grad():
        out = model(clean)
        dets = model.predict(out, clean)
        for other in (poisoned(clean), sealed(clean)):
            try:
                out_other = model(other)
                dets_other = model.predict(out_other, other)
            except _GroundTruthRead as e:
                pytest.fail(f"{name}: eval-mode forward() or predict() reads batch.{e}")
            assert _equal_outputs(out, out_other), f"{name}: forward() in eval mode depends on the ground truth"
            assert all(_equal_outputs(a, b) for a, b in zip(dets, dets_other)), \
                f"{name}: predict() depends on the ground truth"
    assert sum(d.scores.numel() for d in dets) > 0


# ---------------------------------------------------------------- the two-stage output switch
def _scores_from(dets: list[Detections], probs: list[torch.Tensor]) -> bool:
    """Every detection's score is one of its frame's candidate probabilities, to within 2 float32 ulps
    (torch's sigmoid rounds a value in a vectorised block and in a tensor's tail differently)."""
    for d, p in zip(dets, probs):
        if d.scores.numel() and (p.numel() == 0 or
                                 (d.scores[:, None] - p.float()[None]).abs().min(dim=1).values.max() > 1.2e-7):
            return False
    return True


@pytest.mark.parametrize("name", TWO_STAGE)
def test_output_stage_switch_returns_each_stage(name):
    """'proposals' gives the first stage's own detections (scored by its confidence), 'refined' the second
    stage's (scored by the refinement's confidence); they differ, and CT3D's first stage is SECOND."""
    model = golden_model(name).eval()
    batch = golden_batch()
    with torch.no_grad():
        out = model(batch)
        model.set_output_stage("proposals")
        first = model.predict(out, batch)
        model.set_output_stage("refined")
        refined = model.predict(out, batch)
    assert sum(d.scores.numel() for d in first) > 0 and sum(d.scores.numel() for d in refined) > 0
    mask = out.refine.roi_mask
    refine_probs = [torch.sigmoid(out.refine.cls_logits[i][mask[i]].float()) for i in range(batch.batch_size)]
    if name == "ct3d":
        first_probs = [torch.sigmoid(out.rpn.cls_logits[i].float()) for i in range(batch.batch_size)]
    else:
        first_probs = [torch.sigmoid(out.point.cls_logits[i][out.valid[i]].float()) for i in range(batch.batch_size)]
    assert _scores_from(first, first_probs), f"{name}: 'proposals' is not scored by the first stage"
    assert _scores_from(refined, refine_probs), f"{name}: 'refined' is not scored by the refinement"
    assert not all(_equal_outputs(a, b) for a, b in zip(first, refined)), f"{name}: both stages give the same boxes"
    if name == "ct3d":  # the first stage's detections are those of a SECOND holding the same weights
        cfg = {k: v for k, v in load_run_config("ct3d", "smoke")["model"].items() if k != "roi_head"}
        second = models.build_model("second", models.prepare_model_config("second", cfg, TRAIN_BOXES))
        missing = second.load_state_dict(model.state_dict(), strict=False).missing_keys
        assert not missing
        with torch.no_grad():
            alone = second.eval().predict(second(batch), batch)
        assert all(_equal_outputs(a, b) for a, b in zip(first, alone))
