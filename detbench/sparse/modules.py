"""spconv-like sparse convolution layers and `SparseSequential`.

Weights are stored in torch's layout, (C_out, C_in, *kernel) like ``nn.Conv3d``, so a dense
``F.conv3d`` / ``F.conv2d`` with the same weight and bias gives the same values at every
active output site (the test oracle). For `SparseInverseConv3d` the oracle is
``F.conv_transpose3d(x, weight.transpose(0, 1), stride, padding, dilation)`` sampled at the
input sites of the matching `SparseConv3d`.

Rule books are cached per ``indice_key`` in the tensor's ``indice_dict`` (shared by all
tensors derived from one input within a forward pass): layers with the same key on the same
input sites build it once; `SparseInverseConv3d` reads the pairs of the `SparseConv3d` with
its key and restores exactly that layer's input sites.
"""
from __future__ import annotations

import math
from collections import OrderedDict

import torch
from torch import nn
import torch.nn.functional as F
from torch.nn.modules.batchnorm import _BatchNorm

from .functional import sparse_conv
from .rulebook import RuleBook, _tuple, build_conv_rulebook, build_subm_rulebook
from .tensor import SparseConvTensor


class SparseModule(nn.Module):
    """Marker base class: modules whose forward takes and returns a `SparseConvTensor`.

    `SparseSequential` passes the whole tensor to these, and only the features to others.
    Subclass it for your own sparse blocks (e.g. residual blocks).
    """


