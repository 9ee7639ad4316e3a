"""Sparse convolution as gather -> matrix multiply -> scatter-add, per kernel offset.

``sparse_conv(features, weight, rulebook)`` computes, for every output row ``o``::

    out[o] = sum over pairs (i, o, k) of features[i] @ W_k,    W_k = weight[:, :, k].T

with ``weight`` in torch's ``nn.Conv3d`` layout (C_out, C_in, *kernel). The backward pass
uses the same pairs swapped (gradient w.r.t. features) and per-offset outer products
(gradient w.r.t. the weight); nothing but the inputs is saved for it.

Why not one big "implicit GEMM" (gather an (N_out, K * C_in) matrix with zero rows for the
missing neighbours, one matmul)? A LiDAR scan voxelised at 0.1 m has ~5 active neighbours
of 27 per site, so that formulation multiplies ~5x more zeros than useful numbers and was
2-4x slower on CPU in tools/bench_sparse.py measurements.

Mixed precision: under `torch.autocast` the features are cast to the autocast dtype
(float16 / bfloat16) once, before the autograd function, whose matrix products run in that
dtype with autocast off; the weight stays float32 and its gradient is accumulated in float32.
Left to autocast, each `torch.mm` inside the function casts on its own, so the forward output
is float16 while the saved features stay float32, and the backward pass fails on mixed dtypes
(tests/train/test_precision.py drives this path).
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from .rulebook import RuleBook


def _apply_pairs(x: torch.Tensor, w: torch.Tensor, rb: RuleBook) -> torch.Tensor:
    """out[o] = sum over the rule book's pairs (i, o, k) of x[i] @ w[k].

    x: (N_in, C_in); w: (K, C_in, C_out); returns (N_out, C_out).
    """
    if rb.identity_offset >= 0:
        out = torch.mm(x, w[rb.identity_offset])
    else:
        out = x.new_zeros((rb.num_out, w.shape[2]))
    for k, rows_in, rows_out in rb.offset_pairs():
        out.index_add_(0, rows_out, torch.mm(x.index_select(0, rows_in), w[k]))
    return out


class _SparseConvFunction(torch.autograd.Function):
    """Autograd wrapper; ``weight_kio`` is (K, C_in, C_out).

    The products run in the features' dtype; the weight gradient is accumulated in the
    weight's own dtype (float32 under mixed precision: a sum over thousands of sites
    overflows float16 long before the loss scale is lowered far enough)."""

    @staticmethod
    def forward(ctx, features, weight_kio, rb: RuleBook):
        ctx.rb = rb
        ctx.save_for_backward(features, weight_kio)
        return _apply_pairs(features, weight_kio.to(features.dtype), rb)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        features, weight_kio = ctx.saved_tensors
        rb: RuleBook = ctx.rb
        grad_out = grad_out.contiguous()
        need_x, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_x = grad_w = None
        w_t = weight_kio.to(grad_out.dtype).transpose(1, 2)  # (K, C_out, C_in)
        wdt = weight_kio.dtype
        if need_x:
            if rb.identity_offset >= 0:
                grad_x = torch.mm(grad_out, w_t[rb.identity_offset])
            else:
                grad_x = grad_out.new_zeros((rb.num_in, weight_kio.shape[1]))
        if need_w:
            grad_w = torch.zeros_like(weight_kio)
            if rb.identity_offset >= 0:
                grad_w[rb.identity_offset] = torch.mm(features.t().to(wdt), grad_out.to(wdt))
        if need_x or need_w:
            # One gather of the output gradient per offset serves both gradients.
            for k, rows_in, rows_out in rb.offset_pairs():
                g = grad_out.index_select(0, rows_out)
                if need_x:
                    grad_x.index_add_(0, rows_in, torch.mm(g, w_t[k]))
                if need_w:
                    grad_w[k] = torch.mm(features.index_select(0, rows_in).t().to(wdt), g.to(wdt))
        return grad_x, grad_w, None


def _autocast_dtype(device: torch.device) -> torch.dtype | None:
    """The autocast dtype active for `device`'s type, or None when autocast is off (torch >= 2.1)."""
    try:
        if torch.is_autocast_enabled(device.type):
            return torch.get_autocast_dtype(device.type)
        return None
    except (TypeError, AttributeError):  # torch < 2.4: per-device functions
        if device.type == "cuda" and torch.is_autocast_enabled():
            return torch.get_autocast_gpu_dtype()
        if device.type == "cpu" and torch.is_autocast_cpu_enabled():
            return torch.get_autocast_cpu_dtype()
        return None


def sparse_conv(features: torch.Tensor, weight: torch.Tensor, rulebook: RuleBook,
                bias: torch.Tensor | None = None) -> torch.Tensor:
    """Apply a sparse convolution given its rule book.

    Args:
        features: (N_in, C_in) float, rows in the order of ``rulebook.in_indices``.
        weight: (C_out, C_in, *kernel) in ``nn.Conv3d`` / ``nn.Conv2d`` layout.
        rulebook: from `build_subm_rulebook` / `build_conv_rulebook` (or its ``inverse()``).
        bias: (C_out,) or None.

    Returns:
        (N_out, C_out) features of ``rulebook.out_indices``; differentiable w.r.t.
        ``features``, ``weight`` and ``bias``.
    """
    c_out, c_in = int(weight.shape[0]), int(weight.shape[1])
    kvol = rulebook.kernel_volume
    if tuple(weight.shape[2:]) != rulebook.kernel_size:
        raise ValueError(f"weight kernel {tuple(weight.shape[2:])} does not match the rule book's kernel_size "
                         f"{rulebook.kernel_size}")
    if features.dim() != 2 or features.shape[1] != c_in:
        raise ValueError(f"features must be (N, {c_in}) for a weight of shape {tuple(weight.shape)}, "
                         f"got {tuple(features.shape)}")
    if features.shape[0] != rulebook.num_in:
        raise ValueError(f"features have {features.shape[0]} rows but the rule book has {rulebook.num_in} input sites")
    amp = _autocast_dtype(features.device) if features.is_floating_point() else None
    if amp is not None:  # features in the autocast dtype; the weight keeps its own (float32) dtype
        features = features.to(amp)
    else:
        weight = weight.to(features.dtype)
    weight_kio = weight.reshape(c_out, c_in, kvol).permute(2, 1, 0).contiguous()
    if amp is None:
        out = _SparseConvFunction.apply(features.contiguous(), weight_kio, rulebook)
    else:
        with torch.autocast(features.device.type, enabled=False):
            out = _SparseConvFunction.apply(features.contiguous(), weight_kio, rulebook)
    if bias is not None:
        out = out + bias.to(out.dtype)
    return out
