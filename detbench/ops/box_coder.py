"""Box helpers shared by the geometry ops and by the detection heads.

Boxes are `(x, y, z, dx, dy, dz, heading)` in the ego ground frame (metres, radians):
centre of the box, dx = length along the heading, dy = width, dz = height, heading
counter-clockwise from +x, normalised to [-pi, pi). This is OpenPCDet's unified box.

Contents
- `limit_period(val, offset=0.5, period=2*pi)`: wrap angles into [-offset*period, (1-offset)*period).
- `normalize_heading(val)`: wrap into [-pi, pi) exactly (no value equal to pi survives rounding).
- `boxes_to_corners_bev(boxes)` -> (M, 4, 2) and `boxes_to_corners_3d(boxes)` -> (M, 8, 3),
  numpy in -> numpy out, torch in -> torch out.
- `ResidualBoxCoder`: the SECOND / OpenPCDet residual encoding of boxes against anchors.
- `PointBinCoder`: PointRCNN's bin-based coding of a box relative to a point (BEV centre
  offset and heading as a bin class plus a residual inside the bin).

The small `check_boxes` / `check_points` helpers validate shapes for every op in
`detbench.ops` so that each error names the function, the argument and the fix.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from detbench.utils.angles import HUGE_ANGLE, fix_huge, wrap_exact

__all__ = [
    "limit_period",
    "normalize_heading",
    "boxes_to_corners_bev",
    "boxes_to_corners_3d",
    "ResidualBoxCoder",
    "PointBinCoder",
    "BinTargets",
]

TWO_PI = 2.0 * math.pi


# ----------------------------------------------------------------------------------------
# input validation shared by detbench.ops
# ----------------------------------------------------------------------------------------
def is_torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


def check_boxes(boxes: Any, func: str, name: str = "boxes", min_cols: int = 7):
    """Return `boxes` as a 2-D numpy array or tensor with >= `min_cols` columns.

    A 1-D array of exactly `min_cols` values is taken as one box. Anything else raises a
    ValueError naming `func`, the argument and the expected layout.
    """
    if not is_torch(boxes):
        boxes = np.asarray(boxes)
        if boxes.dtype == object or not (np.issubdtype(boxes.dtype, np.floating)
                                         or np.issubdtype(boxes.dtype, np.integer)):
            raise ValueError(
                f"{func}: `{name}` must be a numeric array of boxes (M, 7) "
                f"(x, y, z, dx, dy, dz, heading), got dtype {boxes.dtype}"
            )
    elif boxes.is_complex() or boxes.dtype == torch.bool:
        raise ValueError(f"{func}: `{name}` must be a real tensor (M, 7), got dtype {boxes.dtype}")
    if boxes.ndim == 1 and boxes.shape[0] == min_cols:
        boxes = boxes[None, :]
    if boxes.ndim == 1 and boxes.shape[0] == 0:
        boxes = boxes.reshape(0, min_cols)
    if boxes.ndim != 2 or boxes.shape[1] < min_cols:
        raise ValueError(
            f"{func}: `{name}` must have shape (M, {min_cols}) with columns "
            f"x, y, z, dx, dy, dz, heading (metres, radians); got shape {tuple(boxes.shape)}. "
            f"Reshape it, e.g. boxes.reshape(-1, {min_cols})."
        )
    return boxes


def check_points(points: Any, func: str, name: str = "points"):
    """Return `points` as a 2-D numpy array or tensor with >= 3 columns (x, y, z, ...)."""
    if not is_torch(points):
        points = np.asarray(points)
        if not (np.issubdtype(points.dtype, np.floating) or np.issubdtype(points.dtype, np.integer)):
            raise ValueError(f"{func}: `{name}` must be a numeric array (N, >=3), got dtype {points.dtype}")
    if points.ndim == 1 and points.shape[0] == 0:
        points = points.reshape(0, 3)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(
            f"{func}: `{name}` must have shape (N, >=3) with columns x, y, z[, intensity] "
            f"(metres); got shape {tuple(points.shape)}. Pass frame.points, or stack x, y, z as columns."
        )
    return points


def float_dtype_torch(*tensors: torch.Tensor) -> torch.dtype:
    """The floating dtype to compute in: float64 if any input is float64, else float32."""
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


# ----------------------------------------------------------------------------------------
# angles
# ----------------------------------------------------------------------------------------
def limit_period(val, offset: float = 0.5, period: float = TWO_PI):
    """Wrap `val` into [-offset * period, (1 - offset) * period).

    `val` may be a float, a numpy array or a tensor (same type and shape out). With the
    defaults it maps angles in radians into [-pi, pi), up to one rounding step at the
    upper border; use `normalize_heading` when the half-open interval must hold exactly.
    """
    if is_torch(val):
        return val - torch.floor(val / period + offset) * period
    if isinstance(val, np.ndarray):
        return val - np.floor(val / period + offset) * period
    return val - math.floor(val / period + offset) * period


def normalize_heading(val):
    """Wrap headings (radians) into [-pi, pi); float, numpy array or tensor, same type out.

    Guaranteed half-open: pi maps to -pi, and values that rounding pushes just outside the
    interval are folded back. Angles of HUGE_ANGLE (65536) rad or more are wrapped exactly in
    float64 (detbench.utils.angles; the float formula loses every digit there, e.g. 1e30 gives
    0 instead of 3.1323), then cast to the input's dtype; NaN and inf give NaN.
    """
    if is_torch(val):
        return _half_open(_fix_huge_tensor(val, limit_period(val, 0.5, TWO_PI)))
    if isinstance(val, np.ndarray):
        return _half_open(fix_huge(val, limit_period(val, 0.5, TWO_PI)).astype(val.dtype, copy=False))
    return _half_open(limit_period(val, 0.5, TWO_PI) if abs(val) < HUGE_ANGLE else wrap_exact(val))


def _fix_huge_tensor(val: torch.Tensor, wrapped: torch.Tensor) -> torch.Tensor:
    """`wrapped` with the elements where |val| >= HUGE_ANGLE replaced by their exact float64 wrap."""
    huge = val.detach().abs() >= HUGE_ANGLE
    if not bool(huge.any()):
        return wrapped
    exact = fix_huge(val.detach().cpu().numpy(), wrapped.detach().cpu().numpy().astype(np.float64))
    return torch.where(huge, torch.as_tensor(exact, device=val.device).to(wrapped.dtype), wrapped)


def _half_open(r):
    """Fold values that rounding left at -pi - eps or at pi back into [-pi, pi)."""
    if is_torch(r):
        r = torch.where(r < -math.pi, r + TWO_PI, r)
        return torch.where(r >= math.pi, r - TWO_PI, r)
    if isinstance(r, np.ndarray):
        r = np.where(r < -math.pi, r + TWO_PI, r)
        return np.where(r >= math.pi, r - TWO_PI, r)
    if r < -math.pi:
        r += TWO_PI
    if r >= math.pi:
        r -= TWO_PI
    return r


# ----------------------------------------------------------------------------------------
# corners
# ----------------------------------------------------------------------------------------
# unit corner template, counter-clockwise seen from above:
# front-left, rear-left, rear-right, front-right
_BEV_TEMPLATE = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]], dtype=np.float64)


def boxes_to_corners_bev(boxes):
    """Bird's-eye-view corners of boxes (M, 7) -> (M, 4, 2) x, y in metres.

    Order: counter-clockwise seen from above (+z), starting at the front-left corner:
    front-left, rear-left, rear-right, front-right ("front" is +dx/2 along the heading,
    "left" is +dy/2). numpy in -> numpy out (float64 for float64 input, else the input's
    float dtype); torch in -> torch out on the same device.
    """
    boxes = check_boxes(boxes, "boxes_to_corners_bev")
    if is_torch(boxes):
        dt = boxes.dtype if boxes.is_floating_point() else torch.float32
        b = boxes.to(dt)
        tmpl = torch.as_tensor(_BEV_TEMPLATE, dtype=dt, device=b.device)
        local = tmpl[None] * b[:, None, 3:5]  # (M,4,2)
        c, s = torch.cos(b[:, 6])[:, None], torch.sin(b[:, 6])[:, None]
        x = local[..., 0] * c - local[..., 1] * s + b[:, None, 0]
        y = local[..., 0] * s + local[..., 1] * c + b[:, None, 1]
        return torch.stack([x, y], dim=-1)
    dt = boxes.dtype if np.issubdtype(boxes.dtype, np.floating) else np.float64
    b = boxes.astype(np.float64, copy=False)
    local = _BEV_TEMPLATE[None] * b[:, None, 3:5]
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    x = local[..., 0] * c - local[..., 1] * s + b[:, None, 0]
    y = local[..., 0] * s + local[..., 1] * c + b[:, None, 1]
    return np.stack([x, y], axis=-1).astype(dt, copy=False)


def boxes_to_corners_3d(boxes):
    """3-D corners of boxes (M, 7) -> (M, 8, 3) x, y, z in metres.

    Corners 0-3 are the bottom face (z - dz/2) and 4-7 the top face (z + dz/2), each in
    the order of `boxes_to_corners_bev` (front-left, rear-left, rear-right, front-right),
    so corner k + 4 sits straight above corner k. numpy in -> numpy out, torch in -> torch
    out on the same device.
    """
    boxes = check_boxes(boxes, "boxes_to_corners_3d")
    bev = boxes_to_corners_bev(boxes)
    if is_torch(boxes):
        b = boxes.to(bev.dtype)
        zb = (b[:, 2] - 0.5 * b[:, 5])[:, None, None].expand(-1, 4, 1)
        zt = (b[:, 2] + 0.5 * b[:, 5])[:, None, None].expand(-1, 4, 1)
        return torch.cat([torch.cat([bev, zb], -1), torch.cat([bev, zt], -1)], dim=1)
    b = boxes.astype(np.float64, copy=False)
    zb = np.broadcast_to((b[:, 2] - 0.5 * b[:, 5])[:, None, None], (b.shape[0], 4, 1)).astype(bev.dtype)
    zt = np.broadcast_to((b[:, 2] + 0.5 * b[:, 5])[:, None, None], (b.shape[0], 4, 1)).astype(bev.dtype)
    return np.concatenate([np.concatenate([bev, zb], -1), np.concatenate([bev, zt], -1)], axis=1)


# ----------------------------------------------------------------------------------------
# residual coder
# ----------------------------------------------------------------------------------------
class ResidualBoxCoder:
    """SECOND / OpenPCDet residual encoding of boxes (x, y, z, dx, dy, dz, heading) against anchors.

    With d = sqrt(dx_a^2 + dy_a^2) the anchor's BEV diagonal (metres):

        t_x = (x - x_a) / d          t_dx = log(dx / dx_a)
        t_y = (y - y_a) / d          t_dy = log(dy / dy_a)
        t_z = (z - z_a) / dz_a       t_dz = log(dz / dz_a)
        t_h = heading - heading_a                    (encode_angle_by_sincos=False)
        t_cos, t_sin = cos h - cos h_a, sin h - sin h_a   (encode_angle_by_sincos=True)

    z is the box centre (the unified box). `code_size` is 7, or 8 with sin/cos angles.
    Extra columns past the 7 box values (e.g. velocities) are carried through as plain
    differences on encode and sums on decode.

    `encode(boxes, anchors)` and `decode(deltas, anchors)` take tensors of shape (..., C)
    with matching leading shapes (broadcasting allowed) and return the same dtype and
    device. Sizes are clamped at `min_size` (metres, default 1e-5) before the log, so a
    zero-size box never produces -inf. The heading residual is not wrapped: a decoded
    heading is heading_a + t_h; pass it through `normalize_heading` when needed.
    """

    def __init__(self, encode_angle_by_sincos: bool = False, min_size: float = 1e-5):
        self.encode_angle_by_sincos = bool(encode_angle_by_sincos)
        self.min_size = float(min_size)
        self.code_size = 8 if self.encode_angle_by_sincos else 7

    def __repr__(self) -> str:
        return f"ResidualBoxCoder(encode_angle_by_sincos={self.encode_angle_by_sincos}, min_size={self.min_size})"

    @staticmethod
    def _check(t, name: str, min_cols: int, func: str) -> torch.Tensor:
        if not is_torch(t):
            raise TypeError(f"ResidualBoxCoder.{func}: `{name}` must be a torch.Tensor, got {type(t).__name__}; "
                            f"wrap numpy arrays with torch.from_numpy")
        if t.ndim < 1 or t.shape[-1] < min_cols:
            raise ValueError(f"ResidualBoxCoder.{func}: `{name}` must have shape (..., >={min_cols}), "
                             f"got {tuple(t.shape)}")
        return t

    def encode(self, boxes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """Residuals (..., code_size [+ extra]) of `boxes` (..., 7+E) w.r.t. `anchors` (..., 7+E)."""
        self._check(boxes, "boxes", 7, "encode")
        self._check(anchors, "anchors", 7, "encode")
        if boxes.shape[-1] != anchors.shape[-1]:
            raise ValueError(f"ResidualBoxCoder.encode: boxes have {boxes.shape[-1]} columns but anchors "
                             f"{anchors.shape[-1]}; give both the same columns")
        xa, ya, za, dxa, dya, dza, ra = torch.unbind(anchors[..., :7], dim=-1)
        xg, yg, zg, dxg, dyg, dzg, rg = torch.unbind(boxes[..., :7], dim=-1)
        eps = self.min_size
        dxa, dya, dza = dxa.clamp(min=eps), dya.clamp(min=eps), dza.clamp(min=eps)
        dxg, dyg, dzg = dxg.clamp(min=eps), dyg.clamp(min=eps), dzg.clamp(min=eps)
        diag = torch.sqrt(dxa * dxa + dya * dya)
        parts = [
            (xg - xa) / diag, (yg - ya) / diag, (zg - za) / dza,
            torch.log(dxg / dxa), torch.log(dyg / dya), torch.log(dzg / dza),
        ]
        if self.encode_angle_by_sincos:
            parts += [torch.cos(rg) - torch.cos(ra), torch.sin(rg) - torch.sin(ra)]
        else:
            parts.append(rg - ra)
        out = torch.stack(parts, dim=-1)
        if boxes.shape[-1] > 7:
            out = torch.cat([out, boxes[..., 7:] - anchors[..., 7:]], dim=-1)
        return out

    def decode(self, deltas: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """Boxes (..., 7+E) from residuals `deltas` (..., code_size+E) and `anchors` (..., 7+E)."""
        self._check(deltas, "deltas", self.code_size, "decode")
        self._check(anchors, "anchors", 7, "decode")
        extra = anchors.shape[-1] - 7
        if deltas.shape[-1] != self.code_size + extra:
            raise ValueError(f"ResidualBoxCoder.decode: deltas have {deltas.shape[-1]} columns, expected "
                             f"code_size {self.code_size} + {extra} extra columns of the anchors")
        xa, ya, za, dxa, dya, dza, ra = torch.unbind(anchors[..., :7], dim=-1)
        eps = self.min_size
        dxa, dya, dza = dxa.clamp(min=eps), dya.clamp(min=eps), dza.clamp(min=eps)
        diag = torch.sqrt(dxa * dxa + dya * dya)
        xt, yt, zt, dxt, dyt, dzt = torch.unbind(deltas[..., :6], dim=-1)
        xg = xt * diag + xa
        yg = yt * diag + ya
        zg = zt * dza + za
        dxg = torch.exp(dxt) * dxa
        dyg = torch.exp(dyt) * dya
        dzg = torch.exp(dzt) * dza
        if self.encode_angle_by_sincos:
            cg = deltas[..., 6] + torch.cos(ra)
            sg = deltas[..., 7] + torch.sin(ra)
            rg = torch.atan2(sg, cg)
        else:
            rg = deltas[..., 6] + ra
        out = torch.stack([xg, yg, zg, dxg, dyg, dzg, rg], dim=-1)
        if extra > 0:
            out = torch.cat([out, deltas[..., self.code_size:] + anchors[..., 7:]], dim=-1)
        return out


# ----------------------------------------------------------------------------------------
# bin-based coder (PointRCNN)
# ----------------------------------------------------------------------------------------
class BinTargets(NamedTuple):
    """Targets of `PointBinCoder.encode` for boxes (..., 7) seen from points (..., 3)."""
    x_bin: torch.Tensor  # (...) int64 bin of the x offset, 0 .. num_loc_bins - 1
    y_bin: torch.Tensor  # (...) int64 bin of the y offset
    x_res: torch.Tensor  # (...) offset inside the x bin / bin size, in [-0.5, 0.5]
    y_res: torch.Tensor  # (...) offset inside the y bin / bin size
    z_res: torch.Tensor  # (...) box centre z - point z, metres
    h_bin: torch.Tensor  # (...) int64 heading bin, 0 .. num_heading_bins - 1
    h_res: torch.Tensor  # (...) heading inside its bin / half the bin width, in [-1, 1)
    size_res: torch.Tensor  # (..., 3) (size - mean size) / mean size


class PointBinCoder:
    """PointRCNN's bin-based box coding (Shi et al., CVPR 2019, Sec. 3.1), ground plane x / y.

    A box (x, y, z, dx, dy, dz, heading) is coded relative to a point (px, py, pz):

    - x (and y alike): the offset x - px is shifted by the search range S (`loc_scope`, m) and
      clamped into [0, 2 S): offsets beyond +-S fall into the first or last bin. Its bin
      b = floor(shift / B) (B = `loc_bin_size`, m; 2 S / B bins) is classified; the residual
      inside the bin, (shift - (b + 0.5) B) / B in [-0.5, 0.5], is regressed.
    - z: the plain offset z - pz in metres (one value).
    - heading: shifted by half a bin and wrapped into [0, 2 pi), then `num_heading_bins` bins
      of 2 pi / K; the residual inside the bin is normalised by half the bin width, [-1, 1).
    - size: (size - mean size) / mean size per axis.

    The network output per point (`code_size` channels) is laid out as
    [x bin logits (L) | y bin logits (L) | x residuals (L) | y residuals (L) | z (1) |
     heading bin logits (K) | heading residuals (K) | size (3)], L = 2 S / B, K bins:
    each bin has its own residual channel, and decoding reads the residual of the arg-max bin.
    """

    def __init__(self, mean_size: Sequence[float], loc_scope: float = 3.0, loc_bin_size: float = 0.5,
                 num_heading_bins: int = 12):
        ms = [float(v) for v in mean_size]
        if len(ms) != 3 or min(ms) <= 0:
            raise ValueError(f"PointBinCoder: mean_size must be [length, width, height] > 0 m, got {mean_size}")
        if not (loc_scope > 0 and loc_bin_size > 0):
            raise ValueError(f"PointBinCoder: loc_scope ({loc_scope}) and loc_bin_size ({loc_bin_size}) must be > 0 m")
        nb = 2.0 * float(loc_scope) / float(loc_bin_size)
        if abs(nb - round(nb)) > 1e-6:
            raise ValueError(f"PointBinCoder: 2 * loc_scope ({loc_scope} m) must be a whole number of "
                             f"loc_bin_size ({loc_bin_size} m) bins; e.g. loc_scope 3.0 with loc_bin_size 0.5")
        if int(num_heading_bins) < 1:
            raise ValueError(f"PointBinCoder: num_heading_bins must be >= 1, got {num_heading_bins}")
        self.mean_size = ms
        self.loc_scope, self.loc_bin_size = float(loc_scope), float(loc_bin_size)
        self.num_loc_bins = int(round(nb))
        self.num_heading_bins = int(num_heading_bins)
        self.code_size = 4 * self.num_loc_bins + 1 + 2 * self.num_heading_bins + 3

    def __repr__(self) -> str:
        return (f"PointBinCoder(mean_size={self.mean_size}, loc_scope={self.loc_scope}, "
                f"loc_bin_size={self.loc_bin_size}, num_heading_bins={self.num_heading_bins})")

    def split(self, pred: torch.Tensor) -> dict:
        """The named slices of a raw output (..., code_size)."""
        if pred.shape[-1] != self.code_size:
            raise ValueError(f"PointBinCoder: the output has {pred.shape[-1]} channels, expected code_size "
                             f"{self.code_size} ({self!r})")
        L, K = self.num_loc_bins, self.num_heading_bins
        names = [("x_bin", L), ("y_bin", L), ("x_res", L), ("y_res", L), ("z_res", 1), ("h_bin", K), ("h_res", K),
                 ("size_res", 3)]
        out, i = {}, 0
        for name, n in names:
            out[name] = pred[..., i:i + n]
            i += n
        out["z_res"] = out["z_res"][..., 0]
        return out

    def _loc(self, offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, b = self.loc_scope, self.loc_bin_size
        shift = (offset + s).clamp(0.0, 2.0 * s - 1e-3)
        bins = torch.floor(shift / b).long().clamp(0, self.num_loc_bins - 1)
        res = (shift - (bins.to(shift.dtype) + 0.5) * b) / b
        return bins, res

    def encode(self, boxes: torch.Tensor, points: torch.Tensor) -> BinTargets:
        """Targets of boxes (..., 7) relative to points (..., 3) (broadcasting allowed)."""
        if boxes.shape[-1] < 7 or points.shape[-1] < 3:
            raise ValueError(f"PointBinCoder.encode: boxes must be (..., 7) and points (..., 3), got "
                             f"{tuple(boxes.shape)} and {tuple(points.shape)}")
        x_bin, x_res = self._loc(boxes[..., 0] - points[..., 0])
        y_bin, y_res = self._loc(boxes[..., 1] - points[..., 1])
        z_res = boxes[..., 2] - points[..., 2]
        k = self.num_heading_bins
        width = TWO_PI / k
        h = torch.remainder(boxes[..., 6] + 0.5 * width, TWO_PI)
        h_bin = torch.floor(h / width).long().clamp(0, k - 1)
        h_res = (h - (h_bin.to(h.dtype) + 0.5) * width) / (0.5 * width)
        mean = torch.as_tensor(self.mean_size, dtype=boxes.dtype, device=boxes.device)
        size_res = (boxes[..., 3:6] - mean) / mean
        return BinTargets(x_bin, y_bin, x_res, y_res, z_res, h_bin, h_res, size_res)

    def decode(self, pred: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Boxes (..., 7) from raw outputs (..., code_size) at points (..., 3): arg-max bins + their residuals.

        Sizes are kept at >= 1 % of the mean size (a residual below -1 would give a negative size).
        """
        p = self.split(pred)
        s, b = self.loc_scope, self.loc_bin_size

        def loc(bin_logits, res):
            bins = bin_logits.argmax(dim=-1, keepdim=True)
            r = res.gather(-1, bins)[..., 0]
            return (bins[..., 0].to(res.dtype) + 0.5 + r) * b - s

        x = points[..., 0] + loc(p["x_bin"], p["x_res"])
        y = points[..., 1] + loc(p["y_bin"], p["y_res"])
        z = points[..., 2] + p["z_res"]
        width = TWO_PI / self.num_heading_bins
        hb = p["h_bin"].argmax(dim=-1, keepdim=True)
        hr = p["h_res"].gather(-1, hb)[..., 0]
        heading = normalize_heading((hb[..., 0].to(hr.dtype) + 0.5) * width + hr * 0.5 * width - 0.5 * width)
        mean = torch.as_tensor(self.mean_size, dtype=pred.dtype, device=pred.device)
        size = (p["size_res"] * mean + mean).clamp(min=0.01 * mean)
        return torch.cat([torch.stack([x, y, z], dim=-1), size, heading[..., None]], dim=-1)
