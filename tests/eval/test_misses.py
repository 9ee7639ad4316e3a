"""Where recall goes (detbench.eval.misses): each LiDAR-detected vehicle's best 3D IoU and box error."""
from types import SimpleNamespace

import numpy as np
import pytest

from detbench.eval.misses import misses, misses_markdown


def _frame(fid, boxes):
    """A frame whose every box holds 20 points at its centre's height (LiDAR-detected)."""
    pts = np.concatenate([np.column_stack([np.full(20, b[0]), np.full(20, b[1]), np.full(20, b[2]),
                                           np.full(20, 0.5)]) for b in boxes]).astype(np.float32)
    return SimpleNamespace(frame_id=fid, points=pts, boxes=np.asarray(boxes, np.float32))


def test_found_loose_and_unseen_vehicles_fall_in_their_bands_with_their_errors():
    car = [20.0, 0.0, 0.8, 4.5, 1.8, 1.5, 0.0]
    truck = [30.0, 3.0, 1.6, 9.0, 2.5, 3.2, 0.0]
    far = [80.0, 0.0, 0.8, 4.5, 1.8, 1.5, 0.0]  # in moderate, not in small
    frames = [_frame("a", [car, truck, far]), _frame("b", [car])]
    short_truck = [28.0, 3.0, 1.6, 5.0, 2.5, 3.2, 0.0]  # the rear right, 4 m too short: 3D IoU 5/9
    preds = {"a": (np.array([car, short_truck, far]), np.array([0.9, 0.8, 0.9])),
             "b": (np.array([car]), np.array([0.05]))}  # below the score threshold: frame b's car is unseen
    d = misses(frames, preds, "small").to_dict()
    assert d["vehicles"] == 3 and d["recall"] == pytest.approx(1 / 3, abs=1e-4)
    bands = {(b["from"], b["to"]): b["share"] for b in d["best_iou3d_bands"]}
    assert bands[(0.0, 0.01)] == pytest.approx(1 / 3, abs=1e-4)  # never seen (scored below 0.1)
    assert bands[(0.5, 0.6)] == pytest.approx(1 / 3, abs=1e-4)  # boxed 4 m short
    assert bands[(0.7, 1.01)] == pytest.approx(1 / 3, abs=1e-4)
    assert d["near_misses"]["median_signed_error_m"]["length"] == pytest.approx(-4.0)
    assert d["near_misses"]["median_signed_error_m"]["x"] == pytest.approx(-2.0)
    long_band = next(b for b in d["by_length"] if b["from"] == 7.0)
    assert long_band["vehicles"] == 1 and long_band["recall"] == 0.0
    md = misses_markdown(d, "test")
    assert "| [0.50, 0.60) | 0.333 |" in md and "length -4.00" in md and "| 7-99 | 1 | 0.000 |" in md
    assert misses(frames, preds, "moderate").to_dict()["vehicles"] == 4  # the far car joins


def test_no_vehicle_in_the_range_gives_empty_figures():
    d = misses([_frame("a", [[80.0, 0.0, 0.8, 4.5, 1.8, 1.5, 0.0]])], {}, "small").to_dict()
    assert d["vehicles"] == 0 and d["recall"] is None and d["by_length"] == []
    assert "0 LiDAR-detected vehicles" in misses_markdown(d)
