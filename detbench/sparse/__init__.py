"""Sparse convolution in plain torch with spconv's names (no compiled extension).

>>> import torch
>>> from detbench.sparse import SparseConvTensor, SubMConv3d, SparseConv3d, SparseSequential
>>> x = SparseConvTensor(torch.randn(2, 4), torch.tensor([[0, 1, 2, 3], [0, 1, 2, 4]], dtype=torch.int32),
...                      spatial_shape=(4, 8, 8), batch_size=1)
>>> net = SparseSequential(SubMConv3d(4, 8, 3, indice_key="subm1"), torch.nn.BatchNorm1d(8), torch.nn.ReLU(),
...                        SparseConv3d(8, 16, 3, stride=2, padding=1, indice_key="down1"))
>>> y = net(x)
>>> y.spatial_shape, y.features.shape[1]
([2, 4, 4], 16)

Sites are int32 (batch, z, y, x) / (batch, y, x); spatial_shape is (Z, Y, X) / (Y, X);
weights are (C_out, C_in, *kernel) as torch's nn.Conv3d / nn.Conv2d. See
`detbench.sparse.rulebook` for the rule-book algorithm and `detbench.sparse.functional`
for the gather-matmul-scatter kernel.
"""
from .functional import sparse_conv
from .modules import (SparseConv2d, SparseConv3d, SparseConvolution, SparseInverseConv2d, SparseInverseConv3d,
                      SafeBatchNorm1d, SparseModule, SparseSequential, SubMConv2d, SubMConv3d, ToDense,
                      batch_norm_few_rows)
from .rulebook import RuleBook, build_conv_rulebook, build_subm_rulebook, conv_output_shape
from .tensor import SparseConvTensor

__all__ = [
    "SparseConvTensor", "SubMConv3d", "SparseConv3d", "SparseInverseConv3d", "SubMConv2d", "SparseConv2d",
    "SparseInverseConv2d", "SparseSequential", "SafeBatchNorm1d", "batch_norm_few_rows", "SparseModule",
    "SparseConvolution", "ToDense", "RuleBook",
    "build_subm_rulebook", "build_conv_rulebook", "conv_output_shape", "sparse_conv",
]
