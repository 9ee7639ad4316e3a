"""A first stage that decodes a box to infinity: both two-stage models drop and count it between their stages
(training, evaluation, `predict_frames`), and the training's bird's-eye preview neither fails on a box it
cannot draw nor ends a training when it fails."""
import io
import math

import numpy as np
import pytest
import torch

import models
from detbench.data.batch import Detections
from detbench.train.run_config import load_run_config
from tests.helpers import DATA, RUN_CONFIG, TinyDetector, batch_of, box_points, make_frame, make_set

CAR = [10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.3]
# what the first stage decodes for three of its best candidates: inf, NaN, and a finite box 1e20 m long (its BEV
# diagonal, the radius of CT3D's cylinder, overflows float32)
WILD = {0: (0, math.inf), 1: (1, math.nan), 2: (3, 1e20)}


def tiny_model(name: str) -> torch.nn.Module:
    cfg = load_run_config(name, "smoke")["model"]
    if name == "pointrcnn":
        cfg["sampling"]["num_points"] = 256
        cfg["point_head"]["mean_size"] = [4.5, 1.9, 1.6]
    else:
        cfg = models.prepare_model_config(name, cfg, np.array([CAR], np.float32))
    torch.manual_seed(0)
    return models.build_model(name, cfg)


def inject_wild_boxes(model: torch.nn.Module) -> None:
    """The first stage's decoded boxes get the WILD values at its three best-scored candidates of each frame."""
    head = model.rpn.head if hasattr(model, "rpn") else model.point_head
    real = head.decode

    def decode(*args, **kwargs):
        boxes, scores = real(*args, **kwargs)
        boxes = boxes.clone()
        scores = scores.clone()
        for i in range(boxes.shape[0]):
            top = scores[i].topk(3).indices
            for k, (column, value) in WILD.items():
                boxes[i, top[k], column] = value
                scores[i, top[k]] = 0.99  # among the best: they would be proposed
        return boxes, scores

    head.decode = decode


def scene_batch():
    rng = np.random.default_rng(0)
    road = rng.uniform([0, -10, 0, 0], [40, 10, 0.2, 1], (500, 4))
    return batch_of([np.concatenate([box_points(CAR, 300), road]).astype(np.float32)], [[CAR]])


@pytest.mark.parametrize("name", ["ct3d", "pointrcnn"])
def test_non_finite_first_stage_boxes_are_dropped_and_counted(name):
    """Training and evaluation go on with the three wild boxes left out: a finite loss that logs them
    (num_dropped_proposals), finite predictions, and Proposals.dropped counting them."""
    model = tiny_model(name)
    inject_wild_boxes(model)
    batch = scene_batch()
    model.train()
    torch.manual_seed(1)
    out = model(batch)
    total, parts = model.loss(out, batch)
    assert torch.isfinite(total) and parts["num_dropped_proposals"] == 3.0
    assert out.proposals.dropped.tolist() == [3] and bool(torch.isfinite(out.proposals.rois).all())
    model.eval()
    with torch.no_grad():
        out = model(batch)
        dets = model.predict(out, batch)
    assert out.proposals.dropped.tolist() == [3]
    assert len(dets) == 1 and bool(torch.isfinite(dets[0].boxes).all())


def test_predict_frames_reports_the_dropped_boxes(capsys):
    """Evaluation of a model whose first stage decodes boxes to infinity ends with its detections and one
    warning line that counts the dropped boxes, not in cylinder_query's ValueError."""
    from detbench.train.inference import predict_frames

    model = tiny_model("ct3d")
    inject_wild_boxes(model)
    frames = [make_frame(s, f"0000_{s:03d}") for s in range(3)]
    pc_range = load_run_config("ct3d", "smoke")["model"]["point_cloud_range"]
    got = predict_frames(model, frames, pc_range, batch_size=2, progress=False)
    assert sorted(got) == sorted(f.frame_id for f in frames)
    err = capsys.readouterr().err
    assert "warning: predict: the first stage decoded 9 box(es) over 3 frames to non-finite geometry" in err


@pytest.mark.parametrize("wild", [1e20, 1e9, math.inf])
def test_preview_draws_a_frame_with_a_box_it_cannot_place(wild):
    """A prediction 1e20 m away (or 1e9 m long, or inf) is left out of the bird's-eye figure and counted in
    its legend; the figure renders (matplotlib's text renderer fails on a label that far away)."""
    from detbench.train.logger import bev_figure

    pred = np.array([[20, 0, 1, 4, 2, 1.5, 0.3], [wild, 3, 1, 4, 2, 1.5, 0.1], [30, 0, 1, wild, 2, 1.5, 0.2]])
    fig = bev_figure(np.zeros((10, 4)), pred[:1], pred, np.array([0.9, 0.8, 0.7]), [0, -40, -3, 70.4, 40, 1])
    fig.savefig(io.BytesIO(), format="png")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any("(3; 2 off the view, not drawn)" in t for t in labels), labels


class _PreviewBreaks(TinyDetector):
    """Trains as TinyDetector; its predictions in evaluation mode (the preview's) raise."""

    def predict(self, out, batch) -> list[Detections]:
        if not self.training:
            raise RuntimeError("FT_Render_Glyph failed with error 0x62: raster overflow")
        return super().predict(out, batch)


def test_a_failing_preview_is_a_warning_and_the_training_completes(tmp_path, capsys):
    """The per-epoch preview fails every epoch: each failure is one warning line, and the training saves
    every epoch's checkpoint and ends normally."""
    from detbench.train import TrainConfig, seed_everything, train

    cfg = TrainConfig.from_dict({**RUN_CONFIG["train"], "epochs": 2, "tensorboard": True, "bev_image": True})
    seed_everything(cfg.seed)
    res = train(_PreviewBreaks(), make_set(tmp_path), cfg, tmp_path / "run", model_name="tiny",
                run_config=RUN_CONFIG, data_info=DATA, progress=False)
    assert res.epochs_completed == 2 and not res.interrupted
    assert sorted(p.name for p in (tmp_path / "run" / "checkpoints").glob("epoch_*.pt")) == ["epoch_001.pt",
                                                                                              "epoch_002.pt"]
    err = capsys.readouterr().err
    for epoch in (1, 2):
        assert (f"warning: the bird's-eye preview of epoch {epoch} was not drawn (RuntimeError: FT_Render_Glyph "
                f"failed with error 0x62: raster overflow); the training goes on") in err
