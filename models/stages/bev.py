"""From the sparse 3D backbone to a dense bird's-eye-view map."""
from __future__ import annotations

import torch
import torch.nn as nn

from detbench.sparse import SparseConvTensor


class HeightCompression(nn.Module):
    """Densify a SparseConvTensor (B, C, D, H, W) and stack depth into channels: (B, C*D, H, W)."""

    def forward(self, x: SparseConvTensor) -> torch.Tensor:
        dense = x.dense()
        b, c, d, h, w = dense.shape
        return dense.reshape(b, c * d, h, w)
