"""Training infrastructure (detbench.train: the loop, checkpoints, resume, distributed runs) with the tiny
test-only detector and synthetic frames of tests/helpers.py."""
import math
import os
import pickle
import socket

import numpy as np
import pytest
import torch
from torch import nn

from detbench.config import ConfigError
from detbench.data.augment import AugmentConfig
from detbench.data.batch import Sample, collate
from detbench.data.gt_database import build_gt_database
from detbench.train import (
    CheckpointError, CheckpointManager, TrainConfig, TrainingSet, cleanup, init_distributed, load_checkpoint,
    main_process_first, seed_everything, train,
)
from tests.helpers import DATA, FRAMES, PC_RANGE, RUN_CONFIG, TinyDetector, make_set


def run(tmp_path, out, epochs=2, resume=False, model_kw=None, **over):
    """Seed, build a TinyDetector(**model_kw) and train it in tmp_path/out; returns (model, TrainResult)."""
    cfg = TrainConfig.from_dict({**RUN_CONFIG["train"], "epochs": epochs, "tensorboard": False, "bev_image": False,
                                 **over})
    seed_everything(cfg.seed)
    model = TinyDetector(**(model_kw or {}))
    rc = {**RUN_CONFIG, "train": {**RUN_CONFIG["train"], "epochs": epochs, **over}}
    res = train(model, make_set(tmp_path), cfg, tmp_path / out, model_name="tiny", run_config=rc, data_info=DATA,
                resume=resume, progress=False)
    return model, res


def same_weights(a: nn.Module, b: nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


# ---------------------------------------------------------------- data hand-offs
def test_collate_pads_boxes_and_tags_points():
    s0 = Sample(np.ones((3, 4), np.float32), np.ones((2, 7), np.float32), "a")
    s1 = Sample(np.zeros((0, 4), np.float32), np.zeros((0, 7), np.float32), "b")
    b = collate([s0, s1])
    assert b.points.shape == (3, 5) and b.points[:, 0].tolist() == [0, 0, 0]
    assert b.gt_boxes.shape == (2, 2, 7) and b.gt_mask.tolist() == [[True, True], [False, False]]
    assert b.boxes_of(1).shape == (0, 7) and b.points_of(0).shape == (3, 4) and b.frame_ids == ["a", "b"]
    empty = collate([s1])
    assert empty.gt_boxes.shape == (1, 0, 7) and empty.to("cpu").batch_size == 1
    with pytest.raises(ValueError, match="points must be"):
        collate([Sample(np.ones((3, 3), np.float32), np.zeros((0, 7), np.float32), "c")])


def test_training_set_uses_detected_vehicles_and_replays_augmentation(tmp_path):
    ts = make_set(tmp_path, gt_sampling=False)
    plain = ts.get(0, 0, augment=False)
    assert len(plain.gt_boxes) == len(FRAMES[0].boxes) - 1  # the vehicle without points is not ground truth
    a, b, c = ts.get(3, epoch=1), ts.get(3, epoch=1), ts.get(3, epoch=2)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.gt_boxes, b.gt_boxes)
    assert not np.array_equal(a.gt_boxes, c.gt_boxes)
    ts.set_epoch(1)
    assert np.array_equal(ts[3].points, a.points)


