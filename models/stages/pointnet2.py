"""PointNet++ stages (Qi et al. 2017) on detbench.ops' point ops: sampling, set abstraction, propagation.

Point sets are batched as the ops batch them: the points of F "frames" concatenated, with a
per-frame count. A frame is a LiDAR frame in the backbone and one RoI in PointRCNN's second
stage. Every level keeps a fixed number of points per frame, so counts stay uniform.

- `sample_frame_points`: each frame's points to a fixed budget (the paper's sampling:
  distant points first, near points randomly, repeats when a frame has too few), in scan
  order or shuffled; optionally thinned first to one point per voxel cell.
- `SharedMLP`: per-point Linear + BatchNorm + ReLU layers (or Linear with bias + ReLU).
- `SetAbstraction`: farthest point sampling, ball query per radius (multi-scale grouping),
  shared MLP and max-pool per scale, concatenated; `npoint=None` groups all points of a frame.
- `FeaturePropagation`: three-nearest-neighbour interpolation from a coarse level to a fine
  one, concatenated with the fine level's own features, then a shared MLP.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn

from detbench.ops import ball_query, farthest_point_sample, group_linear, three_nn_interpolate, unique_voxels

from detbench.sparse import SafeBatchNorm1d

from .config import Section, StageConfig, ball_radii, centre_counts, nested_counts

@dataclass(frozen=True)
class SamplingConfig(StageConfig):
    """PointRCNN's `model.sampling`: each frame's points to a fixed budget (`sample_frame_points`)."""

    num_points: int  # points per frame fed to the network
    far_threshold: float  # m (BEV): points farther than this are kept first
    shuffle: bool  # sampled points in random order
    voxel_size: float  # m: first one point per cubic cell of this edge (0: every point)

    @classmethod
    def read(cls, s: Section) -> SamplingConfig:
        return cls(num_points=s.count("num_points"),
                   far_threshold=s.non_negative("far_threshold", "a distance >= 0 in metres"),
                   shuffle=s.flag("shuffle"),
                   voxel_size=s.non_negative("voxel_size", "a cell edge >= 0 in metres (0: no thinning)"))


@dataclass(frozen=True)
class PointNet2Config(StageConfig):
    """PointRCNN's `model.backbone`: one entry per set-abstraction level (and per scale inside one)."""

    npoints: tuple[int | None, ...]  # centres per frame of each level (-1 in the YAML, None here: all points)
    radii: tuple[tuple[float, ...], ...]  # m, ball radius of each scale
    nsamples: tuple[tuple[int, ...], ...]  # points per ball of each scale
    mlps: tuple[tuple[tuple[int, ...], ...], ...]  # layer widths of each scale
    fp_mlps: tuple[tuple[int, ...], ...]  # layer widths of each feature-propagation level

    @classmethod
    def read(cls, s: Section) -> PointNet2Config:
        return cls(npoints=centre_counts(s, "npoints"), radii=ball_radii(s, "radii"),
                   nsamples=nested_counts(s, "nsamples", 2), mlps=nested_counts(s, "mlps", 3),
                   fp_mlps=nested_counts(s, "fp_mlps", 2))


class SampledPoints(NamedTuple):
    points: torch.Tensor  # (B * N, C) the sampled rows of each frame, frames in order
    valid: torch.Tensor  # (B * N,) bool; False for the filler points of an empty frame
    num_points: int  # N, points per frame


