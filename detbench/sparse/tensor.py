"""`SparseConvTensor`: active sites of a voxel grid and their features (spconv-like)."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .rulebook import RuleBook, validate_indices


class SparseConvTensor:
    """Features on the active sites of a batch of D-dimensional grids.

    Args:
        features: (N, C) float features, one row per active site.
        indices: (N, 1+D) int32 sites: (batch, z, y, x) for 3D, (batch, y, x) for 2D; each
            site appears once; converted to int32 if another integer dtype is given.
        spatial_shape: D ints, the grid size (Z, Y, X) / (Y, X) in voxels.
        batch_size: number of batch elements (elements without sites are allowed).
        indice_dict: rule books by ``indice_key``, shared by every tensor derived from this one
            within a forward pass (a fresh dict is made when omitted).
        check: validate indices against the grid (one min/max pass; default True).

    Attributes mirror spconv: ``features``, ``indices``, ``spatial_shape`` (list of ints),
    ``batch_size``, ``indice_dict``.
    """

    def __init__(self, features: torch.Tensor, indices: torch.Tensor, spatial_shape: Sequence[int],
                 batch_size: int, indice_dict: dict | None = None, check: bool = True):
        if not isinstance(features, torch.Tensor) or not isinstance(indices, torch.Tensor):
            raise TypeError("SparseConvTensor needs torch tensors for features (N, C) and indices (N, 1+D)")
        spatial_shape = [int(s) for s in spatial_shape]
        if any(s < 1 for s in spatial_shape):
            raise ValueError(f"spatial_shape must be positive ints, got {spatial_shape}")
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if features.dim() != 2:
            raise ValueError(f"features must be (N, C), got shape {tuple(features.shape)}")
        if features.shape[0] != indices.shape[0]:
            raise ValueError(f"features have {features.shape[0]} rows but indices {indices.shape[0]}; "
                             "there must be one feature row per active site")
        if features.device != indices.device:
            raise ValueError(f"features are on {features.device} but indices on {indices.device}; "
                             "move both to the same device")
        if check:
            validate_indices(indices, spatial_shape, int(batch_size))
        if indices.dtype != torch.int32:
            indices = indices.to(torch.int32)
        self.features = features
        self.indices = indices
        self.spatial_shape = spatial_shape
        self.batch_size = int(batch_size)
        self.indice_dict: dict[str, RuleBook] = {} if indice_dict is None else indice_dict

    # spconv compatibility --------------------------------------------------------------
    @property
    def ndim(self) -> int:
        """D, the number of spatial dims."""
        return len(self.spatial_shape)

    @property
    def spatial_size(self) -> int:
        """Number of grid sites per batch element (prod of spatial_shape)."""
        return math.prod(self.spatial_shape)

    @property
    def device(self) -> torch.device:
        return self.features.device

    @property
    def num_channels(self) -> int:
        return int(self.features.shape[1])

    def replace_feature(self, features: torch.Tensor) -> SparseConvTensor:
        """New tensor with the same sites and rule-book cache and new (N, C') features."""
        if features.dim() != 2 or features.shape[0] != self.features.shape[0]:
            raise ValueError(f"replacement features must be ({self.features.shape[0]}, C), got {tuple(features.shape)}")
        return SparseConvTensor(features, self.indices, self.spatial_shape, self.batch_size,
                                indice_dict=self.indice_dict, check=False)

    def find_indice_pair(self, key: str) -> RuleBook | None:
        """The rule book stored under ``key`` in this forward pass, or None."""
        return self.indice_dict.get(key)

    def dense(self, channels_first: bool = True) -> torch.Tensor:
        """Dense grid (B, C, *spatial_shape) (or (B, *spatial_shape, C)); inactive sites are 0.

        Differentiable w.r.t. the features.
        """
        b, c = self.batch_size, self.num_channels
        flat = self.features.new_zeros((b * self.spatial_size, c))
        if self.indices.shape[0]:
            key = self.indices[:, 0].long()
            for d, size in enumerate(self.spatial_shape):
                key = key * size + self.indices[:, d + 1].long()
            flat = flat.index_put((key,), self.features)
        out = flat.view(b, *self.spatial_shape, c)
        if channels_first:
            out = out.permute(0, self.ndim + 1, *range(1, self.ndim + 1)).contiguous()
        return out

    @classmethod
    def from_dense(cls, x: torch.Tensor, channels_first: bool = True) -> SparseConvTensor:
        """Sparse tensor of the sites of ``x`` (B, C, *spatial) where any channel is non-zero."""
        if not channels_first:
            x = x.permute(0, x.dim() - 1, *range(1, x.dim() - 1))
        b, c = x.shape[:2]
        spatial = list(x.shape[2:])
        active = (x != 0).any(dim=1)  # (B, *spatial)
        idx = active.nonzero()
        feats = x.permute(0, *range(2, x.dim()), 1)[active]
        return cls(feats, idx.to(torch.int32), spatial, int(b), check=False)

    def __repr__(self) -> str:
        return (f"SparseConvTensor(sites={self.indices.shape[0]}, channels={self.num_channels}, "
                f"spatial_shape={self.spatial_shape}, batch_size={self.batch_size}, "
                f"keys={sorted(self.indice_dict)}, device={self.device})")