def test_training_set_from_dataset_builds_the_database_once(tmp_path):
    from detbench.data import DatasetWriter

    root = tmp_path / "data"
    with DatasetWriter(root, heights=[1.8], source={"kind": "test"}, test_fraction=0.25) as w:
        for f in FRAMES:
            w.add([f])
    aug = AugmentConfig.from_dict({"gt_sampling": {"sample_count": 4, "filter_by_min_points": 5}})
    ts = TrainingSet.from_dataset(root, 1.8, PC_RANGE, augment=aug, seed=3, progress=False)
    index = root / "gt_database" / "1.8" / "gt_database.json"
    stamp = index.stat().st_mtime_ns
    train_ids = set(ts.frames.frame_ids)
    assert 0 < len(ts) < len(FRAMES) and ts.sampler is not None
    assert set(ts.sampler.db.frame_ids) <= train_ids  # the database never sees test frames
    s = ts[(1, 0)]
    assert s.points.dtype == np.float32 and s.gt_boxes.shape[1] == 7 and s.frame_id in train_ids
    again = TrainingSet.from_dataset(root, 1.8, PC_RANGE, augment=aug, seed=3, progress=False)
    assert index.stat().st_mtime_ns == stamp and np.array_equal(again[(1, 0)].points, s.points)
    assert np.array_equal(pickle.loads(pickle.dumps(ts))[(1, 0)].points, s.points)  # spawned workers get a copy
    test_set = TrainingSet.from_dataset(root, 1.8, PC_RANGE, augment=aug, split="test", progress=False)
    assert not test_set.training and not set(test_set.frames.frame_ids) & train_ids


def test_train_config_validation():
    with pytest.raises(ConfigError, match="'epochs'"):
        TrainConfig.from_dict({"epoch": 3})
    with pytest.raises(ConfigError, match="pct_start"):
        TrainConfig.from_dict({"pct_start": 1.5})


# ---------------------------------------------------------------- the loop
def test_loss_decreases_and_logs(tmp_path):
    seed_everything(0)
    model = TinyDetector()
    cfg = TrainConfig.from_dict({"epochs": 8, "batch_size": 4, "workers": 0, "lr": 0.05, "log_every": 1})
    ts = make_set(tmp_path)
    seen = []

    def eval_fn(m, epoch):
        assert not m.training
        seen.append(epoch)
        b = collate([ts.get(i, 0, augment=False) for i in range(len(ts))])
        dets = m.predict(m(b), b)
        err = [float((d.boxes[0, :2] - b.boxes_of(i)[0, :2]).abs().mean()) for i, d in enumerate(dets)]
        return {"centre_error_m": float(np.mean(err))}

    res = train(model, ts, cfg, tmp_path / "run", model_name="tiny", run_config={"train": {}}, data_info=DATA,
                eval_fn=eval_fn, progress=False)
    losses = [r["losses"]["loss"] for r in res.history]
    assert all(math.isfinite(v) for v in losses)
    assert losses[-1] < 0.6 * losses[0], losses
    assert seen == list(range(1, 9)) and res.history[-1]["metrics"]["centre_error_m"] < res.history[0]["metrics"][
        "centre_error_m"]
    assert not res.interrupted and res.epochs_completed == 8 and res.global_step == 16
    assert (tmp_path / "run" / "history.json").is_file()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(tmp_path / "run" / "tensorboard"))
    ea.Reload()
    tags = ea.Tags()
    assert "bev/predictions_vs_ground_truth" in tags["images"]
    assert {"train/loss", "train/lr", "epoch/loss", "eval/centre_error_m"} <= set(tags["scalars"])
    assert len(ea.Scalars("train/lr")) == 16


def test_resume_after_crash_equals_uninterrupted_run(tmp_path):
    straight, _ = run(tmp_path, "straight", epochs=2)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run(tmp_path, "crashed", epochs=2, model_kw={"crash_at": 6})  # 4 steps per epoch: dies in epoch 2
    assert [p.name for p in CheckpointManager(tmp_path / "crashed" / "checkpoints").list()] == ["epoch_001.pt"]
    resumed, res = run(tmp_path, "crashed", epochs=2, resume=True)
    assert res.epochs_completed == 2 and res.global_step == 8
    assert same_weights(straight, resumed)