@torch.no_grad()
def thin_to_voxels(pts: torch.Tensor, voxel_size: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Indices (sorted) of one randomly chosen point per occupied cubic cell of edge `voxel_size` (m) of
    `pts` (N, >= 3), so a near vehicle's thousands of points and a far one's few come out at one density."""
    n = pts.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=pts.device)
    cell = torch.floor(pts[:, :3] / voxel_size).to(torch.int64)
    cells, group = unique_voxels(cell - cell.min(dim=0).values)
    rank = torch.randperm(n, generator=generator).to(pts.device)
    first = torch.full((len(cells),), n, dtype=torch.long, device=pts.device).scatter_reduce(0, group, rank, "amin")
    return (rank == first[group]).nonzero(as_tuple=True)[0]


@torch.no_grad()
def sample_frame_points(points: torch.Tensor, batch_size: int, num_points: int, far_threshold: float,
                        generator: torch.Generator | None = None, *, shuffle: bool,
                        voxel_size: float) -> SampledPoints:
    """Each frame of a Batch's points (P, 1 + C) to exactly `num_points` rows (PointRCNN's sampling).

    With `voxel_size` > 0 (m; 0: no thinning) each frame is first thinned to one random point per cubic
    cell of that edge (`thin_to_voxels`): the budget then goes to the scene's shape rather than to the
    densest, nearest surfaces, and a frame crowded with vehicles (ground-truth sampling) is sampled like a
    sparse one.
    A frame with more points keeps all points farther than `far_threshold` (BEV distance from
    the sensor, metres) when they fit, and fills the budget with a random subset of the near
    ones (if even the far ones do not fit, a random subset of them); a frame with fewer
    points keeps them all and repeats random ones; an empty frame gets `num_points` filler
    rows (all zeros, z = -10 m, `valid` False). Kept rows stay in their original order, or with
    `shuffle` come in a random order: a ball query takes the first `nsample` points of a ball in
    row order, and a scan-ordered cloud would give it the lowest laser rows first.
    Random draws come from `generator` (a CPU generator) or torch's global one, so the sample
    and its order are the same for the same generator seed.
    """
    out, valid = [], []
    c = points.shape[1] - 1
    for i in range(batch_size):
        pts = points[points[:, 0] == i, 1:]
        if voxel_size > 0:
            pts = pts[thin_to_voxels(pts, voxel_size, generator)]
        n = pts.shape[0]
        if n == 0:
            filler = pts.new_zeros(num_points, c)
            filler[:, 2] = -10.0
            out.append(filler)
            valid.append(torch.zeros(num_points, dtype=torch.bool, device=points.device))
            continue
        if n >= num_points:
            far = torch.hypot(pts[:, 0], pts[:, 1]) > far_threshold
            far_idx, near_idx = far.nonzero(as_tuple=True)[0], (~far).nonzero(as_tuple=True)[0]
            if far_idx.numel() >= num_points:
                keep = far_idx[torch.randperm(far_idx.numel(), generator=generator)[:num_points].to(pts.device)]
            else:
                pick = torch.randperm(near_idx.numel(), generator=generator)[:num_points - far_idx.numel()]
                keep = torch.cat([far_idx, near_idx[pick.to(pts.device)]])
            keep = keep.sort().values
        else:
            extra = torch.randint(n, (num_points - n,), generator=generator).to(pts.device)
            keep = torch.cat([torch.arange(n, device=pts.device), extra])
        if shuffle:
            keep = keep[torch.randperm(keep.numel(), generator=generator).to(pts.device)]
        out.append(pts[keep])
        valid.append(torch.ones(num_points, dtype=torch.bool, device=points.device))
    if not out:
        return SampledPoints(points.new_zeros(0, c), torch.zeros(0, dtype=torch.bool, device=points.device), num_points)
    return SampledPoints(torch.cat(out), torch.cat(valid), num_points)


class SharedMLP(nn.Module):
    """Per-point layers: (..., C_in) -> (..., C_out), Linear (no bias) + BatchNorm + ReLU each,
    or with `batch_norm` False Linear (with bias) + ReLU."""

    def __init__(self, channels: Sequence[int], batch_norm: bool):
        super().__init__()
        layers: list[nn.Module] = []
        for cin, cout in zip(channels[:-1], channels[1:]):
            if batch_norm:
                layers += [nn.Linear(cin, cout, bias=False), SafeBatchNorm1d(cout), nn.ReLU(inplace=True)]
            else:
                layers += [nn.Linear(cin, cout), nn.ReLU(inplace=True)]
        self.layers = nn.Sequential(*layers)
        self.out_channels = int(channels[-1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = x.shape
        return self.layers(x.reshape(-1, shape[-1])).reshape(*shape[:-1], self.out_channels)

    def forward_grouped(self, xyz: torch.Tensor, centres: torch.Tensor, index: torch.Tensor,
                        features: torch.Tensor | None) -> torch.Tensor:
        """`self(group_neighbours(xyz, centres, index, features))` -> (M, K, C_out), with the first linear
        layer applied per point before the gather (detbench.ops.group_linear): a point in several balls
        is multiplied once, and the grouped input is never built."""
        first = self.layers[0]
        x = group_linear(xyz, centres, index, features, first.weight, first.bias)
        m, k = x.shape[:2]
        return self.layers[1:](x.reshape(m * k, -1)).reshape(m, k, self.out_channels)


class PointLevel(NamedTuple):
    xyz: torch.Tensor  # (F * n, 3) metres
    features: torch.Tensor | None  # (F * n, C)
    n: int  # points per frame


class SetAbstraction(nn.Module):
    """One PointNet++ set-abstraction level with multi-scale grouping.

    npoint: centres per frame (farthest point sampling), or None to group every point of a
    frame around its origin (the last level of a classifier / PointRCNN's RoI network).
    radii, nsamples, mlps: one entry per scale; mlps[s] lists the layer widths after the
    input (3 relative coordinates + the incoming features). batch_norm: see `SharedMLP`.
    """

    def __init__(self, npoint: int | None, radii: Sequence[float], nsamples: Sequence[int],
                 mlps: Sequence[Sequence[int]], in_channels: int, batch_norm: bool):
        super().__init__()
        if npoint is not None and not (len(radii) == len(nsamples) == len(mlps)):
            raise ValueError(f"SetAbstraction: radii {list(radii)}, nsamples {list(nsamples)} and mlps need one "
                             f"entry per scale")
        self.npoint = None if npoint in (None, -1) else int(npoint)
        self.radii, self.nsamples = [float(r) for r in radii], [int(n) for n in nsamples]
        self.mlps = nn.ModuleList(SharedMLP([3 + in_channels, *m], batch_norm) for m in mlps)
        self.out_channels = sum(m.out_channels for m in self.mlps)

    def forward(self, level: PointLevel) -> PointLevel:
        xyz, feats, n = level
        frames = xyz.shape[0] // max(n, 1) if n else 0
        if self.npoint is None:
            grouped = xyz[:, :3] if feats is None else torch.cat([xyz[:, :3], feats], dim=1)
            out = self.mlps[0](grouped.reshape(frames, n, -1)).max(dim=1).values
            return PointLevel(xyz.new_zeros(frames, 3), out, 1)
        counts = torch.full((frames,), n, dtype=torch.int64)
        idx = farthest_point_sample(xyz.detach(), self.npoint, counts=counts)
        new_xyz = xyz[idx.to(xyz.device)]
        new_counts = torch.full((frames,), self.npoint, dtype=torch.int64)
        outs = []
        for r, ns, mlp in zip(self.radii, self.nsamples, self.mlps):
            bq = ball_query(xyz.detach(), new_xyz.detach(), r, ns, xyz_counts=counts, centre_counts=new_counts)
            # mlp over the (M, ns, 3 + C) grouped points (zeros for empty slots), grouped after its first layer
            outs.append(mlp.forward_grouped(xyz, new_xyz, bq.index, feats).max(dim=1).values)
        return PointLevel(new_xyz, torch.cat(outs, dim=1), self.npoint)


class FeaturePropagation(nn.Module):
    """Coarse features interpolated to the fine points, joined with the fine features, then an MLP."""

    def __init__(self, coarse_channels: int, fine_channels: int, mlp: Sequence[int]):
        super().__init__()
        self.mlp = SharedMLP([coarse_channels + fine_channels, *mlp], batch_norm=True)
        self.out_channels = self.mlp.out_channels

    def forward(self, fine: PointLevel, coarse: PointLevel) -> PointLevel:
        frames = fine.xyz.shape[0] // max(fine.n, 1) if fine.n else 0
        interp = three_nn_interpolate(fine.xyz.detach(), coarse.xyz.detach(), coarse.features,
                                      target_counts=torch.full((frames,), fine.n, dtype=torch.int64),
                                      source_counts=torch.full((frames,), coarse.n, dtype=torch.int64))
        x = interp if fine.features is None else torch.cat([interp, fine.features], dim=1)
        return PointLevel(fine.xyz, self.mlp(x), fine.n)


class PointNet2MSG(nn.Module):
    """The PointNet++ backbone of PointRCNN: set-abstraction levels down, feature propagation back up.

    Returns features (F * n, fp_mlps[0][-1]) at every input point.
    """

    def __init__(self, in_channels: int, npoints: Sequence[int], radii: Sequence[Sequence[float]],
                 nsamples: Sequence[Sequence[int]], mlps: Sequence[Sequence[Sequence[int]]],
                 fp_mlps: Sequence[Sequence[int]]):
        super().__init__()
        if not (len(npoints) == len(radii) == len(nsamples) == len(mlps) == len(fp_mlps)):
            raise ValueError("PointNet2MSG: npoints, radii, nsamples, mlps and fp_mlps need one entry per level")
        self.sa = nn.ModuleList()
        channels = [in_channels]
        c = in_channels
        for npoint, r, ns, m in zip(npoints, radii, nsamples, mlps):
            layer = SetAbstraction(npoint, r, ns, m, c, batch_norm=True)
            self.sa.append(layer)
            c = layer.out_channels
            channels.append(c)
        self.fp = nn.ModuleList()
        # FP k joins level k + 1 (coarse; for the deepest, the last SA's output) with level k (fine)
        for k in reversed(range(len(fp_mlps))):
            coarse = channels[k + 1] if k == len(fp_mlps) - 1 else fp_mlps[k + 1][-1]
            self.fp.insert(0, FeaturePropagation(coarse, channels[k], fp_mlps[k]))
        self.out_channels = int(fp_mlps[0][-1])

    def forward(self, xyz: torch.Tensor, features: torch.Tensor | None, n: int) -> torch.Tensor:
        levels = [PointLevel(xyz, features, n)]
        for sa in self.sa:
            levels.append(sa(levels[-1]))
        up = levels[-1]
        for k in reversed(range(len(self.fp))):
            up = self.fp[k](levels[k], up)
        return up.features
