"""CT3D's RoI feature step (Sheng et al., "Improving 3D Object Detection with Channel-wise
Transformer", ICCV 2021): raw points around each proposal -> one feature vector per proposal.

  gather_cylinder_points: the points in a vertical cylinder around each proposal, radius
      `radius_scale` x half the BEV diagonal (the paper: 1.2), unlimited height; a fixed
      number per proposal, batched over all proposals of a frame (no loop over proposals)
  encode_proposal_points: each point's offsets to the proposal's 8 corners and centre in the
      proposal's frame, reparameterised as (distance / box diagonal, azimuth, inclination)
      per keypoint (27 values) plus the intensity
  CT3DRoIHead: point MLP -> self-attention encoder -> channel-wise re-weighting decoder
      (one learned query) -> (R, d) features

Departure from the reference code, on purpose: the offsets are taken in the proposal's
canonical frame (rotated by -heading) and the azimuth is atan2, so the encoding is invariant
to any rigid motion of scene and proposal together (the reference uses ego-frame offsets and
atan(y / x), which changes with the proposal's heading and folds opposite directions).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn

from detbench.ops import cylinder_query

from .config import Section, StageConfig
from .two_stage import ProposalConfig, RefineLossWeights, TargetConfig, rotate_z


@dataclass(frozen=True)
class CT3DLossWeights(StageConfig):
    """CT3D's `roi_head.loss_weights`: the first stage's total and the refinement's terms."""

    rpn: float  # SECOND's anchor loss (its own terms weighted by head.loss_weights)
    refine: RefineLossWeights

    @classmethod
    def read(cls, s: Section) -> CT3DLossWeights:
        return cls(rpn=s.non_negative("rpn"), refine=RefineLossWeights.read(s))


@dataclass(frozen=True)
class CT3DHeadConfig(StageConfig):
    """CT3D's `model.roi_head`: the transformer over each proposal's points and the shared second stage."""

    num_points: int  # points sampled in each proposal's cylinder
    radius_scale: float  # cylinder radius = radius_scale x half the proposal's BEV diagonal
    hidden_dim: int  # transformer width
    heads: int  # attention heads (divide hidden_dim)
    enc_layers: int  # self-attention encoder layers (0: none)
    dim_feedforward: int  # feed-forward width of each layer
    dropout: float  # dropout probability in the transformer and the refinement's branches
    mlp_hidden: int  # the point MLP: 28 -> mlp_hidden -> mlp_hidden -> hidden_dim
    max_pool_skip: bool  # also pass the encoded points' max-pool to the refinement
    fc: tuple[int, ...]  # hidden widths of the confidence and box branches
    proposals: ProposalConfig
    targets: TargetConfig
    loss_weights: CT3DLossWeights

    @classmethod
    def read(cls, s: Section) -> CT3DHeadConfig:
        c = cls(num_points=s.count("num_points"), radius_scale=s.positive("radius_scale", "a positive scale"),
                hidden_dim=s.count("hidden_dim"), heads=s.count("heads"), enc_layers=s.count("enc_layers", 0),
                dim_feedforward=s.count("dim_feedforward"), dropout=s.fraction("dropout", "a probability"),
                mlp_hidden=s.count("mlp_hidden"), max_pool_skip=s.flag("max_pool_skip"),
                fc=s.counts("fc", empty=True), proposals=s.section("proposals", ProposalConfig),
                targets=s.section("targets", TargetConfig), loss_weights=s.section("loss_weights", CT3DLossWeights))
        if c.hidden_dim % c.heads:
            raise s.error("heads", f"a divisor of hidden_dim ({c.hidden_dim})")
        return c

# the 8 corners of a unit box (front/rear x left/right x bottom/top) and its centre
_KEYPOINTS = torch.tensor([[sx, sy, sz] for sx in (0.5, -0.5) for sy in (0.5, -0.5) for sz in (-0.5, 0.5)]
                          + [[0.0, 0.0, 0.0]], dtype=torch.float32)  # (9, 3)
_GOLDEN = 0.6180339887498949


class CylinderPoints(NamedTuple):
    points: torch.Tensor  # (B, R, K, C) x, y, z (ego frame), further point features; zeros for empty
    count: torch.Tensor  # (B, R) int64 points inside each cylinder (before sampling / padding)
    empty: torch.Tensor  # (B, R) bool, no point inside


def cylinder_radius(rois: torch.Tensor, radius_scale: float) -> torch.Tensor:
    """(...,) radius (m) of the cylinder of RoIs (..., 7): scale x half the BEV diagonal."""
    return radius_scale * 0.5 * torch.sqrt(rois[..., 3] ** 2 + rois[..., 4] ** 2)