class SparseConvolution(SparseModule):
    """Sparse convolution over ``ndim`` spatial dims (use the named subclasses).

    Args:
        ndim: 2 or 3 spatial dims.
        in_channels, out_channels: feature widths.
        kernel_size, stride, padding, dilation: int or ndim ints, as ``nn.Conv3d``.
        bias: add a learned (C_out,) bias.
        subm: submanifold (output sites = input sites; stride must be 1).
        inverse: undo the `SparseConvolution` stored under ``indice_key`` (its geometry is used).
        indice_key: name under which the rule book is cached / looked up within a forward pass.
    """

    def __init__(self, ndim: int, in_channels: int, out_channels: int, kernel_size=3, stride=1, padding=0,
                 dilation=1, bias: bool = True, subm: bool = False, inverse: bool = False,
                 indice_key: str | None = None):
        super().__init__()
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"channels must be >= 1, got in_channels={in_channels}, out_channels={out_channels}")
        self.ndim = int(ndim)
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.kernel_size = _tuple(kernel_size, ndim, "kernel_size")
        self.stride = _tuple(stride, ndim, "stride")
        self.dilation = _tuple(dilation, ndim, "dilation")
        self.subm = bool(subm)
        self.inverse = bool(inverse)
        self.indice_key = indice_key
        if self.subm:
            if any(s != 1 for s in self.stride):
                raise ValueError(f"SubMConv{ndim}d needs stride 1, got {self.stride}; "
                                 f"use SparseConv{ndim}d to downsample")
            implied = tuple(d * (k - 1) // 2 for k, d in zip(self.kernel_size, self.dilation))
            if padding is not None and _tuple(padding, ndim, "padding") != implied:
                raise ValueError(f"SubMConv{ndim}d keeps the input grid, so its padding is dilation * (kernel - 1) / 2 "
                                 f"= {implied}; got padding={padding} "
                                 f"(pass padding={implied[0] if len(set(implied)) == 1 else implied} or omit it)")
            self.padding = implied
        else:
            self.padding = _tuple(0 if padding is None else padding, ndim, "padding")
        if self.inverse and not indice_key:
            raise ValueError(f"SparseInverseConv{ndim}d needs the indice_key of the SparseConv{ndim}d it undoes")
        self.weight = nn.Parameter(torch.empty(self.out_channels, self.in_channels, *self.kernel_size))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Same initialisation as ``nn.Conv3d`` (Kaiming-uniform, a = sqrt(5))."""
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        if self.bias is not None:
            fan_in = self.in_channels * math.prod(self.kernel_size)
            bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
            nn.init.uniform_(self.bias, -bound, bound)

    def extra_repr(self) -> str:
        kind = "subm" if self.subm else "inverse" if self.inverse else "conv"
        s = (f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, {kind}, "
             f"stride={self.stride}, padding={self.padding}, dilation={self.dilation}")
        if self.bias is None:
            s += ", bias=False"
        if self.indice_key:
            s += f", indice_key={self.indice_key!r}"
        return s

    def _name(self) -> str:
        kind = "SubMConv" if self.subm else "SparseInverseConv" if self.inverse else "SparseConv"
        return f"{kind}{self.ndim}d(indice_key={self.indice_key!r})"

    def _rulebook(self, x: SparseConvTensor) -> RuleBook:
        key = self.indice_key
        if self.inverse:
            rb = x.indice_dict.get(key)
            if rb is None:
                raise ValueError(f"{self._name()}: no rule book under this key in the forward pass; a SparseConv"
                                 f"{self.ndim}d with indice_key={key!r} must run earlier on the same input "
                                 f"(known keys: {sorted(x.indice_dict)})")
            if rb.subm:
                raise ValueError(f"{self._name()}: the key belongs to a SubM layer; give the inverse the key of a "
                                 f"strided SparseConv{self.ndim}d")
            if rb.kernel_size != self.kernel_size:
                raise ValueError(f"{self._name()}: kernel_size {self.kernel_size} differs from the SparseConv's "
                                 f"{rb.kernel_size}; they must match")
            if not _same_sites(rb.out_indices, x.indices):
                raise ValueError(f"{self._name()}: the input's sites are not the output sites of the SparseConv "
                                 f"with this key; apply the inverse to that layer's output (or a SubM chain on it)")
            return rb.inverse()
        geometry = (self.kernel_size, self.stride, self.padding, self.dilation, self.subm)
        if key is not None and key in x.indice_dict:
            rb = x.indice_dict[key]
            if rb.geometry() == geometry and _same_sites(rb.in_indices, x.indices):
                return rb
            if not (rb.geometry() == geometry):
                raise ValueError(f"{self._name()}: indice_key already holds a rule book of another geometry "
                                 f"{rb.geometry()} vs {geometry}; use a different indice_key for this layer")
            raise ValueError(f"{self._name()}: indice_key already holds a rule book of different input sites; "
                             "layers sharing a key must see the same sites (use a new key after a strided conv)")
        if self.subm:
            rb = build_subm_rulebook(x.indices, x.spatial_shape, self.kernel_size, self.dilation, x.batch_size)
        else:
            rb = build_conv_rulebook(x.indices, x.spatial_shape, self.kernel_size, self.stride, self.padding,
                                     self.dilation, x.batch_size)
        if key is not None:
            x.indice_dict[key] = rb
        return rb

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        """(N_in, C_in) features on ``x``'s sites -> (N_out, C_out) on the rule book's output sites."""
        if not isinstance(x, SparseConvTensor):
            raise TypeError(f"{self._name()} expects a SparseConvTensor, got {type(x).__name__}")
        if x.ndim != self.ndim:
            raise ValueError(f"{self._name()} is {self.ndim}D but the input has spatial_shape {x.spatial_shape}")
        if x.num_channels != self.in_channels:
            raise ValueError(f"{self._name()} expects {self.in_channels} input channels, got {x.num_channels}")
        rb = self._rulebook(x)
        feats = sparse_conv(x.features, self.weight, rb, self.bias)
        return SparseConvTensor(feats, rb.out_indices, rb.out_shape, x.batch_size, indice_dict=x.indice_dict,
                                check=False)


def _same_sites(a: torch.Tensor, b: torch.Tensor) -> bool:
    """True when two index tensors hold the same sites in the same order (identity fast path)."""
    if a is b:
        return True
    return a.shape == b.shape and a.device == b.device and bool(torch.equal(a, b))


class SubMConv3d(SparseConvolution):
    """Submanifold 3D convolution: output sites = input sites; weight (C_out, C_in, kz, ky, kx).

    ``padding`` may be omitted; if given it must equal ``dilation * (kernel - 1) / 2``.
    """

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=None, dilation=1, bias=True,
                 indice_key=None):
        super().__init__(3, in_channels, out_channels, kernel_size, stride, padding, dilation, bias, subm=True,
                         indice_key=indice_key)


class SparseConv3d(SparseConvolution):
    """Regular (e.g. strided) 3D sparse convolution; output sites as a dense conv of this geometry."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1, bias=True,
                 indice_key=None):
        super().__init__(3, in_channels, out_channels, kernel_size, stride, padding, dilation, bias,
                         indice_key=indice_key)


