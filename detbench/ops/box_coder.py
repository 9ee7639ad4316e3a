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

The small `check_boxes` / `check_points` helpers validate shapes for every op in
`detbench.ops` so that each error names the function, the argument and the fix.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from detbench.utils.angles import HUGE_ANGLE, fix_huge, wrap_exact

__all__ = [
    "limit_period",
    "normalize_heading",
    "boxes_to_corners_bev",
    "boxes_to_corners_3d",
    "ResidualBoxCoder",
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
        if boxes.dtype == object or not (np.issubdtype(boxes.dtype, np.floating) or np.issubdtype(boxes.dtype, np.integer)):
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
