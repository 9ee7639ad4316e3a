"""detbench.ops.backend: DETBENCH_OPS=torch sends CPU tensors down the torch path (the GPU's). The torch paths
with a loop, `nms_bev` and `farthest_point_sample`, against the numba kernels: the same indices in the same
order on random and adversarial inputs (score ties, IoU exactly at the threshold, duplicates, chains of boxes
each suppressing the next, block boundaries), and their cost in tensor operations, each a kernel launch on a
GPU."""
from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import detbench.ops.nms as nms_module
from detbench.ops import farthest_point_sample, nms_bev
from detbench.ops.backend import OPS_ENV, forced_backend, ops_mode, use_torch

THRESHOLDS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.85, 0.99)


def both_paths(boxes: np.ndarray, scores: np.ndarray, thr: float, max_keep=None) -> tuple[list, list]:
    """(numba kernel's kept indices, torch path's) for float64 boxes and scores."""
    want = nms_bev(boxes, scores, thr, max_keep).tolist()
    with forced_backend("torch"):
        got = nms_bev(torch.from_numpy(boxes), torch.from_numpy(scores), thr, max_keep)
    assert got.dtype == torch.int64
    return want, got.tolist()


def cloud(rng, n: int, spread: float = 20.0) -> np.ndarray:
    """n boxes of random size and heading in a square of side 2 * spread (metres)."""
    return np.c_[rng.uniform(-spread, spread, (n, 2)), rng.uniform(0.5, 1.5, n), rng.uniform(1.0, 6.0, (n, 3)),
                 rng.uniform(-math.pi, math.pi, n)]


def proposals(rng, n: int, cars: int = 40) -> np.ndarray:
    """A trained first stage's proposals: n car boxes crowded round `cars` vehicles on five lanes."""
    c = np.c_[rng.uniform(5, 150, cars), rng.choice([-7.0, -3.5, 0.0, 3.5, 7.0], cars), np.full(cars, 0.8),
              rng.uniform(4, 5, cars), rng.uniform(1.7, 2, cars), rng.uniform(1.4, 1.8, cars), rng.normal(0, 0.1, cars)]
    return c[rng.integers(0, cars, n)] + rng.normal(0, 1, (n, 7)) * [0.5, 0.3, 0.1, 0.2, 0.1, 0.1, 0.1]


def anchors(rng, n: int) -> np.ndarray:
    """An untrained first stage's candidates: car boxes on the anchor cells of the study's region."""
    x = np.round(rng.uniform(0, 153.6, n) / 0.8) * 0.8 + rng.normal(0, 0.1, n)
    y = np.round(rng.uniform(-16, 16, n) / 0.8) * 0.8 + rng.normal(0, 0.1, n)
    return np.c_[x, y, rng.normal(0.8, 0.1, n), rng.normal(4.5, 0.3, n), rng.normal(1.9, 0.1, n),
                 rng.normal(1.6, 0.1, n), rng.choice([0.0, math.pi / 2], n) + rng.normal(0, 0.05, n)]


def test_the_switch_sends_cpu_tensors_down_the_torch_path(monkeypatch):
    monkeypatch.delenv(OPS_ENV, raising=False)
    assert ops_mode() == "auto" and not use_torch(torch.device("cpu")) and use_torch(torch.device("meta"))
    monkeypatch.setenv(OPS_ENV, "torch")
    assert use_torch(torch.device("cpu"))
    monkeypatch.setenv(OPS_ENV, "cuda")
    with pytest.raises(ValueError, match=f"{OPS_ENV}='cuda'.*{OPS_ENV}=torch"):
        use_torch(torch.device("cpu"))


@pytest.mark.parametrize("block", [13, 1024])
def test_random_inputs_keep_the_numba_kernels_boxes(block, monkeypatch):
    """Blocks of 13 put many block boundaries into 600 boxes; scores rounded to 2 decimals tie often."""
    monkeypatch.setattr(nms_module, "_NMS_BLOCK", block)
    rng = np.random.default_rng(11)
    for boxes in (cloud(rng, 600, 12.0), cloud(rng, 600, 40.0), proposals(rng, 600, cars=8)):
        scores = np.round(rng.uniform(0, 1, len(boxes)), 2)
        for thr in THRESHOLDS:
            for max_keep in (None, 1, 37):
                want, got = both_paths(boxes, scores, thr, max_keep)
                assert got == want, (thr, max_keep)
        assert 5 < len(both_paths(boxes, scores, 0.3)[0]) < len(boxes)


def test_nine_thousand_proposals_to_512_as_the_two_stage_training_budget():
    rng = np.random.default_rng(5)
    for boxes in (proposals(rng, 9000), anchors(rng, 9000)):
        scores = rng.uniform(0, 1, 9000).astype(np.float32).astype(np.float64)
        for thr in (0.7, 0.8, 0.85):
            want, got = both_paths(boxes, scores, thr, 512)
            assert got == want and len(want) == 512, thr
        b32, s32 = torch.from_numpy(boxes).float(), torch.from_numpy(scores).float()  # the models' float32
        with forced_backend("torch"):
            assert nms_bev(b32, s32, 0.8, 512).tolist() == nms_bev(b32.numpy(), s32.numpy(), 0.8, 512).tolist()


