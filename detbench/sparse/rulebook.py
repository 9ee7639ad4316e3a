"""Rule books: which input site feeds which output site through which kernel offset.

A rule book holds, for every kernel offset ``k`` (row-major order of the kernel dims, the
order of the trailing dims of a torch ``nn.Conv3d`` weight (out, in, kz, ky, kx)), the pairs
``(in_row, out_row)`` such that output site ``out_row`` reads input site ``in_row`` through
that offset. The convolution is then, per offset, a gather of input rows, one matrix
multiply and a scatter-add into the output rows (`detbench.sparse.functional`).

Geometry follows ``torch.nn.functional.conv3d`` (cross-correlation): output site ``o`` reads
input site ``i = o * stride - padding + k * dilation`` in every spatial dim. A submanifold
("SubM") convolution has stride 1 and padding ``dilation * (kernel - 1) / 2``; its output
sites are its input sites. A regular ("strided") sparse convolution outputs every site that
a dense convolution of the same geometry reaches from at least one active input site.

Neighbours are found with sorted int64 linear keys (batch-major) and ``torch.searchsorted``;
there is no Python loop over sites, and every tensor stays on the device of the indices.
"""
from __future__ import annotations

import itertools
import math
import numbers
from dataclasses import dataclass
from collections.abc import Sequence

import torch

_INT64_MAX = 2**63 - 1


