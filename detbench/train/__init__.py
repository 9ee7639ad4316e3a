"""Training infrastructure shared by every detector: data pipeline hand-offs, loop, checkpoints, DDP.

The detector contract (the loop, inference and the benchmark use nothing else) is the
`Detector` protocol in detbench/train/detector.py: forward(batch), loss(outputs, batch),
predict(outputs, batch), STAGES and prepare_config(model_cfg, train_boxes); the hand-offs
`Sample`, `Batch`, `Detections` are in detbench/data/batch.py (`Detections` defined in detections.py).

Typical use (tools/train.py; `models` is the detector registry above this package)
-----------------------------------------------------------------------------------
    info = init_distributed(args.device)
    run_config = load_run_config("second", "smoke")                   # detbench.train.run_config
    cfg = TrainConfig.from_dict(run_config["train"])
    with main_process_first(info):
        train_set = TrainingSet.from_dataset(root, height, run_config["model"]["point_cloud_range"],
                                             augment=AugmentConfig.from_dict(run_config["augment"]),
                                             seed=cfg.seed)
    run_config["model"] = models.prepare_model_config("second", run_config["model"], train_boxes)
    model = models.build_model("second", run_config["model"])
    result = train(model, train_set, cfg, out_dir, model_name="second", run_config=run_config,
                   data_info=training_data_info(root, height, train_set), dist_info=info,
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
from detbench.train.detector import Detector
from detbench.train.distributed import (
    DistInfo, barrier, cleanup, init_distributed, main_process_first, reduce_mean, wrap_model,
)
from detbench.train.logger import TrainLogger, bev_figure, format_epoch_summary
from detbench.train.loop import TrainResult, train
from detbench.train.optim import build_optimizer, build_scheduler
from detbench.train.rng import capture_rng_state, restore_rng_state, sample_rng, seed_everything, worker_init_fn
from detbench.train.train_config import RESUME_SAFE_KEYS, TRAIN_DEFAULTS, TrainConfig

__all__ = [
    "Batch", "Detections", "Sample", "collate", "AugmentConfig", "AUGMENT_DEFAULTS",
    "TrainingSet", "default_database_dir", "Detector",
    "TrainConfig", "TRAIN_DEFAULTS", "RESUME_SAFE_KEYS", "TrainResult", "train",
    "CheckpointError", "CheckpointManager", "TrainState", "save_checkpoint", "load_checkpoint",
    "load_model_weights", "restore_training", "config_diff", "unwrap_model",
    "DistInfo", "init_distributed", "wrap_model", "reduce_mean", "barrier", "main_process_first", "cleanup",
    "TrainLogger", "bev_figure", "format_epoch_summary", "build_optimizer", "build_scheduler",
    "seed_everything", "sample_rng", "worker_init_fn", "capture_rng_state", "restore_rng_state",
]