def _box(x, y=0.0, dx=4.0, dy=2.0, heading=0.0):
    return [x, y, 0.8, dx, dy, 1.5, heading]


@pytest.mark.parametrize("block", [2, 3, 1024])
def test_adversarial_inputs(block, monkeypatch):
    monkeypatch.setattr(nms_module, "_NMS_BLOCK", block)
    # IoU exactly at the threshold: a 4 x 2 box and its copy shifted by half its length (IoU 4 / 12), and a
    # box holding another of half its area (IoU 1 / 2); suppression needs IoU strictly above the threshold
    for pair, iou in (([_box(0.0), _box(2.0)], 4.0 / 12.0), ([_box(0.0), _box(1.0, dx=2.0)], 0.5)):
        b, s = np.array(pair), np.array([0.9, 0.8])
        for thr, kept in ((iou, [0, 1]), (float(np.nextafter(iou, 0.0)), [0])):
            assert both_paths(b, s, thr) == (kept, kept), (iou, thr)
    # duplicates with tied scores: the first of the best survives; at threshold 1 every box does
    dup = np.array([_box(30.0, heading=math.pi)] * 9)
    dup[::2, 6] = -math.pi  # the same box written with the other end of the heading range
    s = np.array([0.5, 0.9, 0.9, 0.1, 0.9, 0.5, 0.5, 0.9, 0.2])
    assert both_paths(dup, s, 0.5) == ([1], [1])
    everyone = sorted(range(9), key=lambda k: (-s[k], k))
    assert both_paths(dup, s, 1.0) == (everyone, everyone)
    # a chain: each box overlaps its neighbours (IoU 0.6) but not the next but one (IoU 1/3), so each decision
    # waits for the one before it; in score order the kept boxes alternate, in other orders they do not
    chain = np.array([_box(float(x)) for x in range(60)])
    rng = np.random.default_rng(3)
    for s in (np.linspace(1, 0.1, 60), np.linspace(0.1, 1, 60), rng.permutation(60) / 60.0, np.full(60, 0.5)):
        want, got = both_paths(chain, s, 0.5)
        assert got == want
    assert both_paths(chain, np.linspace(1, 0.1, 60), 0.5)[0] == list(range(0, 60, 2))
    # touching and zero-size boxes suppress nothing, even at threshold 0
    odd = np.array([_box(0.0), _box(4.0), _box(0.0, 2.0), _box(0.0, dx=0.0, dy=0.0), _box(1.0, dx=0.0)])
    assert both_paths(odd, np.array([0.9, 0.8, 0.7, 0.95, 0.6]), 0.0) == ([3, 0, 1, 2, 4], [3, 0, 1, 2, 4])
    # empty input and max_keep 0
    assert both_paths(np.zeros((0, 7)), np.zeros(0), 0.5) == ([], [])
    assert both_paths(chain, np.ones(60), 0.5, 0) == ([], [])


class _CountOps(TorchDispatchMode):
    """Counts the tensor operations that compute (views excluded) and the host syncs among them."""

    SYNCS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::item")

    def __init__(self):
        super().__init__()
        self.ops = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not func.is_view:
            self.ops[func.name()] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def syncs(self) -> int:
        return sum(self.ops[s] for s in self.SYNCS)


def test_nms_of_9000_to_512_takes_a_few_hundred_tensor_operations():
    """Each operation is a kernel launch on a GPU: the greedy sweep runs on whole blocks of boxes, not one
    kept box at a time (which took about 280 operations and a host sync per kept box)."""
    rng = np.random.default_rng(5)
    for boxes in (proposals(rng, 9000), anchors(rng, 9000)):
        b, s = torch.from_numpy(boxes).float(), torch.rand(9000, generator=torch.Generator().manual_seed(0))
        with _CountOps() as count:
            kept = nms_module._nms_torch(b, s, 0.8, 512)
        assert kept.numel() == 512
        assert count.total < 1500 and count.syncs < 60, (count.total, count.syncs, count.ops.most_common(8))


def test_fps_takes_seven_tensor_operations_per_sample_on_all_frames_at_once():
    rng = np.random.default_rng(2)
    xyz = torch.from_numpy(rng.uniform([0, -15, -1], [150, 15, 3], (3000, 3)))
    threads = torch.get_num_threads()
    with forced_backend("torch"), _CountOps() as count:
        got = farthest_point_sample(xyz, [400, 300], [2000, 1000])
    assert torch.get_num_threads() == threads  # the steps run on one CPU thread, then the count is put back
    assert torch.equal(got, farthest_point_sample(xyz, [400, 300], [2000, 1000]))  # the numba kernel's samples
    assert count.syncs == 0, count.ops
    assert count.total <= 7 * 399 + 40, (count.total, count.ops.most_common(8))
