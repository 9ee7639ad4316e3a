"""Builders the tests share: synthetic points and frames, the exact IoU reference, a tiny SECOND
configuration and batch maker, and the tiny test-only detector with its training set.

Tests import them as `from tests.helpers import ...`; no test module imports another. Helpers that only
one test module uses stay in that module."""
from __future__ import annotations

import math
import os
import signal
from fractions import Fraction
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from detbench.data.augment import AugmentConfig
from detbench.data.batch import Batch, Detections
from detbench.data.frame import Frame, Sensor
from detbench.data.gt_database import build_gt_database
from detbench.train import TrainingSet
from models.stages import VoxelGrid

ROOT = Path(__file__).resolve().parents[1]  # the repository root


# ---------------------------------------------------------------- points in a box
def box_points(box, n: int = 300, rng: int | np.random.Generator = 0, *, on_faces: bool = False,
               margin: float = 0.0, intensity: float | None = 0.5) -> np.ndarray:
    """(n, 4) float32 points (x, y, z, intensity) in the rotated box (x, y, z, dx, dy, dz, heading).

    Uniform in the box shrunk by `margin` metres on every side; with `on_faces`, each point is pushed
    onto one of the box's faces (the front/back, left/right or top/bottom pair, picked at random).
    `rng` is a generator or a seed; `intensity` is a constant, or None for uniform [0, 1) draws.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    x, y, z, dx, dy, dz, h = (float(v) for v in box[:7])
    half = np.array([dx, dy, dz]) / 2 - margin
    local = rng.uniform(-1, 1, size=(n, 3)) * half
    if on_faces:
        rows, face = np.arange(n), rng.integers(0, 3, n)
        local[rows, face] = np.sign(local[rows, face]) * half[face]
    c, s = math.cos(h), math.sin(h)
    wx = x + c * local[:, 0] - s * local[:, 1]
    wy = y + s * local[:, 0] + c * local[:, 1]
    value = rng.uniform(0, 1, n) if intensity is None else np.full(n, intensity)
    return np.stack([wx, wy, z + local[:, 2], value], axis=1).astype(np.float32)


# ---------------------------------------------------------------- exact IoU reference
# Box b's rectangle clipped by each edge of box a in world coordinates (Sutherland-Hodgman, general
# half-planes) in exact rational arithmetic: it shares neither the local frame nor the axis-aligned
# clipping of detbench.ops.iou.
def ref_corners(box):
    x, y, _, dx, dy, _, h = (float(v) for v in box[:7])
    c, s = math.cos(h), math.sin(h)
    out = []
    for u, v in ((dx / 2, dy / 2), (-dx / 2, dy / 2), (-dx / 2, -dy / 2), (dx / 2, -dy / 2)):
        out.append((Fraction(x + u * c - v * s), Fraction(y + u * s + v * c)))
    return out


def ref_clip(poly, p, q):
    """Keep the part of `poly` left of the directed line p -> q (exact)."""
    def side(pt):
        return (q[0] - p[0]) * (pt[1] - p[1]) - (q[1] - p[1]) * (pt[0] - p[0])

    out = []
    for i in range(len(poly)):
        s_pt, e_pt = poly[i - 1], poly[i]
        fs, fe = side(s_pt), side(e_pt)
        if fe >= 0:
            if fs < 0:
                t = fs / (fs - fe)
                out.append((s_pt[0] + t * (e_pt[0] - s_pt[0]), s_pt[1] + t * (e_pt[1] - s_pt[1])))
            out.append(e_pt)
        elif fs >= 0:
            t = fs / (fs - fe)
            out.append((s_pt[0] + t * (e_pt[0] - s_pt[0]), s_pt[1] + t * (e_pt[1] - s_pt[1])))
    return out


def ref_area(poly):
    if len(poly) < 3:
        return Fraction(0)
    acc = Fraction(0)
    for i in range(len(poly)):
        x0, y0 = poly[i - 1]
        x1, y1 = poly[i]
        acc += x0 * y1 - x1 * y0
    return abs(acc) / 2


def ref_overlap_bev(a, b):
    ca, cb = ref_corners(a), ref_corners(b)
    poly = cb
    for i in range(4):
        poly = ref_clip(poly, ca[i], ca[(i + 1) % 4])
        if not poly:
            return 0.0
    return float(ref_area(poly))


def ref_iou(a, b, mode="3d"):
    inter = ref_overlap_bev(a, b)
    area_a, area_b = float(a[3]) * float(a[4]), float(b[3]) * float(b[4])
    if mode == "bev":
        union = area_a + area_b - inter
        return inter / union if union > 0 else 0.0
    top = min(float(a[2]) + float(a[5]) / 2, float(b[2]) + float(b[5]) / 2)
    bot = max(float(a[2]) - float(a[5]) / 2, float(b[2]) - float(b[5]) / 2)
    inter3 = inter * max(0.0, top - bot)
    union3 = area_a * float(a[5]) + area_b * float(b[5]) - inter3
    return inter3 / union3 if union3 > 0 else 0.0


# ---------------------------------------------------------------- a tiny SECOND
GRID = VoxelGrid((0.0, -3.2, -0.6, 12.8, 3.2, 4.2), (0.2, 0.2, 0.15))
TINY = {
    "name": "second", "point_cloud_range": list(GRID.point_cloud_range), "voxel_size": list(GRID.voxel_size),
    "vfe": {"xy": "offset"}, "backbone3d": {"channels": [4, 8, 8, 8], "blocks": [1, 1, 1, 1], "out_channels": 8},
    "backbone2d": {"layer_nums": [1, 1], "layer_strides": [1, 2], "num_filters": [8, 16],
                   "upsample_strides": [1, 2], "num_upsample_filters": [8, 8]},
    "head": {"anchor_sizes": [[4.5, 1.9, 1.6]], "num_anchor_sizes": 1, "rotations": [0.0, math.pi / 2],
             "pos_iou": 0.6, "neg_iou": 0.45, "num_dir_bins": 2, "dir_offset": math.pi / 4, "focal_alpha": 0.25,
             "focal_gamma": 2.0, "loss_weights": {"cls": 1.0, "box": 2.0, "dir": 0.2}},
    "post": {"score_threshold": 0.1, "pre_nms_top_k": 100, "nms_threshold": 0.1, "post_nms_top_k": 20},
}


def batch_of(points_list, boxes_list):
    pts = [torch.cat([torch.full((len(p), 1), float(i)), torch.as_tensor(p, dtype=torch.float32).reshape(-1, 4)], 1)
           for i, p in enumerate(points_list)]
    m = max([len(b) for b in boxes_list] + [0])
    gt = torch.zeros(len(boxes_list), m, 7)
    mask = torch.zeros(len(boxes_list), m, dtype=torch.bool)
    for i, b in enumerate(boxes_list):
        gt[i, :len(b)] = torch.as_tensor(b, dtype=torch.float32).reshape(-1, 7)
        mask[i, :len(b)] = True
    return Batch(torch.cat(pts) if pts else torch.zeros(0, 5), gt, mask, [str(i) for i in range(len(boxes_list))],
                 len(boxes_list))


# ---------------------------------------------------------------- the tiny test-only detector
# Synthetic frames (road points, 1-2 vehicles with points, one without) and a detector that pools per-point
# MLP features per frame and regresses one box plus a "has a vehicle" logit: small, honest, finite on
# empty frames.
PC_RANGE = [0.0, -20.0, -2.0, 80.0, 20.0, 4.0]
SCALE = torch.tensor([80.0, 20.0, 2.0, 5.0, 2.0, 2.0, 1.0])


def make_frame(seed: int, frame_id: str) -> Frame:
    """Road points, 1-2 vehicles with points, one vehicle without points (not LiDAR-detected)."""
    rng = np.random.default_rng(seed)
    boxes, pts = [], []
    for y in rng.permutation([-3.5, 0.0, 3.5])[: int(rng.integers(1, 3))]:
        dims = (rng.uniform(4, 5), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.7))
        box = [rng.uniform(10, 60), y, dims[2] / 2, *dims, float(rng.uniform(-0.1, 0.1))]
        boxes.append(box)
        local = rng.uniform(-0.45, 0.45, size=(40, 3)) * np.array(dims)
        c, s = math.cos(box[6]), math.sin(box[6])
        pts.append(np.stack([box[0] + c * local[:, 0] - s * local[:, 1], box[1] + s * local[:, 0] + c * local[:, 1],
                             box[2] + np.abs(local[:, 2]), rng.uniform(0, 1, 40)], axis=1))
    boxes.append([75.0, -10.5, 0.8, 4.5, 1.8, 1.6, 0.0])
    pts.append(np.stack([rng.uniform(0, 80, 150), rng.uniform(-20, 20, 150), np.zeros(150),
                         rng.uniform(0, 1, 150)], axis=1))
    m = len(boxes)
    return Frame(frame_id, frame_id[:4], np.concatenate(pts).astype(np.float32), np.asarray(boxes, np.float32),
                 np.array(["car"] * m), np.arange(m, dtype=np.int64), np.zeros(m, dtype=np.int64),
                 Sensor(height=1.8)).check()


FRAMES = [make_frame(s, f"{s // 4:04d}_{s % 4:03d}") for s in range(8)]


def make_set(tmp_path, gt_sampling=True, seed=0) -> TrainingSet:
    aug = AugmentConfig.from_dict({"gt_sampling": {"enabled": gt_sampling, "sample_count": 4,
                                                   "filter_by_min_points": 5}})
    db = build_gt_database(FRAMES, tmp_path / "db", progress=False) if gt_sampling else None
    return TrainingSet(FRAMES, PC_RANGE, augment=aug, gt_database=db, seed=seed)


class TinyOut(NamedTuple):
    boxes: torch.Tensor  # (B, 7) normalised box
    logits: torch.Tensor  # (B,)


class TinyDetector(nn.Module):
    def __init__(self, hidden: int = 32, interrupt_at: int | None = None, crash_at: int | None = None):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(4, hidden), nn.ReLU(), nn.Dropout(0.1), nn.Linear(hidden, hidden), nn.ReLU())
        self.norm = nn.BatchNorm1d(hidden)
        self.head = nn.Linear(hidden, 8)
        self.interrupt_at, self.crash_at, self.train_calls = interrupt_at, crash_at, 0

    def forward(self, batch: Batch) -> TinyOut:
        if self.training and torch.is_grad_enabled():  # a training step (not the BatchNorm statistics' passes)
            self.train_calls += 1
            if self.train_calls == self.interrupt_at:
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of a step
            if self.train_calls == self.crash_at:
                raise RuntimeError("simulated crash")
        p = batch.points
        feats = self.mlp(p[:, 1:5] / torch.tensor([80.0, 20.0, 2.0, 1.0], device=p.device))
        idx = p[:, 0].long()
        pooled = feats.new_zeros((batch.batch_size, feats.shape[1])).index_add_(0, idx, feats)  # autocast: half
        pooled = pooled / torch.bincount(idx, minlength=batch.batch_size).clamp(min=1)[:, None]
        out = self.head(self.norm(pooled))
        return TinyOut(out[:, :7], out[:, 7])

    def loss(self, out: TinyOut, batch: Batch):
        has = batch.gt_mask.any(dim=1) if batch.gt_mask.shape[1] else torch.zeros(batch.batch_size, dtype=torch.bool)
        if batch.gt_mask.shape[1] and has.any():
            target = batch.gt_boxes[:, 0] / SCALE.to(out.boxes.device)
            box = F.smooth_l1_loss(out.boxes[has], target[has])
        else:
            box = out.boxes.sum() * 0.0
        cls = F.binary_cross_entropy_with_logits(out.logits, has.float())
        total = box + cls
        return total, {"box": float(box.detach()), "cls": float(cls.detach())}

    def predict(self, out: TinyOut, batch: Batch) -> list[Detections]:
        boxes = out.boxes * SCALE.to(out.boxes.device)
        return [Detections(boxes[i:i + 1], torch.sigmoid(out.logits[i:i + 1]),
                           torch.zeros(1, dtype=torch.int64, device=boxes.device)) for i in range(batch.batch_size)]


RUN_CONFIG = {"model": {"name": "tiny"}, "train": {"epochs": 2, "batch_size": 2, "workers": 0, "lr": 0.01}}
DATA = {"source": "synthetic", "height": 1.8}


# ---------------------------------------------------------------- golden files
GOLDEN_DIR = ROOT / "tests" / "golden"


def assert_golden(name: str, text: str) -> None:
    """`text` equals tests/golden/<name>, the output pinned when the file was written.

    A golden file holds what a tool or report printed for fixed inputs, so a restructuring that changes any
    figure, row or word fails here. After a deliberate change of the output, rewrite the files with
    DETBENCH_WRITE_GOLDEN=1 and review their diff."""
    path = GOLDEN_DIR / name
    if os.environ.get("DETBENCH_WRITE_GOLDEN") == "1":
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        return
    assert path.is_file(), f"{path}: no golden file; write it with DETBENCH_WRITE_GOLDEN=1 and review it"
    expected = path.read_text(encoding="utf-8")
    if text != expected:
        import difflib

        diff = "".join(difflib.unified_diff(expected.splitlines(True), text.splitlines(True), f"golden/{name}",
                                            "now", n=1))
        raise AssertionError(f"output differs from tests/golden/{name}:\n{diff[:6000]}")