def gather_cylinder_points(points: torch.Tensor, rois: torch.Tensor, num_points: int, radius_scale: float,
                           random: bool = False, generator: torch.Generator | None = None) -> CylinderPoints:
    """The points around each proposal, a fixed count per proposal.

    Args:
        points: (P, 1 + C) [batch_index, x, y, z, features...] (a Batch's points).
        rois: (B, R, 7) proposals per frame.
        num_points: K, points per proposal.
        radius_scale: cylinder radius = radius_scale * sqrt((dx/2)^2 + (dy/2)^2); a point is
            inside when its BEV distance to the proposal's centre is <= the radius (any z).
        random: True (training): a uniformly random subset of the inside points (torch's
            global generator, or `generator`); False (evaluation): a deterministic spread
            (points ordered by the fractional part of index x golden ratio), so the same
            frame always gives the same points.
    Returns:
        CylinderPoints: (B, R, K, C) points; when a proposal holds fewer than K points they
        repeat cyclically; an empty proposal gives zeros and `empty` True.
    """
    b, r = rois.shape[:2]
    c = points.shape[1] - 1
    out = points.new_zeros(b, r, num_points, c)
    count = torch.zeros(b, r, dtype=torch.int64, device=rois.device)
    if r == 0:
        return CylinderPoints(out, count, count.bool())
    for i in range(b):
        pts = points[points[:, 0] == i, 1:]
        n = pts.shape[0]
        if n == 0:
            continue
        if random:
            keys = torch.rand(n, generator=generator).to(pts.device)
        else:
            keys = torch.remainder(torch.arange(n, device=pts.device, dtype=torch.float64) * _GOLDEN, 1.0).float()
        idx, cnt = cylinder_query(pts[:, :2].detach(), keys, rois[i, :, :2].detach(),
                                  cylinder_radius(rois[i].detach(), radius_scale), num_points)
        idx, cnt = idx.to(pts.device), cnt.to(pts.device)
        # an empty cylinder's slots are all EMPTY_INDEX: gather row 0 there, then the mask zeroes it
        out[i] = pts[idx.clamp_min(0)] * (cnt > 0)[:, None, None].to(pts.dtype)
        count[i] = cnt
    return CylinderPoints(out, count, count == 0)


def encode_proposal_points(points: torch.Tensor, rois: torch.Tensor) -> torch.Tensor:
    """CT3D's keypoint encoding: (..., K, 3 + F) points and (..., 7) RoIs -> (..., K, 27 + F).

    For each of the 9 keypoints (8 corners, centre) of the RoI: the point's offset in the RoI
    frame as (distance / RoI 3D diagonal, azimuth atan2(dy, dx), inclination acos(dz / d));
    then the point's further features (intensity). Finite for every input (d = 0 included).
    """
    local = points[..., :3] - rois[..., None, :3]
    local = rotate_z(local, -rois[..., 6])  # (..., K, 3) in the RoI frame
    kp = _KEYPOINTS.to(points.device, points.dtype) * rois[..., None, 3:6]  # (..., 9, 3)
    off = local[..., :, None, :] - kp[..., None, :, :]  # (..., K, 9, 3)
    dist = off.norm(dim=-1)
    diag = rois[..., 3:6].norm(dim=-1).clamp(min=1e-3)[..., None, None]
    azimuth = torch.atan2(off[..., 1], off[..., 0])
    incl = torch.acos((off[..., 2] / dist.clamp(min=1e-6)).clamp(-1.0, 1.0))
    enc = torch.cat([dist / diag, azimuth, incl], dim=-1)  # (..., K, 27)
    return torch.cat([enc, points[..., 3:]], dim=-1)


class ChannelWiseAttention(nn.Module):
    """CT3D's channel-wise re-weighting decoder attention (one query, `heads` heads).

    Per head of width dh, with q the projected query and k_m, v_m the projected keys and
    values of the K points:
        global score   s_m = q . k_m / sqrt(dh)                     one per point
        channel score  e_cm = k_cm * s_m                             one per point and channel
        weights        w_cm = softmax over points m of e_cm          sum to 1 over points, per channel
        Z_c'c = sum_m w_cm v_c'm;  output_c' = linear_c(Z_c'c)      (dh x dh -> dh)
    so each value channel is pooled with weights of every key channel, then mixed.
    """

    def __init__(self, d_model: int, heads: int):
        super().__init__()
        if d_model % heads:
            raise ValueError(f"CT3D: hidden_dim {d_model} must divide by heads {heads}")
        self.heads, self.dh = heads, d_model // heads
        self.q = nn.Linear(d_model, d_model)
        self.k = nn.Linear(d_model, d_model)
        self.v = nn.Linear(d_model, d_model)
        self.down = nn.Linear(self.dh, 1)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, query: torch.Tensor, memory: torch.Tensor, key_pos: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """query (N, d), memory (N, K, d) -> (output (N, d), weights (N, heads, dh, K))."""
        n, k, _ = memory.shape
        h, dh = self.heads, self.dh
        q = self.q(query).view(n, h, dh)
        key = self.k(memory if key_pos is None else memory + key_pos).view(n, k, h, dh).permute(0, 2, 3, 1)
        val = self.v(memory).view(n, k, h, dh).permute(0, 2, 3, 1)  # (N, h, dh, K)
        s = torch.einsum("nhc,nhck->nhk", q, key) / math.sqrt(dh)  # (N, h, K)
        w = torch.softmax(key * s[:, :, None, :], dim=-1)  # (N, h, dh, K)
        z = torch.einsum("nhck,nhdk->nhdc", w, val)  # (N, h, dh(value), dh(weight))
        o = self.down(z).squeeze(-1).reshape(n, h * dh)
        return self.out(o), w


