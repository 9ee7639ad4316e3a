"""Every registered detector follows the contract `detbench.train.detector.Detector`.

Each model is built from its own configs/<name>.yaml with the smoke preset (the narrow
widths), after `prepare_model_config`, and run once in training and once in eval mode on a
two-frame batch: one frame with a vehicle, one with neither points nor boxes.
"""
import inspect
import math

import numpy as np
import pytest
import torch

import models
from detbench.data.batch import Batch, Detections, Sample, collate
from detbench.train.detector import Detector, TwoStageDetector
from detbench.train.run_config import load_run_config
from tests.helpers import box_points

CAR = np.array([20.0, 1.0, 0.8, 4.5, 1.9, 1.6, 0.3], np.float32)  # metres, radians


def two_frames() -> Batch:
    return collate([Sample(box_points(CAR, 512, margin=0.1), CAR[None], "car"),
                    Sample(np.zeros((0, 4), np.float32), np.zeros((0, 7), np.float32), "empty")])


def smoke_model(name: str) -> torch.nn.Module:
    cfg = load_run_config(name, "smoke")
    model_cfg = models.prepare_model_config(name, cfg["model"], np.stack([CAR, CAR * [1, 1, 1, 1.1, 1, 1, 1]]))
    torch.manual_seed(0)
    return models.build_model(name, model_cfg)


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_class_declares_the_contract(name):
    cls = models.REGISTRY[name]
    assert issubclass(cls, torch.nn.Module)
    for method, params in (("forward", ["batch"]), ("loss", ["outputs", "batch"]), ("predict", ["outputs", "batch"])):
        assert len(inspect.signature(getattr(cls, method)).parameters) == 1 + len(params), f"{name}.{method}"
    prep = inspect.getattr_static(cls, "prepare_config", None)
    assert isinstance(prep, (staticmethod, classmethod)), f"{name}.prepare_config must be a static or class method"
    assert list(inspect.signature(cls.prepare_config).parameters)[-2:] == ["model_cfg", "train_boxes"]
    from models.stages import StageConfig

    assert isinstance(cls.CONFIG, type) and issubclass(cls.CONFIG, StageConfig), f"{name}.CONFIG: its typed config"
    stages = inspect.getattr_static(cls, "STAGES", None)
    assert isinstance(stages, dict) and stages and all(
        isinstance(k, str) and isinstance(v, list) and v and all(isinstance(c, str) for c in v)
        for k, v in stages.items()), f"{name}.STAGES must map stage names to lists of child module names"


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_model_follows_the_contract(name):
    model = smoke_model(name)
    assert isinstance(model, Detector)
    children = dict(model.named_children())
    listed = [c for cs in model.STAGES.values() for c in cs]
    assert set(listed) <= set(children) and len(listed) == len(set(listed)), f"{name}.STAGES: {model.STAGES}"

    batch = two_frames()
    model.train()
    total, parts = model.loss(model(batch), batch)
    assert total.dim() == 0 and torch.isfinite(total) and total.requires_grad
    assert parts and all(isinstance(k, str) and isinstance(v, float) and math.isfinite(v) for k, v in parts.items())
    total.backward()
    empty = collate([Sample(np.zeros((0, 4), np.float32), np.zeros((0, 7), np.float32), "empty")])
    total_e, parts_e = model.loss(model(empty), empty)
    assert torch.isfinite(total_e) and set(parts_e) == set(parts), "loss parts must keep their keys"

    model.eval()
    with torch.no_grad():
        dets = model.predict(model(batch), batch)
    assert isinstance(dets, list) and len(dets) == batch.batch_size
    for d in dets:
        assert isinstance(d, Detections)
        k = d.boxes.shape[0]
        assert d.boxes.shape == (k, 7) and d.scores.shape == (k,) and d.labels.shape == (k,)
        assert d.boxes.dtype == torch.float32 and d.scores.dtype == torch.float32 and d.labels.dtype == torch.int64
        assert bool(((d.scores >= 0) & (d.scores <= 1)).all())


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_channels_last_weights_compute_the_same_model(name):
    """train.channels_last and tools/benchmark.py --channels-last hold the 2D convolution weights in NHWC: every
    2D convolution's output and the training loss are those of the contiguous model (float32 sums in another
    order: within 1e-4; the proposals of an untrained model tie in score, so their order, not their values, may
    differ)."""
    import copy

    from detbench.train.detector import channels_last_2d

    model = smoke_model(name)
    nhwc = channels_last_2d(copy.deepcopy(model))
    convs = [m for m in nhwc.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    assert convs or name == "pointrcnn"  # PointRCNN has no dense 2D convolution: nothing to convert
    assert all(m.weight.is_contiguous(memory_format=torch.channels_last) for m in convs)
    batch = two_frames()
    losses = []
    for m in (model, nhwc):
        torch.manual_seed(0)
        m.train()
        losses.append(float(m.loss(m(batch), batch)[0].detach()))
    assert losses[0] == pytest.approx(losses[1], rel=1e-4, abs=1e-5)
    outputs = ([], [])
    for m, seen in zip((model, nhwc), outputs):
        for conv in m.modules():
            if isinstance(conv, (torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
                conv.register_forward_hook(lambda mod, args, out, seen=seen: seen.append(out))
        with torch.no_grad():
            m.eval()(batch)
    assert len(outputs[0]) == len(outputs[1]) >= len(convs)
    for a, b in zip(*outputs):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    assert all(b.is_contiguous(memory_format=torch.channels_last) for b in outputs[1] if b.shape[1] > 1)


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_two_stage_models_declare_the_output_stage_switch(name):
    """The models with a proposal and a refinement stage follow `TwoStageDetector` (tools/eval.py --stage);
    the others do not claim to."""
    model = smoke_model(name)
    assert isinstance(model, TwoStageDetector) == (name in ("ct3d", "pointrcnn")), name
    if isinstance(model, TwoStageDetector):
        model.set_output_stage("proposals")
        model.set_output_stage("refined")
        with pytest.raises(ValueError, match="'refined' or 'proposals'"):
            model.set_output_stage("rpn")


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_model_config_is_named_by_its_file_and_declares_its_width_keys(name):
    """configs/<name>.yaml configures the registered `name` (written nowhere else) and lists the keys of its
    model: section that hold channel widths, each present in every preset's config."""
    from detbench.config import get
    from detbench.train.run_config import preset_names, width_keys

    keys = width_keys(name)
    assert keys, f"configs/{name}.yaml: width_keys is empty, so the trade study has no width knob for {name}"
    for preset in [None, *preset_names()]:
        cfg = load_run_config(name, preset)
        assert cfg["model"]["name"] == name and "width_keys" not in cfg
        missing = [k for k in keys if get(cfg["model"], k) is None]
        assert not missing, f"{name} ({preset or 'no'} preset): width_keys {missing} not in its model: section"
