"""Training infrastructure shared by every detector: data pipeline hand-offs, loop, checkpoints, DDP.

The contract between detectors and this package (the loop uses nothing else)
---------------------------------------------------------------------------
Data in (detbench.data.batch):

    Sample(points (N, 4) float32 x y z intensity, gt_boxes (M, 7) float32, frame_id: str)
    collate(list[Sample]) -> Batch
    Batch.points    (P, 5) float32 [batch_index, x, y, z, intensity], frames concatenated in order
    Batch.gt_boxes  (B, Mmax, 7) float32 x y z dx dy dz heading, zero rows as padding
    Batch.gt_mask   (B, Mmax) bool, True for real boxes (Mmax may be 0)
    Batch.frame_ids list[str]; Batch.batch_size int; Batch.to(device); Batch.boxes_of(i) -> (Mi, 7)

A detector is an `nn.Module` with three methods:

    forward(batch: Batch) -> outputs                      any typed NamedTuple of tensors
    loss(outputs, batch: Batch) -> (total: Tensor[], parts: dict[str, float])
    predict(outputs, batch: Batch) -> list[Detections]    one per frame, in batch order

    Detections(boxes (K, 7) float32, scores (K,) float32 in [0, 1], labels (K,) int64)

Units: metres and radians in the ego ground frame (x forward, y left, z up; heading
counter-clockwise from +x in [-pi, pi)). `loss` must be finite for empty frames (no points
or no boxes), and `parts` must have the same keys at every step (they are averaged over
ranks by key). The ground truth in a Batch is the LiDAR-detected vehicles (>= 1 point inside
the box with its bottom raised 0.05 m), cropped to the model's point-cloud range.

Typical use (tools/train.py)
----------------------------
    info = init_distributed(args.device)
    cfg = TrainConfig.from_dict(run_config["train"])
    seed_everything(cfg.seed)
    model = build_model(run_config)                                    # the lead's registry
    with main_process_first(info):
        train_set = TrainingSet.from_dataset(root, height, point_cloud_range,
                                             augment=AugmentConfig.from_dict(run_config["augment"]),
                                             seed=cfg.seed)
    result = train(model, train_set, cfg, out_dir, model_name="second", run_config=run_config,
                   data_info={"source": str(root), "height": height}, dist_info=info,
                   resume=args.resume, eval_fn=my_eval)
    cleanup(info)

DataLoader workers are spawned (numba's OpenMP kernels and CUDA are not fork-safe), so a
script that trains with `workers > 0` keeps its top level under `if __name__ == "__main__":`.
Ctrl-C or SIGTERM: the loop finishes the current step, writes a checkpoint and returns
`TrainResult(interrupted=True)`; `train(..., resume=True)` continues bit-for-bit on CPU.
"""
from detbench.data.augment import AUGMENT_DEFAULTS, AugmentConfig
from detbench.data.batch import Batch, Detections, Sample, collate
from detbench.train.checkpoint import (
    CheckpointError, CheckpointManager, TrainState, config_diff, load_checkpoint, load_model_weights,
    restore_training, save_checkpoint, unwrap_model,
)
from detbench.train.dataset import TrainingSet, default_database_dir
from detbench.train.distributed import (
    DistInfo, barrier, cleanup, init_distributed, main_process_first, reduce_mean, wrap_model,
)
from detbench.train.logger import TrainLogger, bev_figure, format_epoch_summary
from detbench.train.loop import RESUME_SAFE_KEYS, TRAIN_DEFAULTS, TrainConfig, TrainResult, train
from detbench.train.optim import build_optimizer, build_scheduler
from detbench.train.seed import capture_rng_state, restore_rng_state, sample_rng, seed_everything, worker_init_fn

__all__ = [
    "Batch", "Detections", "Sample", "collate", "AugmentConfig", "AUGMENT_DEFAULTS",
    "TrainingSet", "default_database_dir",
    "TrainConfig", "TRAIN_DEFAULTS", "RESUME_SAFE_KEYS", "TrainResult", "train",
    "CheckpointError", "CheckpointManager", "TrainState", "save_checkpoint", "load_checkpoint",
    "load_model_weights", "restore_training", "config_diff", "unwrap_model",
    "DistInfo", "init_distributed", "wrap_model", "reduce_mean", "barrier", "main_process_first", "cleanup",
    "TrainLogger", "bev_figure", "format_epoch_summary", "build_optimizer", "build_scheduler",
    "seed_everything", "sample_rng", "worker_init_fn", "capture_rng_state", "restore_rng_state",
]