def test_ctrl_c_mid_epoch_saves_and_resume_equals_uninterrupted_run(tmp_path, capsys):
    straight, _ = run(tmp_path, "straight", epochs=2)
    _, res = run(tmp_path, "stopped", epochs=2, model_kw={"interrupt_at": 6})
    assert res.interrupted and res.epochs_completed == 1 and res.global_step == 6
    assert res.last_checkpoint.name == "epoch_001_step_000002.pt"
    assert "--resume" in capsys.readouterr().out
    resumed, res2 = run(tmp_path, "stopped", epochs=2, resume=True)
    assert not res2.interrupted and res2.global_step == 8
    assert same_weights(straight, resumed)


def test_worker_processes_give_the_same_result(tmp_path):
    a, _ = run(tmp_path, "w0", epochs=2, workers=0)
    b, _ = run(tmp_path, "w1", epochs=2, workers=1)  # spawned, persistent across the two epochs
    assert same_weights(a, b)


def test_keep_last_n_and_fresh_run_refuses_old_checkpoints(tmp_path):
    _, res = run(tmp_path, "keep", epochs=4, keep_checkpoints=2)
    assert [p.name for p in CheckpointManager(tmp_path / "keep" / "checkpoints").list()] == ["epoch_003.pt",
                                                                                             "epoch_004.pt"]
    with pytest.raises(CheckpointError, match="--resume"):
        run(tmp_path, "keep", epochs=4, keep_checkpoints=2)
    model, res = run(tmp_path, "keep", epochs=4, keep_checkpoints=2, resume=True)  # already complete: no-op
    assert res.epochs_completed == 4 and res.global_step == 16


# ---------------------------------------------------------------- checkpoint errors
def test_checkpoint_errors_name_the_file_and_fix(tmp_path):
    _, res = run(tmp_path, "ck", epochs=1)
    good = res.last_checkpoint
    ckpt = load_checkpoint(good, model_name="tiny", data=DATA)
    assert ckpt["state"]["epoch"] == 1 and ckpt["config"]["train"]["epochs"] == 1

    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r"truncated\.pt: cannot read.*damaged"):
        load_checkpoint(truncated)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00\x01 not a checkpoint at all")
    with pytest.raises(CheckpointError, match=r"garbage\.pt"):
        load_checkpoint(garbage)
    bare = tmp_path / "bare.pt"
    torch.save(TinyDetector().state_dict(), bare)
    with pytest.raises(CheckpointError, match=r"bare\.pt: not a detbench checkpoint"):
        load_checkpoint(bare)
    unsafe = tmp_path / "unsafe.pt"
    torch.save({"format": "detbench-checkpoint", "obj": ValueError("x")}, unsafe)
    with pytest.raises(CheckpointError, match=r"unsafe\.pt: holds Python objects"):
        load_checkpoint(unsafe)
    with pytest.raises(CheckpointError, match=r"for model 'tiny', not 'second'"):
        load_checkpoint(good, model_name="second")
    with pytest.raises(CheckpointError, match=r"another config \(train\.lr: 0\.01 \(checkpoint\) vs 0\.02"):
        load_checkpoint(good, config={**RUN_CONFIG, "train": {**RUN_CONFIG["train"], "epochs": 1, "lr": 0.02}})
    with pytest.raises(CheckpointError, match=r"other data \(height"):
        load_checkpoint(good, data={**DATA, "height": 0.5})
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")
    # resuming a run whose newest checkpoint is damaged names it and the older one to fall back to
    _, res = run(tmp_path, "ck2", epochs=2, keep_checkpoints=0)
    res.last_checkpoint.write_bytes(b"broken")
    with pytest.raises(CheckpointError, match=r"epoch_002\.pt.*previous one \(epoch_001\.pt\)"):
        run(tmp_path, "ck2", epochs=2, keep_checkpoints=0, resume=True)
    with pytest.raises(CheckpointError, match=r"another config"):
        run(tmp_path, "ck", epochs=1, lr=0.5, resume=True)
    assert pickle.dumps(ckpt["rng"])  # plain data


