"""Warm starts: `init_from_checkpoint` (tools/train.py --init-from)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import models
from detbench.train.checkpoint import CheckpointError, TrainState, init_from_checkpoint, save_checkpoint
from detbench.train.run_config import load_run_config

BOXES = np.array([[10.0, 2.0, 0.8, 4.5, 1.8, 1.5, 0.1], [20.0, -3.0, 0.9, 4.8, 1.9, 1.6, -0.2]], np.float32)


def _model(name: str, overrides=()):
    cfg = models.prepare_model_config(name, load_run_config(name, "smoke", overrides=list(overrides))["model"], BOXES)
    torch.manual_seed(1 if name == "second" else 2)
    return models.build_model(name, cfg), cfg


def _save(tmp_path, model, cfg, name):
    return save_checkpoint(tmp_path / f"{name}.pt", model=model, state=TrainState(), config={"model": cfg},
                           data={"source": "test"}, model_name=name)


def test_ct3d_starts_from_second_everywhere_but_its_refinement(tmp_path):
    second, scfg = _model("second")
    path = _save(tmp_path, second, scfg, "second")
    ct3d, ccfg = _model("ct3d")
    before = copy.deepcopy(ct3d.state_dict())
    rec = init_from_checkpoint(ct3d, path, ccfg)
    after, src = ct3d.state_dict(), second.state_dict()
    assert rec["loaded_tensors"] == len(src) and rec["unused_tensors"] == 0
    assert rec["new_tensors"] == len(after) - len(src) > 0
    for k, v in after.items():
        if k in src:
            assert torch.equal(v, src[k]), k
        else:  # the refinement head keeps its own initialisation
            assert k.startswith(("roi_head.", "refine.")), k
            assert torch.equal(v, before[k]), k
    # a weight that differs between the two random initialisations really was copied
    assert any(not torch.equal(before[k], src[k]) for k in src if before[k].is_floating_point())


def test_refused_without_a_shared_layer_or_with_another_model_config(tmp_path):
    second, scfg = _model("second")
    path = _save(tmp_path, second, scfg, "second")
    prcnn, pcfg = _model("pointrcnn")
    with pytest.raises(CheckpointError, match="no weight of this second checkpoint fits"):
        init_from_checkpoint(prcnn, path, pcfg)
    # same shapes, other meaning: a voxel size the checkpoint was not trained with
    ct3d, ccfg = _model("ct3d")
    ccfg = copy.deepcopy(ccfg)
    ccfg["voxel_size"] = [v * 2 for v in ccfg["voxel_size"]]
    with pytest.raises(CheckpointError, match="another model config.*voxel_size"):
        init_from_checkpoint(ct3d, path, ccfg)
    # values the run resolves from its own data (anchor sizes at another height) may differ
    ccfg = copy.deepcopy(_model("ct3d")[1])
    ccfg["head"]["anchor_sizes"] = "auto"
    assert init_from_checkpoint(ct3d, path, ccfg)["loaded_tensors"] > 0


def test_refused_for_non_finite_weights_and_another_shape(tmp_path):
    second, scfg = _model("second")
    state = second.state_dict()
    key = next(k for k, v in state.items() if v.is_floating_point() and v.ndim > 1)
    with torch.no_grad():
        state[key].view(-1)[0] = float("nan")
    path = _save(tmp_path, second, scfg, "second_nan")
    ct3d, ccfg = _model("ct3d")
    with pytest.raises(CheckpointError, match="NaN or inf"):
        init_from_checkpoint(ct3d, path, ccfg)
    wide, wcfg = _model("second", ["model.backbone2d.num_filters=[8,16]"])
    path = _save(tmp_path, wide, {**wcfg, "backbone2d": scfg["backbone2d"]}, "second_wide")  # config hides it
    with pytest.raises(CheckpointError, match="another shape"):
        init_from_checkpoint(_model("ct3d")[0], path, ccfg)
