"""Prediction files: what a model predicts reaches the evaluator unchanged whether it is handed over in memory
(tools/eval.py --ckpt) or written to one file per frame and read back (--pred)."""
from __future__ import annotations

import numpy as np
import torch

from detbench.eval import evaluate_predictions, read_prediction_dir
from detbench.eval.run import write_predictions
from detbench.train.inference import predict_frames
from tests.helpers import FRAMES, PC_RANGE, TinyDetector


class SizedTiny(TinyDetector):
    """The tiny detector with sizes made positive, as a real head's decoding makes them."""

    def predict(self, out, batch):
        dets = super().predict(out, batch)
        return [d._replace(boxes=torch.cat([d.boxes[:, :3], d.boxes[:, 3:6].abs(), d.boxes[:, 6:]], 1)) for d in dets]


def test_a_models_predictions_survive_their_files_bit_for_bit(tmp_path):
    torch.manual_seed(0)
    model = SizedTiny()
    preds = predict_frames(model, FRAMES, PC_RANGE, progress=False)
    assert sorted(preds) == sorted(f.frame_id for f in FRAMES)
    for boxes, scores in (preds[fid][:2] for fid in preds):  # the model's float32 figures
        assert boxes.dtype == np.float32 and boxes.shape == (1, 7) and scores.dtype == np.float32

    write_predictions(preds, tmp_path)
    read, skipped = read_prediction_dir(tmp_path, [f.frame_id for f in FRAMES])
    assert skipped == [] and sorted(read) == sorted(preds)
    for fid, p in preds.items():
        np.testing.assert_array_equal(read[fid][0], p[0].astype(np.float64))
        np.testing.assert_array_equal(read[fid][1], p[1].astype(np.float64))

    in_memory = evaluate_predictions(FRAMES, preds, score_threshold=0.0, progress=False)
    from_files = evaluate_predictions(FRAMES, read, score_threshold=0.0, progress=False)
    assert in_memory == from_files
    assert from_files["results"]["large"]["all"]["fp"] + from_files["results"]["large"]["all"]["tp"] > 0
