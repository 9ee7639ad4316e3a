"""Prediction files (detbench.eval.prediction_files): parsing, file errors, and what a model predicts reaching
the evaluator unchanged whether it is handed over in memory (tools/eval.py --ckpt) or written to one file per
frame and read back (--pred)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from detbench.data.detections import Detections
from detbench.eval import evaluate_predictions, parse_prediction_file, read_prediction_dir, write_predictions
from detbench.eval.prediction_files import format_prediction_lines
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
    assert all(isinstance(p, Detections) and p.labels.dtype == np.int64 for p in preds.values())

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


def test_parse_prediction_file(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("1 2 0.8 4 2 1.6 0.1 0.9 car\n\n  -3.5 0 1 4.5 1.9 1.5 -3.1 0.25\n")
    boxes, scores, labels = parse_prediction_file(p)
    np.testing.assert_allclose(boxes, [[1, 2, 0.8, 4, 2, 1.6, 0.1], [-3.5, 0, 1, 4.5, 1.9, 1.5, -3.1]])
    np.testing.assert_allclose(scores, [0.9, 0.25])
    assert labels.tolist() == [0, 0] and labels.dtype == np.int64  # a file's class names are not read
    (tmp_path / "empty.txt").write_text("")
    boxes, scores, labels = parse_prediction_file(tmp_path / "empty.txt")
    assert boxes.shape == (0, 7) and scores.shape == (0,) and labels.shape == (0,)


def test_format_and_parse_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    boxes, scores = rng.normal(size=(5, 7)), rng.random(5)
    boxes[:, 3:6] = np.abs(boxes[:, 3:6])
    (tmp_path / "x.txt").write_text(format_prediction_lines(boxes, scores, "car"))
    b, s, _ = parse_prediction_file(tmp_path / "x.txt")
    np.testing.assert_array_equal(b, boxes)
    np.testing.assert_array_equal(s, scores)


@pytest.mark.parametrize("line, message", [
    ("1 2 3 4 5 6 7", "expected 8 numbers"),
    ("1 2 3 4 5 6 7 0.5 car extra", "expected 8 numbers"),
    ("1 2 3 4 5 6 x 0.5", "not a number"),
    ("1 2 3 4 5 6 7 nan", "non-finite"),
    ("1 2 3 -4 5 6 7 0.5", "negative box size"),
])
def test_malformed_line_names_file_and_line(tmp_path, line, message):
    p = tmp_path / "0001.txt"
    p.write_text("1 2 0.8 4 2 1.6 0 0.9\n" + line + "\n")
    with pytest.raises(ValueError, match=message) as e:
        parse_prediction_file(p)
    assert f"{p}:2:" in str(e.value)


def test_read_prediction_dir(tmp_path):
    d = tmp_path / "pred"
    d.mkdir()
    (d / "f1.txt").write_text("1 2 0.8 4 2 1.6 0 0.9\n")
    (d / "f9.txt").write_text("1 2 0.8 4 2 1.6 0 0.9\n")
    (d / ".hidden").write_text("ignored")
    preds, skipped = read_prediction_dir(d, ["f1", "f2"], other_ids=["f9"])
    assert list(preds) == ["f1"] and skipped == ["f9"]
    with pytest.raises(ValueError, match=r"f9\.txt: unknown frame id 'f9'"):
        read_prediction_dir(d, ["f1", "f2"])
    (d / "notes.md").write_text("x")
    with pytest.raises(ValueError, match=r"notes\.md: unexpected entry"):
        read_prediction_dir(d, ["f1", "f2"], other_ids=["f9"])
    with pytest.raises(FileNotFoundError, match="prediction folder not found"):
        read_prediction_dir(tmp_path / "nope", ["f1"])
