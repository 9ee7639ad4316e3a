"""What tools/bench_sparse.py times besides the library's own layers: a SECOND-style 3D backbone
built from detbench.sparse layers, and the implicit-GEMM kernel it compares against."""
from __future__ import annotations

import torch
from torch import nn

from .modules import SparseConv3d, SparseSequential, SubMConv3d


def backbone(in_channels: int = 4) -> SparseSequential:
    """SECOND-style 3D backbone (OpenPCDet VoxelBackBone8x topology, BN eps 1e-3, momentum 0.01).

    A flat SparseSequential of conv + BatchNorm + ReLU blocks (each block's first module is its
    convolution), so a benchmark can walk the blocks and count each convolution's multiply-adds."""
    def block(cin, cout, key, stride=1, padding=1, kind="subm", kernel=3):
        conv = (SubMConv3d(cin, cout, kernel, bias=False, indice_key=key) if kind == "subm" else
                SparseConv3d(cin, cout, kernel, stride=stride, padding=padding, bias=False, indice_key=key))
        return SparseSequential(conv, nn.BatchNorm1d(cout, eps=1e-3, momentum=0.01), nn.ReLU())

    return SparseSequential(
        block(in_channels, 16, "subm1"),
        block(16, 16, "subm1"),
        block(16, 32, "spconv2", 2, 1, "spconv"), block(32, 32, "subm2"), block(32, 32, "subm2"),
        block(32, 64, "spconv3", 2, 1, "spconv"), block(64, 64, "subm3"), block(64, 64, "subm3"),
        block(64, 64, "spconv4", 2, (0, 1, 1), "spconv"), block(64, 64, "subm4"), block(64, 64, "subm4"),
        block(64, 128, "spconv_down2", (2, 1, 1), 0, "spconv", (3, 1, 1)),
    )


def implicit_gemm(features: torch.Tensor, weight: torch.Tensor, table: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """The alternative kernel (for comparison only): gather (N_out, K * C_in) with zero rows for
    missing neighbours and multiply by the (K * C_in, C_out) weight, in row chunks."""
    n_in, c_in = features.shape
    c_out, kvol = weight.shape[0], table.shape[1]
    padded = torch.cat([features, features.new_zeros(1, c_in)])
    idx = torch.where(table < 0, torch.full_like(table, n_in), table)
    w = weight.reshape(c_out, c_in, kvol).permute(2, 1, 0).reshape(kvol * c_in, c_out)
    out = features.new_empty(table.shape[0], c_out)
    for s in range(0, table.shape[0], chunk):
        rows = padded.index_select(0, idx[s:s + chunk].reshape(-1)).view(-1, kvol * c_in)
        torch.mm(rows, w, out=out[s:s + chunk])
    return out


__all__ = ["backbone", "implicit_gemm"]