# ---------------------------------------------------------------- two processes
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, out: str) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    info = init_distributed("cpu")
    from pathlib import Path

    cfg = TrainConfig.from_dict({"epochs": 2, "batch_size": 2, "workers": 0, "lr": 0.01, "tensorboard": False,
                                 "bev_image": False})
    seed_everything(cfg.seed + rank)  # different initial weights per rank: DDP must broadcast rank 0's
    model = TinyDetector()
    with main_process_first(info):
        db = build_gt_database(FRAMES, Path(out) / "db", progress=False) if rank == 0 else None
    if db is None:
        from detbench.data.gt_database import load_gt_database
        db = load_gt_database(Path(out) / "db")
    aug = AugmentConfig.from_dict({"gt_sampling": {"sample_count": 4, "filter_by_min_points": 5}})
    ts = TrainingSet(FRAMES, PC_RANGE, augment=aug, gt_database=db)
    res = train(model, ts, cfg, Path(out) / "run", model_name="tiny", run_config={"train": {}}, data_info=DATA,
                dist_info=info, progress=False)
    torch.save({k: v for k, v in model.state_dict().items()}, Path(out) / f"rank{rank}.pt")
    if rank == 0:
        torch.save({"frames": [r["frames"] for r in res.history], "steps": res.global_step}, Path(out) / "meta.pt")
    cleanup(info)


def test_two_process_distributed_run_ends_with_identical_weights(tmp_path):
    import torch.multiprocessing as mp

    # the port is found free and then bound by the workers: another process can take it in
    # between, so a rendezvous failure (and only that) gets one retry on a fresh port
    for attempt in range(2):
        try:
            mp.spawn(_ddp_worker, args=(2, _free_port(), str(tmp_path / f"try{attempt}")), nprocs=2, join=True)
            break
        except Exception as err:
            text = str(err).lower()
            if attempt == 1 or not any(w in text for w in ("address already in use", "connection", "timed out",
                                                             "gloo", "store")):
                raise
    tmp_path = tmp_path / f"try{attempt}"
    w0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    w1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert all(torch.equal(w0[k], w1[k]) for k in w0)
    meta = torch.load(tmp_path / "meta.pt", weights_only=True)
    assert meta["frames"] == [8, 8] and meta["steps"] == 4  # 8 frames split over 2 ranks, 2 per batch
    ckpt = load_checkpoint(CheckpointManager(tmp_path / "run" / "checkpoints").latest())
    assert all(torch.equal(ckpt["model"][k], w0[k]) for k in w0) and len(ckpt["rng"]) == 2


def _cleanup_worker(rank: int, world: int, port: int, out: str) -> None:
    import time as _time
    from pathlib import Path

    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    info = init_distributed("cpu")
    if rank == 1:  # a peer that fails elsewhere and never reaches its cleanup (it stays alive a while)
        _time.sleep(3.0)
        os._exit(0)
    t0 = _time.perf_counter()
    cleanup(info, wait_for_peers=False)  # the error path: must not wait for the peer
    Path(out).write_text(f"{_time.perf_counter() - t0:.3f}")


def test_cleanup_on_an_error_path_does_not_wait_for_a_peer_that_never_comes(tmp_path):
    import torch.multiprocessing as mp

    mp.spawn(_cleanup_worker, args=(2, _free_port(), str(tmp_path / "t")), nprocs=2, join=True)
    assert float((tmp_path / "t").read_text()) < 2.0  # a barrier would have waited the peer's 3 s (or forever)


