"""detbench.sparse against dense torch convolutions (the oracle), plus rule-book edges."""
import itertools

import pytest
import torch
import torch.nn.functional as F

from detbench.sparse import (SparseConv2d, SparseConv3d, SparseConvTensor, SparseInverseConv2d, SparseInverseConv3d,
                             SparseSequential, SubMConv2d, SubMConv3d, ToDense, build_conv_rulebook,
                             build_subm_rulebook, sparse_conv)
from detbench.sparse import modules as sparse_modules

DENSE = {3: F.conv3d, 2: F.conv2d}
DENSE_T = {3: F.conv_transpose3d, 2: F.conv_transpose2d}
SUBM = {3: SubMConv3d, 2: SubMConv2d}
CONV = {3: SparseConv3d, 2: SparseConv2d}
INV = {3: SparseInverseConv3d, 2: SparseInverseConv2d}


def random_sparse(shape, batch_size=2, channels=3, density=0.3, seed=0, empty_batch=None, dtype=torch.float64,
                  corners=True):
    """Random unique sites (always including both grid corners) with random features."""
    g = torch.Generator().manual_seed(seed)
    active = torch.rand((batch_size, *shape), generator=g) < density
    if corners:
        active[(0,) + (0,) * len(shape)] = True
        active[(batch_size - 1,) + tuple(s - 1 for s in shape)] = True
    if empty_batch is not None:
        active[empty_batch] = False
    idx = active.nonzero().to(torch.int32)
    idx = idx[torch.randperm(idx.shape[0], generator=g)]  # unsorted input order
    feats = torch.randn(idx.shape[0], channels, generator=g, dtype=dtype)
    return SparseConvTensor(feats, idx, shape, batch_size)


def gather_dense(dense, indices):
    """(B, C, *S) dense tensor sampled at (N, 1+D) sites -> (N, C)."""
    idx = indices.long()
    return dense.permute(0, *range(2, dense.dim()), 1)[tuple(idx.t())]


def site_set(indices):
    return {tuple(r) for r in indices.tolist()}