class ChannelWiseDecoderLayer(nn.Module):
    """Decoder layer: channel-wise cross-attention + feed-forward, post-norm residuals.

    (The reference's self-attention over the queries is left out: with one query it is a
    fixed linear map of a learned vector, which the learned query already is.)
    """

    def __init__(self, d_model: int, heads: int, ff: int, dropout: float):
        super().__init__()
        self.attn = ChannelWiseAttention(d_model, heads)
        self.norm1, self.norm2 = nn.LayerNorm(d_model), nn.LayerNorm(d_model)
        self.ff = nn.Sequential(nn.Linear(d_model, ff), nn.ReLU(inplace=True), nn.Dropout(dropout),
                                nn.Linear(ff, d_model))
        self.drop = nn.Dropout(dropout)

    def forward(self, query: torch.Tensor, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a, w = self.attn(query, memory)
        x = self.norm1(query + self.drop(a))
        return self.norm2(x + self.drop(self.ff(x))), w


class CT3DRoIHead(nn.Module):
    """Points around each proposal -> one feature per proposal (B, R, d), set up by `cfg`; each point
    carries `point_features` values after x, y, z (a Batch's: the intensity)."""

    def __init__(self, cfg: CT3DHeadConfig, point_features: int):
        super().__init__()
        self.num_points, self.radius_scale = cfg.num_points, cfg.radius_scale
        hidden_dim, heads, enc_layers, dropout = cfg.hidden_dim, cfg.heads, cfg.enc_layers, cfg.dropout
        mlp_hidden, dim_feedforward = cfg.mlp_hidden, cfg.dim_feedforward
        cin = 27 + point_features
        self.up = nn.Sequential(nn.Linear(cin, mlp_hidden), nn.ReLU(inplace=True), nn.Linear(mlp_hidden, mlp_hidden),
                                nn.ReLU(inplace=True), nn.Linear(mlp_hidden, hidden_dim))
        self.empty_token = nn.Parameter(torch.zeros(hidden_dim))
        layer = nn.TransformerEncoderLayer(hidden_dim, heads, dim_feedforward, dropout, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, enc_layers, enable_nested_tensor=False) if enc_layers else None
        self.query = nn.Parameter(torch.randn(hidden_dim) * 0.02)
        self.decoder = ChannelWiseDecoderLayer(hidden_dim, heads, dim_feedforward, dropout)
        self.max_pool_skip = cfg.max_pool_skip
        self.out_channels = hidden_dim * (2 if self.max_pool_skip else 1)

    def forward(self, points: torch.Tensor, rois: torch.Tensor) -> torch.Tensor:
        """points (P, 5) of a Batch, rois (B, R, 7) -> features (B, R, hidden_dim)."""
        b, r = rois.shape[:2]
        cyl = gather_cylinder_points(points, rois.detach(), self.num_points, self.radius_scale,
                                     random=self.training)
        src = encode_proposal_points(cyl.points, rois.detach())  # (B, R, K, 28)
        src = self.up(src.reshape(b * r, self.num_points, src.shape[-1]))  # explicit width: b * r may be 0
        empty = cyl.empty.reshape(b * r)
        src = torch.where(empty[:, None, None], self.empty_token.expand_as(src), src)
        if self.encoder is not None and src.shape[0]:
            src = self.encoder(src)
        query = self.query.expand(b * r, -1)
        feat, _ = self.decoder(query, src)
        if self.max_pool_skip:  # the encoded points' channel-wise maximum beside the decoder's output
            feat = torch.cat([feat, src.max(dim=1).values if src.shape[0] else feat], dim=-1)
        return feat.reshape(b, r, feat.shape[-1])