def _second_smoke_run(tmp_path, name: str, *overrides: str):
    """SECOND at the smoke preset trained on the 8 test frames (no augmentation, seed 0) in tmp_path/name with
    the config `overrides`; returns (model, TrainResult, training set)."""
    import models
    from detbench.train.run_config import load_run_config
    from tests.helpers import FRAMES

    off = AugmentConfig.from_dict({k: {"enabled": False} for k in (
        "random_world_flip", "random_world_rotation", "random_world_scaling", "gt_sampling")})
    run_cfg = load_run_config("second", "smoke", overrides=[
        "train.batch_size=2", "train.workers=0", "train.tensorboard=false", "train.bev_image=false", *overrides])
    run_cfg["model"] = models.prepare_model_config("second", run_cfg["model"],
                                                   np.concatenate([f.boxes for f in FRAMES]))
    seed_everything(0)
    model = models.build_model("second", run_cfg["model"])
    ts = TrainingSet(FRAMES, run_cfg["model"]["point_cloud_range"], augment=off, seed=0)
    res = train(model, ts, TrainConfig.from_dict(run_cfg["train"]), tmp_path / name, model_name="second",
                run_config=run_cfg, data_info=DATA, progress=False)
    return model, res, ts


def test_channels_last_training_trains_the_same_model_and_its_checkpoint_loads_contiguous(tmp_path):
    """train.channels_last holds the 2D convolution weights in NHWC while training (SECOND at the smoke preset):
    the losses are the contiguous run's up to float32 summation order, and the checkpoint rebuilds the
    ordinary (contiguous) model, which predicts what the trained NHWC model predicts."""
    import models

    trained, losses = {}, {}
    for nhwc in (False, True):
        model, res, ts = _second_smoke_run(tmp_path, f"nhwc{nhwc}", "train.epochs=2",
                                           f"train.channels_last={str(nhwc).lower()}")
        trained[nhwc], losses[nhwc] = (model, res), [r["losses"]["loss"] for r in res.history]
    convs = [m for m in trained[True][0].modules() if isinstance(m, nn.Conv2d)]
    assert convs and all(m.weight.is_contiguous(memory_format=torch.channels_last) for m in convs)
    assert not any(m.weight.is_contiguous(memory_format=torch.channels_last) and not m.weight.is_contiguous()
                   for m in trained[False][0].modules() if isinstance(m, nn.Conv2d))
    assert losses[True] == pytest.approx(losses[False], rel=1e-3)
    rebuilt, _ = models.load_from_checkpoint(trained[True][1].last_checkpoint)
    assert all(m.weight.is_contiguous() for m in rebuilt.modules() if isinstance(m, nn.Conv2d))
    batch = collate([ts.get(i, 0, augment=False) for i in range(2)])
    with torch.no_grad():
        a = trained[True][0].eval()(batch)
        b = rebuilt(batch)
    assert len(a) == len(b) == 3  # the anchor head's class logits, box residuals and direction logits
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-4)


def test_batchnorm_statistics_are_recomputed_where_a_checkpoint_is_used_and_the_model_is_the_same(tmp_path):
    """A checkpoint only a resume reads keeps the running BatchNorm statistics; the last one (and every one when
    train.keep_checkpoints is 0) has them recomputed. The weights, the last checkpoint and the losses are the
    same bit for bit either way."""
    from detbench.train.checkpoint import load_checkpoint

    runs = {keep: _second_smoke_run(tmp_path, f"keep{keep}", "train.epochs=3", f"train.keep_checkpoints={keep}")
            for keep in (3, 0)}
    ckpts = {keep: [load_checkpoint(p) for p in CheckpointManager(tmp_path / f"keep{keep}" / "checkpoints").list()]
             for keep in runs}
    assert [len(c) for c in ckpts.values()] == [3, 3]
    assert [r["losses"] for r in runs[3][1].history] == [r["losses"] for r in runs[0][1].history]
    assert same_weights(runs[3][0], runs[0][0])
    bn = [k for k in ckpts[0][0]["model"] if k.endswith("running_mean")]
    assert bn
    for epoch, (a, b) in enumerate(zip(ckpts[3], ckpts[0])):
        stats_equal = all(torch.equal(a["model"][k], b["model"][k]) for k in bn)
        assert stats_equal == (epoch == 2), epoch  # epochs 1 and 2: running against recomputed; the last: both
        assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"] if "running" not in k
                   and "num_batches" not in k)
