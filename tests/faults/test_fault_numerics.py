"""Numerical faults: huge angles, NaN boxes, impossible heights."""
import math

import numpy as np
import pytest
import torch

WRAPPED_1E30 = 3.1322610492283266  # 1e30 rad wrapped into [-pi, pi) (exact, 80-digit arithmetic)


@pytest.mark.parametrize("as_type", [float, lambda v: np.array([v]), lambda v: torch.tensor([v], dtype=torch.float64)])
def test_huge_heading_wraps_exactly(as_type):
    """A heading of +-1e30 rad wraps into [-pi, pi) exactly, given as a float, a numpy array or a torch
    tensor."""
    from detbench.ops import normalize_heading

    for x, want in ((1e30, WRAPPED_1E30), (-1e30, -WRAPPED_1E30)):
        got = np.asarray(normalize_heading(as_type(x))).reshape(-1)[0]
        assert got == pytest.approx(want, abs=1e-12)


def test_label_headings_wrap_exactly():
    """A label's heading of 1e30 rad is read wrapped into [-pi, pi), exactly."""
    from detbench.data.readers import parse_labels

    boxes, _ = parse_labels("10 0 0.8 4 2 1.6 1e30 car\n")
    assert boxes[0, 6] == pytest.approx(WRAPPED_1E30, abs=1e-6)


def test_nan_box_iou_is_an_error_on_every_cpu_path():
    """On the CPU a NaN box given to the IoU is a ValueError naming the argument and the row, for numpy and
    torch inputs, with or without gradients, never an IoU of 0."""
    from detbench.ops import boxes_iou3d, boxes_iou_bev_aligned

    boxes = np.array([[0, 0, 0.8, 4, 2, 1.6, 0], [np.nan, 0, 0.8, 4, 2, 1.6, 0]])
    for a in (boxes, torch.from_numpy(boxes), torch.from_numpy(boxes).float().requires_grad_()):
        with pytest.raises(ValueError, match=r"`a` row 1 contains NaN or inf"):
            boxes_iou3d(a, boxes[:1])
    with pytest.raises(ValueError, match=r"`b` row 1 contains NaN"):
        boxes_iou_bev_aligned(torch.from_numpy(boxes[[0, 0]]), torch.from_numpy(boxes))


def test_device_path_gives_nan_never_zero():
    """Off the CPU no host sync is spent on checking: a NaN box's IoUs are NaN (the rule, tested on CPU)."""
    from detbench.ops.iou import _nan_where_nonfinite

    a = torch.tensor([[0, 0, 0.8, 4, 2, 1.6, 0], [math.nan, 0, 0.8, 4, 2, 1.6, 0]])
    out = _nan_where_nonfinite(torch.zeros(2, 2), a, a, pairwise=True)
    assert out[0, 0] == 0 and torch.isnan(out[1]).all() and torch.isnan(out[:, 1]).all()


def test_impossible_height_is_a_user_error(tool, tmp_path):
    """A mounting height of 0 is refused in one line naming --heights, without a traceback and with nothing
    written."""
    code, err = tool("analyze", "--simulate", 2, "--heights", 0, "--out", tmp_path, "--no-figures", "--no-progress")
    assert code == 2 and "--heights 0: a mounting height is a positive number of metres" in err
    assert "Traceback" not in err and not list(tmp_path.iterdir())