def _tuple(value, ndim: int, name: str) -> tuple[int, ...]:
    """Expand an int or a sequence to an ``ndim``-tuple of ints; reject bad lengths."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        return (int(value),) * ndim
    try:
        out = tuple(int(v) for v in value)
    except TypeError:
        raise ValueError(f"{name} must be an int or {ndim} ints, got {value!r}") from None
    if len(out) != ndim:
        raise ValueError(f"{name} must be an int or {ndim} ints, got {value!r}")
    return out


@dataclass
class RuleBook:
    """Input/output pairs of one sparse convolution geometry on one set of input sites.

    Attributes:
        in_indices: (N_in, 1+D) int32 input sites (batch, z, y, x) / (batch, y, x).
        out_indices: (N_out, 1+D) int32 output sites (the same object as ``in_indices`` for SubM).
        in_shape / out_shape: spatial grid (Z, Y, X) / (Y, X) of input and output, voxels.
        kernel_size, stride, padding, dilation: D-tuples of ints, as in ``nn.Conv3d``.
        subm: True for a submanifold convolution.
        pair_in / pair_out: (P,) int64 input and output rows of all pairs, grouped by offset
            (offset 0 first). For SubM with an odd kernel the centre offset is left out
            (it pairs every site with itself; see ``identity_offset``).
        counts: K Python ints, the number of pairs of each offset (0 for the omitted centre).
        identity_offset: the offset whose pairs are ``(i, i)`` for every site (SubM with odd
            kernel: K // 2), else -1.
        batch_size: number of batch elements the sites belong to.
    """

    in_indices: torch.Tensor
    out_indices: torch.Tensor
    in_shape: tuple[int, ...]
    out_shape: tuple[int, ...]
    kernel_size: tuple[int, ...]
    stride: tuple[int, ...]
    padding: tuple[int, ...]
    dilation: tuple[int, ...]
    subm: bool
    pair_in: torch.Tensor
    pair_out: torch.Tensor
    counts: list[int]
    identity_offset: int
    batch_size: int

    @property
    def kernel_volume(self) -> int:
        """K, the number of kernel offsets."""
        return math.prod(self.kernel_size)

    @property
    def num_in(self) -> int:
        """N_in, number of input sites."""
        return int(self.in_indices.shape[0])

    @property
    def num_out(self) -> int:
        """N_out, number of output sites."""
        return int(self.out_indices.shape[0])

    @property
    def num_pairs(self) -> int:
        """Total (input, output, offset) pairs including an identity centre: the useful
        multiply-adds of the convolution per (in_channel, out_channel)."""
        return sum(self.counts) + (self.num_in if self.identity_offset >= 0 else 0)

    def offset_pairs(self) -> list[tuple[int, torch.Tensor, torch.Tensor]]:
        """Non-empty offsets as ``(k, in_rows (n_k,), out_rows (n_k,))`` views, identity centre excluded."""
        out, start = [], 0
        for k, n in enumerate(self.counts):
            if n:
                out.append((k, self.pair_in[start:start + n], self.pair_out[start:start + n]))
            start += n
        return out

    def geometry(self) -> tuple:
        """Hashable description of the convolution geometry (for indice_key checks)."""
        return (self.kernel_size, self.stride, self.padding, self.dilation, self.subm)

    def inverse(self) -> RuleBook:
        """Rule book of the inverse convolution: output sites become input sites and back.

        The inverse of a strided convolution maps its output sites back onto exactly its
        input sites with the same offset numbering (the pairing of ``conv_transpose``).
        """
        if self.subm:
            raise ValueError("a SubM rule book has no inverse; SparseInverseConv needs the indice_key "
                             "of a SparseConv (strided) layer")
        return RuleBook(self.out_indices, self.in_indices, self.out_shape, self.in_shape, self.kernel_size,
                        self.stride, self.padding, self.dilation, False, self.pair_out, self.pair_in,
                        list(self.counts), -1, self.batch_size)

    def neighbour_table(self) -> torch.Tensor:
        """(N_out, K) int64: input row read by each output row through each offset, -1 for none.

        A dense view of the pairs for inspection and tests; the convolution does not use it.
        """
        k = self.kernel_volume
        table = torch.full((self.num_out, k), -1, dtype=torch.int64, device=self.pair_in.device)
        offs = torch.repeat_interleave(torch.arange(k, device=table.device),
                                       torch.tensor(self.counts, device=table.device))
        table[self.pair_out, offs] = self.pair_in
        if self.identity_offset >= 0:
            table[:, self.identity_offset] = torch.arange(self.num_out, device=table.device)
        return table


def linear_keys(indices: torch.Tensor, spatial_shape: Sequence[int],
                shift: Sequence[int] | None = None) -> torch.Tensor:
    """Batch-major int64 keys of sites.

    Args:
        indices: (N, 1+D) integer sites (batch, z, y, x) / (batch, y, x).
        spatial_shape: D ints, the grid the keys enumerate (Z, Y, X) / (Y, X).
        shift: optional D ints added to the coordinates first (used for padded grids).

    Returns:
        (N,) int64 ``((b * Z + z) * Y + y) * X + x``; sorting keys sorts sites batch-major.
    """
    idx = indices.long()
    key = idx[:, 0]
    for d, size in enumerate(spatial_shape):
        col = idx[:, d + 1] if shift is None else idx[:, d + 1] + int(shift[d])
        key = key * int(size) + col
    return key


def decode_keys(keys: torch.Tensor, spatial_shape: Sequence[int]) -> torch.Tensor:
    """Inverse of `linear_keys` (no shift): (N,) int64 keys -> (N, 1+D) int32 sites."""
    cols = []
    rest = keys
    for size in reversed(list(spatial_shape)):
        cols.append(torch.remainder(rest, int(size)))
        rest = torch.div(rest, int(size), rounding_mode="floor")
    cols.append(rest)
    return torch.stack(cols[::-1], dim=1).to(torch.int32)


def _check_key_range(batch_size: int, spatial_shape: Sequence[int]) -> None:
    total = max(int(batch_size), 1) * math.prod(int(s) for s in spatial_shape)
    if total > _INT64_MAX:
        raise ValueError(f"batch_size {batch_size} x spatial_shape {tuple(spatial_shape)} has more than 2**63 "
                         "sites; linear keys would overflow int64. Use a coarser grid (larger voxels).")


def validate_indices(indices: torch.Tensor, spatial_shape: Sequence[int], batch_size: int) -> None:
    """Raise ValueError unless ``indices`` are (N, 1+D) integer sites inside the grid.

    Checks dtype, shape, the batch column in [0, batch_size) and every coordinate in
    [0, spatial_shape[d]). Duplicate sites are rejected when the rule book sorts the keys.
    """
    ndim = len(spatial_shape)
    names = ["batch"] + (["z", "y", "x"] if ndim == 3 else ["y", "x"] if ndim == 2 else [f"d{i}" for i in range(ndim)])
    if indices.dim() != 2 or indices.shape[1] != ndim + 1:
        raise ValueError(f"indices must have shape (N, {ndim + 1}) = ({', '.join(names)}) for spatial_shape "
                         f"{tuple(spatial_shape)}, got {tuple(indices.shape)}")
    if indices.dtype.is_floating_point or indices.dtype.is_complex or indices.dtype == torch.bool:
        raise ValueError(f"indices must be an integer tensor (int32), got {indices.dtype}")
    if indices.shape[0] == 0:
        return
    lo = indices.min(dim=0).values.tolist()
    hi = indices.max(dim=0).values.tolist()
    limits = [int(batch_size)] + [int(s) for s in spatial_shape]
    for d in range(ndim + 1):
        if lo[d] < 0 or hi[d] >= limits[d]:
            raise ValueError(f"indices column {d} ({names[d]}) has values in [{lo[d]}, {hi[d]}] but must lie in "
                             f"[0, {limits[d] - 1}] (batch_size={batch_size}, spatial_shape={tuple(spatial_shape)}); "
                             "fix the voxel coordinates or enlarge spatial_shape / batch_size")


def _sort_unique(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sort keys ascending (returns sorted keys and permutation); reject duplicate sites."""
    sorted_keys, order = torch.sort(keys)
    if sorted_keys.numel() > 1 and bool((sorted_keys[1:] == sorted_keys[:-1]).any()):
        raise ValueError("indices contain duplicate sites; every active site must appear once "
                         "(merge duplicate voxels, e.g. with detbench.ops.unique_voxels, before building "
                         "a SparseConvTensor)")
    return sorted_keys, order


def _kernel_offsets(kernel_size: Sequence[int]) -> list[tuple[int, ...]]:
    """Kernel positions in row-major order (the weight's trailing-dims order)."""
    return list(itertools.product(*[range(k) for k in kernel_size]))


def _search_offsets(sorted_keys: torch.Tensor, padded: Sequence[int], ks: Sequence[int], dil: Sequence[int],
                    pad: Sequence[int], num_offsets: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Find the neighbour of every site through kernel offsets 0 .. num_offsets-1.

    Returns ``found`` (H, N) bool and ``pos`` (H, N) int64 (row in ``sorted_keys`` of the
    neighbour where found), both in sorted-site order.

    Offsets that differ only in the last (x) dim, with dilation 1 there, ask for consecutive
    keys; one ``searchsorted`` per such row of offsets suffices: the neighbour at x + 1 sits
    at the position of the neighbour at x plus one if that one was present.
    """
    n = sorted_keys.shape[0]
    ndim = len(ks)
    strides = [math.prod(padded[d + 1:]) for d in range(ndim)]
    offsets = _kernel_offsets(ks)[:num_offsets]
    deltas = [sum((o * dl - p) * s for o, dl, p, s in zip(off, dil, pad, strides)) for off in offsets]
    found = torch.empty((num_offsets, n), dtype=torch.bool, device=sorted_keys.device)
    pos = torch.empty((num_offsets, n), dtype=torch.int64, device=sorted_keys.device)
    k = 0
    while k < num_offsets:
        end = k + 1
        if dil[-1] == 1:  # extend the run of offsets that share all but the last dim
            while end < num_offsets and offsets[end][:-1] == offsets[k][:-1]:
                end += 1
        p = torch.searchsorted(sorted_keys, sorted_keys + deltas[k])
        for j in range(k, end):
            pc = p.clamp_max(n - 1)
            f = sorted_keys[pc] == sorted_keys + deltas[j]
            found[j], pos[j] = f, pc
            if j + 1 < end:
                p = p + f
        k = end
    return found, pos


def build_subm_rulebook(indices: torch.Tensor, spatial_shape: Sequence[int], kernel_size, dilation=1,
                        batch_size: int | None = None) -> RuleBook:
    """Rule book of a submanifold convolution (output sites = input sites).

    Args:
        indices: (N, 1+D) int32 active sites, unique.
        spatial_shape: D ints, the grid (Z, Y, X) / (Y, X).
        kernel_size, dilation: int or D ints; ``dilation * (kernel_size - 1)`` must be even
            in every dim so that the output grid equals the input grid (odd kernels always are).
        batch_size: batch elements (for the key range); defaults to ``max(batch) + 1``.

    Returns:
        RuleBook whose ``out_indices`` is ``indices`` itself.

    Keys are taken on the grid padded by the kernel radius, so a neighbour outside the grid
    lands in the (empty) padding and needs no bounds check; only half of the offsets are
    searched, because a pair (i -> o, offset k) implies (o -> i, offset K-1-k).
    """
    ndim = len(spatial_shape)
    ks = _tuple(kernel_size, ndim, "kernel_size")
    dil = _tuple(dilation, ndim, "dilation")
    for k, d in zip(ks, dil):
        if k < 1 or d < 1:
            raise ValueError(f"kernel_size and dilation must be >= 1, got kernel_size={ks}, dilation={dil}")
        if (d * (k - 1)) % 2:
            raise ValueError(f"SubM convolution needs dilation * (kernel_size - 1) even in every dim so that the "
                             f"output grid equals the input grid; got kernel_size={ks}, dilation={dil} "
                             "(use an odd kernel size)")
    pad = tuple(d * (k - 1) // 2 for k, d in zip(ks, dil))
    device = indices.device
    n = int(indices.shape[0])
    kvol = math.prod(ks)
    if batch_size is None:
        batch_size = int(indices[:, 0].max()) + 1 if n else 1
    padded = tuple(int(s) + 2 * p for s, p in zip(spatial_shape, pad))
    _check_key_range(batch_size, padded)
    half = kvol // 2
    identity = half if kvol % 2 else -1
    counts = [0] * kvol
    empty = torch.zeros(0, dtype=torch.int64, device=device)
    pair_in, pair_out = empty, empty
    if n and half:
        keys = linear_keys(indices, padded, shift=pad)
        sorted_keys, order = _sort_unique(keys)
        found, pos = _search_offsets(sorted_keys, padded, ks, dil, pad, half)
        k_ids, o_sorted = found.nonzero(as_tuple=True)  # grouped by offset
        i_sorted = pos[k_ids, o_sorted]
        o_rows, i_rows = order[o_sorted], order[i_sorted]
        first = found.sum(dim=1).tolist()
        # Offsets 0..H-1 as found; offsets K-1-k (k = H-1..0) are the same pairs swapped,
        # and flipping the concatenation reverses the order of the groups.
        pair_in = torch.cat([i_rows, o_rows.flip(0)])
        pair_out = torch.cat([o_rows, i_rows.flip(0)])
        counts = first + ([0] if identity >= 0 else []) + first[::-1]
    elif n:
        _sort_unique(linear_keys(indices, padded, shift=pad))  # duplicate check only (1x1 kernel)
    shape = tuple(int(s) for s in spatial_shape)
    return RuleBook(indices, indices, shape, shape, ks, (1,) * ndim, pad, dil, True, pair_in, pair_out,
                    counts, identity, int(batch_size))


def conv_output_shape(spatial_shape: Sequence[int], kernel_size, stride=1, padding=0, dilation=1) -> tuple[int, ...]:
    """Output grid of a convolution, per dim ``(in + 2p - d (k - 1) - 1) // s + 1`` (as ``nn.Conv3d``).

    Raises ValueError when a dim would be empty.
    """
    ndim = len(spatial_shape)
    ks, st = _tuple(kernel_size, ndim, "kernel_size"), _tuple(stride, ndim, "stride")
    pd, dl = _tuple(padding, ndim, "padding"), _tuple(dilation, ndim, "dilation")
    out = tuple((int(i) + 2 * p - d * (k - 1) - 1) // s + 1 for i, k, s, p, d in zip(spatial_shape, ks, st, pd, dl))
    if any(o < 1 for o in out):
        raise ValueError(f"convolution with kernel_size={ks}, stride={st}, padding={pd}, dilation={dl} "
                         f"on spatial_shape {tuple(spatial_shape)} gives an empty output grid {out}; "
                         f"reduce the kernel or add padding")
    return out


def build_conv_rulebook(indices: torch.Tensor, spatial_shape: Sequence[int], kernel_size, stride=1, padding=0,
                        dilation=1, batch_size: int | None = None) -> RuleBook:
    """Rule book of a regular (possibly strided) sparse convolution.

    Output sites are all sites of the output grid that a dense convolution of the same
    geometry reaches from at least one active input site, sorted batch-major.

    Args:
        indices: (N, 1+D) int32 active input sites, unique; spatial_shape: D ints.
        kernel_size, stride, padding, dilation: int or D ints, as ``nn.Conv3d``.
        batch_size: batch elements (for the key range); defaults to ``max(batch) + 1``.

    Returns:
        RuleBook with ``out_indices`` (N_out, 1+D) int32 on the grid `conv_output_shape`.
    """
    ndim = len(spatial_shape)
    ks, st = _tuple(kernel_size, ndim, "kernel_size"), _tuple(stride, ndim, "stride")
    pd, dl = _tuple(padding, ndim, "padding"), _tuple(dilation, ndim, "dilation")
    if min(ks) < 1 or min(st) < 1 or min(dl) < 1 or min(pd) < 0:
        raise ValueError(f"need kernel_size, stride, dilation >= 1 and padding >= 0; got kernel_size={ks}, "
                         f"stride={st}, padding={pd}, dilation={dl}")
    out_shape = conv_output_shape(spatial_shape, ks, st, pd, dl)
    device = indices.device
    n = int(indices.shape[0])
    kvol = math.prod(ks)
    if batch_size is None:
        batch_size = int(indices[:, 0].max()) + 1 if n else 1
    _check_key_range(batch_size, spatial_shape)
    _check_key_range(batch_size, out_shape)
    shape = tuple(int(s) for s in spatial_shape)
    empty = torch.zeros(0, dtype=torch.int64, device=device)
    if n == 0:
        return RuleBook(indices, torch.zeros((0, ndim + 1), dtype=torch.int32, device=device), shape, out_shape,
                        ks, st, pd, dl, False, empty, empty, [0] * kvol, -1, int(batch_size))
    if n > 1:
        _sort_unique(linear_keys(indices, spatial_shape))
    # Separable per dim: input coordinate c reaches output o = (c + p - k d) / s when divisible
    # and inside the output grid. valid (N, K) and the output key (N, K) are outer sums/products.
    out_strides = [math.prod(out_shape[d + 1:]) for d in range(ndim)]
    valid = None
    okey = indices[:, 0].long() * math.prod(out_shape)
    okey = okey.view(n, *([1] * ndim))
    coords = indices[:, 1:].long()
    for d in range(ndim):
        kpos = torch.arange(ks[d], device=device, dtype=torch.int64) * dl[d]
        num = coords[:, d:d + 1] + pd[d] - kpos.unsqueeze(0)  # (N, k_d)
        o = torch.div(num, st[d], rounding_mode="floor")
        ok = (o * st[d] == num) & (o >= 0) & (o < out_shape[d])
        view = [n] + [1] * ndim
        view[d + 1] = ks[d]
        valid = ok.view(view) if valid is None else valid & ok.view(view)
        okey = okey + (o * out_strides[d]).view(view)
    valid = valid.reshape(n, kvol)
    okey = okey.reshape(n, kvol)
    k_ids, i_rows = valid.t().nonzero(as_tuple=True)  # grouped by offset
    uniq, o_rows = torch.unique(okey[i_rows, k_ids], sorted=True, return_inverse=True)
    counts = torch.bincount(k_ids, minlength=kvol).tolist()
    return RuleBook(indices, decode_keys(uniq, out_shape), shape, out_shape, ks, st, pd, dl, False,
                    i_rows, o_rows, counts, -1, int(batch_size))