class SparseInverseConv3d(SparseConvolution):
    """Inverse of the `SparseConv3d` with the same ``indice_key``: restores its input sites.

    Stride, padding and dilation come from that layer's rule book; the kernel size must match.
    """

    def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=True):
        super().__init__(3, in_channels, out_channels, kernel_size, bias=bias, inverse=True, indice_key=indice_key)


class SubMConv2d(SparseConvolution):
    """Submanifold 2D convolution on (batch, y, x) sites; weight (C_out, C_in, ky, kx)."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=None, dilation=1, bias=True,
                 indice_key=None):
        super().__init__(2, in_channels, out_channels, kernel_size, stride, padding, dilation, bias, subm=True,
                         indice_key=indice_key)


class SparseConv2d(SparseConvolution):
    """Regular (e.g. strided) 2D sparse convolution."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1, bias=True,
                 indice_key=None):
        super().__init__(2, in_channels, out_channels, kernel_size, stride, padding, dilation, bias,
                         indice_key=indice_key)


class SparseInverseConv2d(SparseConvolution):
    """Inverse of the `SparseConv2d` with the same ``indice_key``: restores its input sites."""

    def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=True):
        super().__init__(2, in_channels, out_channels, kernel_size, bias=bias, inverse=True, indice_key=indice_key)


class ToDense(SparseModule):
    """SparseConvTensor -> dense (B, C, *spatial_shape) tensor."""

    def forward(self, x: SparseConvTensor) -> torch.Tensor:
        return x.dense()


def batch_norm_few_rows(bn: _BatchNorm, x: torch.Tensor) -> torch.Tensor:
    """BatchNorm of (N < 2, C) rows while training: no batch statistics exist, so the running
    ones normalise (and are not updated); zero rows stay zero rows."""
    if x.shape[0] == 0:
        return x
    return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)


class SafeBatchNorm1d(nn.BatchNorm1d):
    """BatchNorm1d over (N, C) rows that also accepts N < 2 while training (see
    `batch_norm_few_rows`); with N >= 2 it is exactly `nn.BatchNorm1d`. For features used
    outside a SparseSequential (residual blocks, point-wise MLPs)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training and x.shape[0] < 2:
            return batch_norm_few_rows(self, x)
        return super().forward(x)


class SparseSequential(nn.Sequential):
    """``nn.Sequential`` for sparse tensors.

    `SparseModule` children receive the whole `SparseConvTensor`; other modules (BatchNorm1d,
    ReLU, Dropout, Linear, ...) are applied to its (N, C) features. Once a child returns a
    plain tensor (e.g. `ToDense`), later children get that tensor. With no active sites the
    features stay empty (BatchNorm is skipped: it has no statistics to take); with a single
    active site in training, BatchNorm normalises with its running statistics (one value per
    channel has no variance) and leaves them unchanged.
    """

    def __init__(self, *args, **kwargs):
        if kwargs:
            if args:
                raise ValueError("SparseSequential takes modules as positional args or as keyword args, not both")
            args = (OrderedDict(kwargs),)
        super().__init__(*args)

    def forward(self, x):
        for module in self:
            if isinstance(x, SparseConvTensor) and not isinstance(module, (SparseModule, SparseSequential)):
                if isinstance(module, _BatchNorm) and module.training and x.features.shape[0] < 2:
                    x = x.replace_feature(batch_norm_few_rows(module, x.features))
                    continue
                x = x.replace_feature(module(x.features))
            else:
                x = module(x)
        return x
