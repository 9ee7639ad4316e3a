"""Numerical stability of training.

1. Every registered model (smoke preset sizes, seeded random initialisation) gives a finite
   loss and finite gradients on the extreme frames: a batch of only empty frames, a frame with
   200 vehicles, a frame whose single vehicle stands 1 m from the sensor, a vehicle with one
   point at 150 m. The frames go through the training data path (`TrainingSet`: range crop,
   LiDAR-detected filter, collate) without augmentation.
2. The loop skips a step whose loss or gradient is NaN or inf (no update, BatchNorm statistics
   restored), logs it with its frame ids, and stops the run after `train.max_nonfinite_steps`
   in a row, naming the frames and the last good checkpoint.
3. Mixed precision keeps float32 master weights and scales the loss: run on the CPU through the
   same code path (float16 autocast + GradScaler on the CPU), and on CUDA where it exists.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import models
from detbench.config import ConfigError
from detbench.data.augment import AugmentConfig
from detbench.data.batch import Batch, collate
from detbench.data.frame import Frame, Sensor
from detbench.train import CheckpointManager, TrainConfig, TrainingSet, load_checkpoint, seed_everything, train
from detbench.train import loop as loop_mod
from detbench.train.loop import NonFiniteTrainingError
from detbench.train.run_config import load_run_config
from tests.helpers import DATA, FRAMES, RUN_CONFIG, TinyDetector, box_points, make_set

NO_AUGMENT = AugmentConfig.from_dict({k: {"enabled": False} for k in (
    "random_world_flip", "random_world_rotation", "random_world_scaling", "gt_sampling")})


# ---------------------------------------------------------------- 1. extreme frames, every model
def _car(x: float, y: float, heading: float = 0.0) -> np.ndarray:
    return np.array([x, y, 0.8, 4.5, 1.9, 1.6, heading], np.float32)


def _frame(frame_id: str, points: np.ndarray, boxes: np.ndarray) -> Frame:
    m = len(boxes)
    boxes = np.asarray(boxes, np.float32).reshape(-1, 7)
    return Frame(frame_id, frame_id[:4], np.asarray(points, np.float32).reshape(-1, 4), boxes,
                 np.array(["car"] * m), np.arange(m, dtype=np.int64), np.zeros(m, dtype=np.int64),
                 Sensor(height=1.8)).check()


def extreme_frames() -> dict[str, list[Frame]]:
    """Name -> the frames of one batch."""
    empty = np.zeros((0, 4), np.float32)
    crowd = [_car(6.0 + 7.4 * i, -13.5 + 3.0 * j, 0.05 * ((i + j) % 3 - 1)) for i in range(20) for j in range(10)]
    near = _car(1.0, 0.0)  # centre 1 m ahead: the box reaches 1.25 m behind the sensor, out of the range
    near_pts = box_points(near, 512, margin=0.1)
    far = _car(149.0, 0.5)
    return {
        "empty_batch": [_frame("0000_000", empty, np.zeros((0, 7))), _frame("0000_001", empty, np.zeros((0, 7)))],
        "200_vehicles": [_frame("0001_000", np.concatenate([box_points(b, 27, margin=0.1) for b in crowd]),
                                np.stack(crowd))],
        "vehicle_1m": [_frame("0002_000", near_pts[near_pts[:, 0] >= 0], near[None])],
        "one_point_150m": [_frame("0003_000", np.array([[146.8, 0.5, 0.9, 0.3]]), far[None])],
    }


def _batch(frames: list[Frame], pc_range):
    ts = TrainingSet(frames, pc_range, augment=NO_AUGMENT, seed=0)
    return collate([ts.get(i, 0, augment=False) for i in range(len(frames))])


@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_every_model_has_finite_loss_and_gradients_on_extreme_frames(name):
    cfg = load_run_config(name, "smoke")
    boxes = np.stack([_car(20, 0), _car(40, 3.5) * [1, 1, 1, 1.1, 1, 1, 1]])
    model_cfg = models.prepare_model_config(name, cfg["model"], boxes)
    torch.manual_seed(0)
    model = models.build_model(name, model_cfg).train()
    batches = {k: _batch(v, model_cfg["point_cloud_range"]) for k, v in extreme_frames().items()}
    # the data path keeps the extreme vehicles: all 200, the one at 1 m, the one with a point at 150 m
    assert [int(batches[k].gt_mask.sum()) for k in ("empty_batch", "200_vehicles", "vehicle_1m", "one_point_150m")] \
        == [0, 200, 1, 1]
    assert batches["one_point_150m"].points.shape[0] == 1 and batches["empty_batch"].points.shape[0] == 0
    for case, batch in batches.items():
        model.zero_grad(set_to_none=True)
        total, parts = model.loss(model(batch), batch)
        assert torch.isfinite(total), (name, case, parts)
        assert all(math.isfinite(v) for v in parts.values()), (name, case, parts)
        total.backward()
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        assert grads, (name, case)
        bad = [n for n, p in model.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
        assert not bad, (name, case, bad[:5])
        if case != "empty_batch":  # a frame with vehicles teaches something
            assert sum(float(g.abs().sum()) for g in grads) > 0, (name, case)


# ---------------------------------------------------------------- 2. the loop skips non-finite steps
class FaultyDetector(TinyDetector):
    """TinyDetector whose training forward pass `k` (1-based) goes wrong for k in `nan_input` (NaN in the
    features before BatchNorm: a NaN loss and NaN BatchNorm statistics) or `nan_grad` (finite loss, NaN
    gradient). It keeps a copy of its weights at the start of every training forward pass."""

    def __init__(self, nan_input=(), nan_grad=()):
        super().__init__()
        self.nan_input, self.nan_grad = set(nan_input), set(nan_grad)
        self.weights_at_call: dict[int, dict[str, torch.Tensor]] = {}

    def forward(self, batch):
        if not (self.training and torch.is_grad_enabled()):  # evaluation, or the BatchNorm statistics' passes
            return super().forward(batch)
        call = self.train_calls + 1
        self.weights_at_call[call] = {k: v.detach().clone() for k, v in self.state_dict().items()}
        if call in self.nan_input:
            nan_points = torch.cat([batch.points[:, :1], batch.points[:, 1:] * float("nan")], 1)
            batch = Batch(nan_points, batch.gt_boxes, batch.gt_mask, batch.frame_ids, batch.batch_size)
        out = super().forward(batch)
        if call in self.nan_grad:
            out.boxes.register_hook(lambda g: g * float("nan"))
        return out


def _train(tmp_path, out, model, epochs=2, **over):
    cfg = TrainConfig.from_dict({**RUN_CONFIG["train"], "epochs": epochs, "tensorboard": False, "bev_image": False,
                                 **over})
    rc = {**RUN_CONFIG, "train": {**RUN_CONFIG["train"], "epochs": epochs, **over}}
    return train(model, make_set(tmp_path), cfg, tmp_path / out, model_name="tiny", run_config=rc, data_info=DATA,
                 progress=False)


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_non_finite_step_is_skipped_logged_and_changes_nothing(tmp_path, capsys):
    seed_everything(0)
    model = FaultyDetector(nan_input={2}, nan_grad={6})  # 4 steps per epoch: step 2 of epoch 1, step 2 of epoch 2
    res = _train(tmp_path, "run", model)
    assert res.epochs_completed == 2 and res.global_step == 8 and not res.interrupted
    # a skipped step changes no weight and no BatchNorm statistic; a good step does
    w = model.weights_at_call
    assert _same(w[2], w[3]) and _same(w[6], w[7]) and not _same(w[3], w[4])
    assert all(torch.isfinite(v).all() for v in model.state_dict().values() if v.is_floating_point())
    # logged with the frame ids: console, history.json, averaged losses finite
    out = capsys.readouterr().out
    assert "epoch 1, step 2: non-finite loss" in out and "epoch 2, step 2: non-finite gradient" in out
    h = res.history
    for rec, cause in zip(h, ("loss", "gradient")):
        assert rec["skipped_steps"] == 1 and rec["nonfinite_steps"][0]["nonfinite"] == cause
        frames = rec["nonfinite_steps"][0]["frames"]
        assert len(frames) == 2 and all(f in out for f in frames)
        assert math.isfinite(rec["losses"]["loss"])
    assert h[0]["nonfinite_steps"][0]["loss"] == "nan" and math.isfinite(h[1]["nonfinite_steps"][0]["loss"])


def test_non_finite_steps_in_a_row_stop_the_run_keeping_the_last_good_checkpoint(tmp_path):
    seed_everything(0)
    model = FaultyDetector(nan_input=set(range(3, 100)))  # every step from the 3rd on
    with pytest.raises(NonFiniteTrainingError) as e:
        _train(tmp_path, "run", model, epochs=3, max_nonfinite_steps=3)
    msg = str(e.value)
    ckpt_path = tmp_path / "run" / "checkpoints" / "epoch_001.pt"
    assert "3 steps in a row had a non-finite loss or gradient (the last at epoch 2, step 1" in msg
    assert f"the newest checkpoint, {ckpt_path}, holds the weights of the last step with a finite loss" in msg
    assert "frames ['" in msg and "train.max_nonfinite_steps" in msg and "train.lr" in msg
    assert [p.name for p in CheckpointManager(tmp_path / "run" / "checkpoints").list()] == ["epoch_001.pt"]
    ckpt = load_checkpoint(ckpt_path)
    # the weights after step 2, the last good one (the BatchNorm statistics are recomputed for them: precise BN)
    params = {name for name, _ in model.named_parameters()}
    assert _same({k: v for k, v in ckpt["model"].items() if k in params},
                 {k: v for k, v in model.weights_at_call[3].items() if k in params})
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values())
    assert len(model.weights_at_call) == 5  # nothing ran after the stop
    # a streak shorter than the limit does not stop the run; the limit is a validated config key
    seed_everything(0)
    res = _train(tmp_path, "run2", FaultyDetector(nan_input={3, 4}), max_nonfinite_steps=3)
    assert res.epochs_completed == 2 and res.history[0]["skipped_steps"] == 2
    with pytest.raises(ConfigError, match="max_nonfinite_steps must be >= 1"):
        TrainConfig.from_dict({"max_nonfinite_steps": 0})


# ---------------------------------------------------------------- 3. mixed precision
def _amp_run(tmp_path, device: torch.device, epochs: int = 2):
    """SECOND (smoke sizes) trained `epochs` x 4 steps with mixed precision on `device` (the scaler skips the
    first ~5 steps, as designed: the initial loss scale 2**16 overflows float16 until it is lowered to 2**11;
    they are no updates)."""
    from detbench.train.distributed import DistInfo

    run_cfg = load_run_config("second", "smoke", overrides=[f"train.epochs={epochs}", "train.tensorboard=false"])
    model_cfg = models.prepare_model_config("second", run_cfg["model"], np.concatenate([f.boxes for f in FRAMES]))
    seed_everything(0)
    model = models.build_model("second", model_cfg)
    start = {k: v.clone() for k, v in model.state_dict().items()}
    cfg = TrainConfig.from_dict(run_cfg["train"])
    ts = TrainingSet(FRAMES, model_cfg["point_cloud_range"], augment=NO_AUGMENT, seed=0)
    res = train(model, ts, cfg, tmp_path / "amp", model_name="second", run_config=run_cfg, data_info=DATA,
                dist_info=DistInfo(device=device), progress=False)
    return model, start, res


def _check_amp(model, start, res):
    # float32 master weights, float32 optimizer state; the loss was scaled (the scaler's state is saved)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    ckpt = load_checkpoint(res.last_checkpoint)
    assert ckpt["scaler"] and 0 < ckpt["scaler"]["scale"] <= 65536.0
    moments = [v for st in ckpt["optimizer"]["state"].values() for k, v in st.items() if k in ("exp_avg", "exp_avg_sq")]
    assert moments and all(v.dtype == torch.float32 for v in moments)
    assert all(v.dtype == torch.float32 for v in ckpt["model"].values() if v.is_floating_point())
    # the steps the scaler skipped are counted apart, not averaged into the losses of the steps that updated
    skipped = [r["scaler_skipped_steps"] for r in res.history]
    assert sum(skipped) >= 1 and res.history[-1]["loss_scale"] == ckpt["scaler"]["scale"]
    assert all(math.isfinite(r["losses"]["loss"]) for r, n in zip(res.history, skipped) if n < 4)
    assert all(r["losses"] == {} for r, n in zip(res.history, skipped) if n == 4)  # no update in that epoch
    assert all(torch.isfinite(v).all() for v in model.state_dict().values() if v.is_floating_point())
    # the updates went through the scaler: weights moved, and by small, unscaled amounts
    moved = [float((v.cpu() - start[k]).abs().max()) for k, v in model.state_dict().items()
             if v.is_floating_point() and "running" not in k]
    assert max(moved) > 0 and max(moved) < 1.0


def test_mixed_precision_training_keeps_float32_master_weights_cpu_code_path(tmp_path, monkeypatch):
    """The CUDA mixed-precision path, run on the CPU (float16 autocast + a CPU GradScaler): the same code."""
    monkeypatch.setattr(loop_mod, "_use_amp", lambda cfg, dev: cfg.amp)
    _check_amp(*_amp_run(tmp_path, torch.device("cpu")))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_mixed_precision_training_on_cuda(tmp_path):
    assert loop_mod._use_amp(TrainConfig.from_dict({}), torch.device("cuda"))
    _check_amp(*_amp_run(tmp_path, torch.device("cuda")))


class OverflowingDetector(FaultyDetector):
    """TinyDetector with its loss times 1e-3 (so the GradScaler's first scale, 2 ** 16, leaves its float16
    gradients finite), and times 1e30 at training forward pass k in `overflow`: a finite loss whose scaled
    gradients overflow float16 (any scale > 1 makes them). At pass k in `inf_output` an output box is inf and
    the loss, as a regression loss that zeroes non-finite differences, stays finite."""

    def __init__(self, overflow=(), nan_input=(), inf_output=()):
        super().__init__(nan_input=nan_input)
        self.overflow, self.inf_output = set(overflow), set(inf_output)

    def forward(self, batch):
        out = super().forward(batch)
        if self.training and self.train_calls in self.inf_output:
            out = out._replace(boxes=out.boxes + torch.tensor(float("inf")).to(out.boxes.dtype))
        return out

    def loss(self, out, batch):
        total, parts = super().loss(out._replace(boxes=torch.nan_to_num(out.boxes, posinf=0.0)), batch)
        return total * (1e30 if self.train_calls in self.overflow else 1e-3), parts


def test_steps_the_grad_scaler_skips_are_no_updates(tmp_path, monkeypatch):
    """A step whose scaled gradients overflow changes nothing, is left out of the epoch's averaged losses and
    is counted apart, with the scale it leaves, so a collapsing scale shows in history.json."""
    monkeypatch.setattr(loop_mod, "_use_amp", lambda cfg, dev: cfg.amp)  # the CUDA path, run on the CPU
    seed_everything(0)
    model = OverflowingDetector(overflow={2, 5, 6})  # 4 steps per epoch: one skip in epoch 1, two in epoch 2
    res = _train(tmp_path, "run", model)
    w = model.weights_at_call
    assert _same(w[2], w[3]) and _same(w[5], w[6]) and _same(w[6], w[7]) and not _same(w[3], w[4])
    h = res.history
    assert [r["scaler_skipped_steps"] for r in h] == [1, 2] and "skipped_steps" not in h[0]
    assert [r["loss_scale"] for r in h] == [2.0 ** 15, 2.0 ** 13]  # halved at each skip from 2 ** 16
    assert all(r["losses"]["loss"] < 0.01 for r in h), [r["losses"] for r in h]  # the 1e30 losses left out
    assert load_checkpoint(res.last_checkpoint)["scaler"]["scale"] == 2.0 ** 13


def test_under_mixed_precision_the_models_non_finite_steps_keep_the_scale(tmp_path, monkeypatch):
    """A NaN loss, or an inf in the forward pass's outputs that the loss hides, is the model's fault: the step is
    skipped and logged as non-finite ("loss", "output"), and the GradScaler keeps its scale (halving it cannot
    help); an overflow of the scaled gradients still halves it."""
    monkeypatch.setattr(loop_mod, "_use_amp", lambda cfg, dev: cfg.amp)
    seed_everything(0)
    model = OverflowingDetector(nan_input={2}, inf_output={3}, overflow={6})
    res = _train(tmp_path, "run", model)
    w = model.weights_at_call
    assert _same(w[2], w[3]) and _same(w[3], w[4]) and _same(w[6], w[7])
    h = res.history
    assert [r["nonfinite"] for r in h[0]["nonfinite_steps"]] == ["loss", "output"] and "skipped_steps" not in h[1]
    assert [r["scaler_skipped_steps"] for r in h] == [0, 1]
    assert [r["loss_scale"] for r in h] == [2.0 ** 16, 2.0 ** 15]
