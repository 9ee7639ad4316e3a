"""detbench.train.demo: choosing the frame, the boxes recorded and drawn."""
import numpy as np
import pytest

from detbench.data import DatasetWriter, Frame, Height3Dataset, Sensor
from detbench.train.demo import DemoFrame, demo_figure, demo_record, select_frame, write_demo
from detbench.utils.cli import UserError


def car(x, y=0.0):
    return [x, y, 0.8, 4.0, 2.0, 1.6, 0.0]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """3 scenes x 2 frames at 1.8 m, one vehicle each."""
    root = tmp_path_factory.mktemp("demo")
    with DatasetWriter(root, [1.8], {"kind": "test fixture"}) as w:
        for s in range(3):
            for i in range(2):
                w.add([Frame(f"{s:04d}_{i:03d}", f"{s:04d}", np.zeros((1, 4), np.float32),
                             np.array([car(10)], np.float32), np.array(["car"]), np.arange(1), np.zeros(1, np.int64),
                             Sensor(1.8))])
    return Height3Dataset(root, 1.8, "all")


def test_a_frame_is_named_by_id_or_index(dataset):
    ids = dataset.frame_ids
    assert select_frame(dataset, ids[3]) == ids[3]
    assert select_frame(dataset, "0") == ids[0] and select_frame(dataset, "-1") == ids[-1]
    for bad in ("6", "-7", "0009_000", "x"):
        with pytest.raises(UserError, match=r"neither a frame id of the all split at 1\.8 m .* index in 0\.\.5"):
            select_frame(dataset, bad)


def demo(scores):
    n = len(scores)
    return DemoFrame(frame_id="0000_000", height=1.8, split="test", model="second", checkpoint="c.pt",
                     stage="refined", points=np.array([[5, 0, 0.2, 0.5], [12, 1, 0.5, 0.5]], np.float32),
                     gt_boxes=np.array([car(10), car(30, 3.5)], np.float32),
                     boxes=np.array([car(10 + 10 * k) for k in range(n)], np.float32).reshape(-1, 7),
                     scores=np.asarray(scores, np.float32), score_threshold=0.3,
                     point_cloud_range=[0.0, -16.0, -1.0, 60.0, 16.0, 3.0])


def test_only_predictions_at_or_above_the_threshold_are_recorded_and_drawn(tmp_path):
    d = demo([0.9, 0.3, 0.1])
    rec = demo_record(d)
    assert [p["score"] for p in rec["predictions"]] == [0.9, 0.3] and rec["predictions_below_threshold"] == 1
    assert rec["predictions"][1]["box"] == pytest.approx(car(20)) and len(rec["ground_truth"]) == 2
    labels = [t.get_text() for t in demo_figure(d).axes[0].get_legend().get_texts()]
    assert labels == ["ground truth (2)", "predictions >= 0.3 (2)"]
    png, js = write_demo(demo([]), tmp_path)
    assert png.name == "0000_000.png" and png.read_bytes()[:4] == b"\x89PNG" and js.name == "0000_000.json"
    assert demo_record(demo([]))["predictions"] == []