def reached_sites(x, kernel, stride, padding, dilation):
    """Sites a dense conv of this geometry makes non-zero from the active sites (all-ones kernel)."""
    ones = torch.zeros((x.batch_size, 1, *x.spatial_shape), dtype=torch.float64)
    ones[tuple(torch.cat([x.indices[:, :1].long(), torch.zeros_like(x.indices[:, :1]).long(),
                          x.indices[:, 1:].long()], 1).t())] = 1.0
    nd = len(x.spatial_shape)
    k = (kernel,) * nd if isinstance(kernel, int) else kernel
    out = DENSE[nd](ones, torch.ones((1, 1, *k), dtype=torch.float64), None, stride, padding, dilation)
    nz = (out[:, 0] > 0.5).nonzero()
    return {tuple(r) for r in nz.tolist()}


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("kernel,dilation", [(3, 1), (1, 1), (3, 2), ((3, 1, 3), 1)])
def test_subm_matches_dense(ndim, kernel, dilation):
    if isinstance(kernel, tuple):
        kernel = kernel[:ndim]
    shape = (5, 6, 7)[:ndim]
    x = random_sparse(shape, seed=ndim)
    conv = SUBM[ndim](3, 4, kernel, dilation=dilation).double()
    y = conv(x)
    assert y.indices is x.indices and y.spatial_shape == list(shape)
    k = conv.kernel_size
    pad = tuple(dilation * (kk - 1) // 2 for kk in k)
    ref = DENSE[ndim](x.dense(), conv.weight, conv.bias, 1, pad, dilation)
    torch.testing.assert_close(y.features, gather_dense(ref, x.indices), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("stride,padding", [(1, 0), (1, 1), (2, 0), (2, 1), ((2, 1, 2), (0, 1, 1))])
def test_strided_conv_matches_dense(ndim, stride, padding):
    if isinstance(stride, tuple):
        stride, padding = stride[:ndim], padding[:ndim]
    shape = (7, 8, 9)[:ndim]
    x = random_sparse(shape, seed=10 + ndim, density=0.2)
    conv = CONV[ndim](3, 5, 3, stride=stride, padding=padding).double()
    y = conv(x)
    ref = DENSE[ndim](x.dense(), conv.weight, conv.bias, stride, padding)
    assert y.spatial_shape == list(ref.shape[2:])
    assert site_set(y.indices) == reached_sites(x, 3, stride, padding, 1)
    assert y.indices.dtype == torch.int32
    torch.testing.assert_close(y.features, gather_dense(ref, y.indices), rtol=1e-10, atol=1e-10)
    # Outside the output sites the dense conv sees only zeros: output equals bias there.
    dense_y = y.dense()
    mask = torch.zeros_like(dense_y[:, :1], dtype=torch.bool)
    mask[tuple(torch.cat([y.indices[:, :1], torch.zeros_like(y.indices[:, :1]), y.indices[:, 1:]], 1)
               .long().t())] = True
    off = (ref - conv.bias.view(1, -1, *([1] * ndim))).detach().masked_select(~mask)
    assert float(off.abs().sum()) < 1e-12


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("stride,padding,dilation", [(2, 1, 1), (2, 0, 1), (1, 1, 2), (3, 1, 1)])
def test_inverse_conv_restores_sites_and_matches_transpose(ndim, stride, padding, dilation):
    shape = (7, 9, 8)[:ndim]
    x = random_sparse(shape, seed=20 + ndim, density=0.25)
    down = CONV[ndim](3, 4, 3, stride=stride, padding=padding, dilation=dilation, indice_key="d1").double()
    subm = SUBM[ndim](4, 4, 3, indice_key="s2").double()
    up = INV[ndim](4, 2, 3, indice_key="d1").double()
    y = subm(down(x))
    z = up(y)
    assert torch.equal(z.indices, x.indices) and z.spatial_shape == x.spatial_shape
    # Oracle: transposed conv of the dense intermediate with the transposed weight.
    dense_y = y.dense()
    k = 3
    base = [(o - 1) * stride - 2 * padding + dilation * (k - 1) + 1 for o in y.spatial_shape]
    out_pad = [s - b for s, b in zip(shape, base)]
    ref = DENSE_T[ndim](dense_y, up.weight.transpose(0, 1), up.bias, stride, padding, out_pad, 1, dilation)
    assert list(ref.shape[2:]) == list(shape)
    torch.testing.assert_close(z.features, gather_dense(ref, x.indices), rtol=1e-10, atol=1e-10)


def test_gradcheck_subm_strided_inverse():
    x = random_sparse((3, 4, 4), batch_size=2, channels=2, density=0.35, seed=3)
    rb_s = build_subm_rulebook(x.indices, x.spatial_shape, 3)
    rb_c = build_conv_rulebook(x.indices, x.spatial_shape, 3, 2, 1)
    rb_i = rb_c.inverse()
    g = torch.Generator().manual_seed(0)
    feats = x.features.clone().requires_grad_(True)
    for rb, cin, cout in [(rb_s, 2, 3), (rb_c, 2, 3), (rb_i, 2, 3)]:
        f_in = feats if rb is not rb_i else torch.randn(rb_i.num_in, cin, dtype=torch.float64, generator=g
                                                        ).requires_grad_(True)
        w = torch.randn(cout, cin, 3, 3, 3, dtype=torch.float64, generator=g, requires_grad=True)
        b = torch.randn(cout, dtype=torch.float64, generator=g, requires_grad=True)
        assert torch.autograd.gradcheck(lambda f, w_, b_, rb=rb: sparse_conv(f, w_, rb, b_), (f_in, w, b))


def test_gradients_match_dense_autograd():
    x = random_sparse((5, 5, 5), channels=3, density=0.3, seed=4)
    conv = SparseConv3d(3, 2, 3, stride=2, padding=1).double()
    feats = x.features.clone().requires_grad_(True)
    y = conv(x.replace_feature(feats))
    g = torch.randn_like(y.features)
    (y.features * g).sum().backward()
    feats_d = x.features.clone().requires_grad_(True)
    w_d = conv.weight.detach().clone().requires_grad_(True)
    xd = x.replace_feature(feats_d).dense()
    ref = gather_dense(F.conv3d(xd, w_d, conv.bias.detach(), 2, 1), y.indices)
    (ref * g).sum().backward()
    torch.testing.assert_close(feats.grad, feats_d.grad)
    torch.testing.assert_close(conv.weight.grad, w_d.grad)


@pytest.mark.parametrize("ndim", [2, 3])
def test_empty_tensor(ndim):
    shape = (4, 5, 6)[:ndim]
    x = SparseConvTensor(torch.zeros(0, 3), torch.zeros(0, ndim + 1, dtype=torch.int32), shape, 2)
    net = SparseSequential(SUBM[ndim](3, 4, 3, indice_key="a"), torch.nn.BatchNorm1d(4), torch.nn.ReLU(),
                           CONV[ndim](4, 5, 3, stride=2, padding=1, indice_key="b"),
                           INV[ndim](5, 6, 3, indice_key="b"))
    net.train()
    y = net(x)
    assert y.features.shape == (0, 6) and y.indices.shape == (0, ndim + 1)
    assert y.spatial_shape == list(shape)
    assert y.dense().shape == (2, 6, *shape) and float(y.dense().abs().sum()) == 0.0
    down = CONV[ndim](3, 5, 3, stride=2, padding=1)(x)
    assert down.features.shape == (0, 5) and down.spatial_shape == [2, 3, 3][:ndim]
    feats = torch.zeros(0, 3, requires_grad=True)
    SUBM[ndim](3, 4, 3)(x.replace_feature(feats)).features.sum().backward()
    assert feats.grad.shape == (0, 3)


def test_batch_element_without_sites_and_single_site():
    x = random_sparse((4, 5, 6), batch_size=3, empty_batch=1, seed=7, corners=False)
    assert not bool((x.indices[:, 0] == 1).any())
    conv = SparseConv3d(3, 2, 3, stride=2, padding=1).double()
    y = conv(x)
    assert not bool((y.indices[:, 0] == 1).any())
    ref = F.conv3d(x.dense(), conv.weight, conv.bias, 2, 1)
    torch.testing.assert_close(y.features, gather_dense(ref, y.indices))
    one = SparseConvTensor(torch.ones(1, 3, dtype=torch.float64), torch.tensor([[0, 3, 4, 5]], dtype=torch.int32),
                           (4, 5, 6), 1)
    s = SubMConv3d(3, 2, 3).double()
    out = s(one)
    torch.testing.assert_close(out.features, (s.weight[:, :, 1, 1, 1].sum(1) + s.bias).unsqueeze(0))


def test_large_grid_int64_keys():
    """Grid with 2.4e10 sites per batch element: keys must not wrap around int32."""
    shape = (2000, 3000, 4000)
    base = torch.tensor([[1, 1999, 2999, 3999], [1, 1998, 2999, 3999], [1, 1999, 2998, 3998],
                         [0, 0, 0, 0], [0, 1, 1, 1], [1, 1000, 1500, 2000], [1, 1000, 1501, 2000]], dtype=torch.int32)
    x = SparseConvTensor(torch.randn(base.shape[0], 2, dtype=torch.float64), base, shape, 2)
    rb = build_subm_rulebook(x.indices, shape, 3)
    table = rb.neighbour_table()
    # Brute force: neighbours by coordinates.
    sites = base.tolist()
    for o, so in enumerate(sites):
        for k, off in enumerate(itertools.product(range(3), repeat=3)):
            want = [i for i, si in enumerate(sites)
                    if si[0] == so[0] and all(si[d + 1] == so[d + 1] + off[d] - 1 for d in range(3))]
            assert table[o, k].item() == (want[0] if want else -1)
    y = SparseConv3d(2, 2, 3, stride=2, padding=1).double()(x)
    assert y.spatial_shape == [1000, 1500, 2000]
    assert site_set(y.indices) >= {(1, 999, 1499, 1999), (0, 0, 0, 0)}
    with pytest.raises(ValueError, match="overflow"):
        build_subm_rulebook(base, (2**30, 2**30, 2**30), 3, batch_size=2)


def test_indice_key_reuse_and_checks(monkeypatch):
    calls = []
    real = sparse_modules.build_subm_rulebook
    monkeypatch.setattr(sparse_modules, "build_subm_rulebook", lambda *a, **k: calls.append(1) or real(*a, **k))
    x = random_sparse((5, 6, 7), seed=5)
    net = SparseSequential(SubMConv3d(3, 4, 3, indice_key="s1"), torch.nn.ReLU(), SubMConv3d(4, 4, 3, indice_key="s1"),
                           SubMConv3d(4, 4, 3, indice_key="s1")).double()
    y = net(x)
    assert len(calls) == 1 and "s1" in y.indice_dict and y.indice_dict is x.indice_dict
    # A new input tensor (new forward pass) builds again.
    net(random_sparse((5, 6, 7), seed=5))
    assert len(calls) == 2
    with pytest.raises(ValueError, match="another geometry"):
        SubMConv3d(3, 4, 5, indice_key="s1").double()(x)
    down = SparseConv3d(3, 3, 3, stride=2, padding=1, indice_key="d").double()(x)
    with pytest.raises(ValueError, match="different input sites"):
        SubMConv3d(3, 3, 3, indice_key="s1").double()(down)
    with pytest.raises(ValueError, match="no rule book"):
        SparseInverseConv3d(3, 3, 3, indice_key="missing").double()(down)
    with pytest.raises(ValueError, match="SubM layer"):
        SparseInverseConv3d(4, 3, 3, indice_key="s1").double()(y)
    with pytest.raises(ValueError, match="not the output sites"):
        SparseInverseConv3d(3, 3, 3, indice_key="d").double()(x)


def test_bad_inputs_raise_clear_errors():
    idx = torch.tensor([[0, 1, 1, 1], [0, 1, 1, 1]], dtype=torch.int32)
    x = SparseConvTensor(torch.randn(2, 3), idx, (4, 4, 4), 1)
    with pytest.raises(ValueError, match="duplicate"):
        SubMConv3d(3, 3, 3)(x)
    with pytest.raises(ValueError, match="column 3 \\(x\\)"):
        SparseConvTensor(torch.randn(1, 3), torch.tensor([[0, 1, 1, 4]]), (4, 4, 4), 1)
    with pytest.raises(ValueError, match="batch"):
        SparseConvTensor(torch.randn(1, 3), torch.tensor([[1, 1, 1, 1]]), (4, 4, 4), 1)
    with pytest.raises(ValueError, match="one feature row per"):
        SparseConvTensor(torch.randn(2, 3), torch.tensor([[0, 1, 1, 1]]), (4, 4, 4), 1)
    with pytest.raises(ValueError, match="padding"):
        SubMConv3d(3, 3, 3, padding=0)
    with pytest.raises(ValueError, match="stride 1"):
        SubMConv3d(3, 3, 3, stride=2)
    with pytest.raises(ValueError, match="input channels"):
        SubMConv3d(4, 3, 3)(random_sparse((4, 4, 4), dtype=torch.float32))
    with pytest.raises(ValueError, match="empty output grid"):
        SparseConv3d(3, 3, 5)(random_sparse((3, 4, 4), dtype=torch.float32))


def test_sequential_bn_relu_dense_roundtrip():
    x = random_sparse((4, 5, 6), channels=3, seed=8, dtype=torch.float32)
    bn = torch.nn.BatchNorm1d(3)
    seq = SparseSequential(bn, torch.nn.ReLU(), ToDense())
    dense = seq(x)
    ref = torch.relu(torch.nn.functional.batch_norm(x.features, None, None, bn.weight, bn.bias, training=True))
    torch.testing.assert_close(gather_dense(dense, x.indices), ref)
    back = SparseConvTensor.from_dense(x.dense())
    assert site_set(back.indices) == site_set(x.indices)
    torch.testing.assert_close(gather_dense(back.dense(), x.indices), x.features)
    named = SparseSequential(conv=SubMConv3d(3, 2, 3), relu=torch.nn.ReLU())
    assert named(x).features.shape == (x.features.shape[0], 2) and hasattr(named, "conv")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    x = random_sparse((6, 7, 8), channels=4, seed=9, dtype=torch.float32)
    net = SparseSequential(SubMConv3d(4, 8, 3, indice_key="a"), torch.nn.ReLU(),
                           SparseConv3d(8, 8, 3, stride=2, padding=1, indice_key="b"),
                           SparseInverseConv3d(8, 4, 3, indice_key="b"))
    y_cpu = net(x)
    net_cuda = net.cuda()
    xc = SparseConvTensor(x.features.cuda(), x.indices.cuda(), x.spatial_shape, x.batch_size)
    y_cuda = net_cuda(xc)
    assert torch.equal(y_cuda.indices.cpu(), y_cpu.indices)
    torch.testing.assert_close(y_cuda.features.cpu(), y_cpu.features, rtol=1e-4, atol=1e-4)
