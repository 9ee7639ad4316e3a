"""The sparse-convolution benchmark (tools/bench_sparse.py): voxelization, rule-book builds, single
sparse layers, a SECOND-style 3D backbone forward and backward, a dense conv3d on a crop against the
sparse conv on the same sites, the implicit-GEMM alternative, and spconv when it is installed.

Times are milliseconds (median and best of `repeats` runs after one warm-up); GFLOP/s count the useful
multiply-adds (one per active (input, output, offset) pair and channel pair; one multiply-add = 2 FLOP).
"""
from __future__ import annotations

import math
import platform
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from detbench import runtime
from detbench.ops.voxelize import dynamic_voxelize, scatter_mean, unique_voxels, voxel_grid_size, voxelize
from detbench.sparse import (RuleBook, SparseConv3d, SparseConvTensor, SubMConv3d, build_conv_rulebook,
                             build_subm_rulebook, sparse_conv)
from detbench.sparse.bench import backbone, implicit_gemm
from detbench.utils.bench import gflops, idle_and_loaded, load_line, ratio, runtime_line, timed

__all__ = ["SparseBenchSettings", "run_sparse_bench", "sparse_bench_markdown"]


@dataclass
class SparseBenchSettings:
    """What the benchmark measures and how often (the options of tools/bench_sparse.py)."""

    voxel_size: list[float] = field(default_factory=lambda: [0.1, 0.1, 0.15])  # metres
    range: list[float] = field(default_factory=lambda: [0.0, -15.0, -1.0, 150.0, 15.0, 4.0])  # metres, ego frame
    max_points: int = 5  # hard voxelization: points per voxel
    seed: int = 0  # weights and random features
    repeats: int = 5  # timed runs per case after one warm-up
    dense_crop_x: float = 30.0  # x extent (metres, from XMIN) of the dense conv3d comparison; 0 skips it
    dense_max_gb: float = 2.0  # skip the dense comparison above this many GB of input + output
    load: int = 0  # also measure beside this many busy-loop processes


@dataclass
class BenchPass:
    """What every case of one pass (idle or loaded) needs: the settings, the device and the sync after a
    timed call, `add` (a row into the pass's table, printed as it comes) and the progress bar."""

    s: SparseBenchSettings
    device: torch.device
    sync: Callable[[], None]
    add: Callable[..., dict]
    steps: tqdm


@dataclass
class Sites:
    """The active voxels of the batched scans: coords (N, 4) int32 (batch, z, y, x), their mean point as the
    features (N, 4) float32, and the sparse spatial shape (Z + 1, Y, X)."""

    coords: torch.Tensor
    feats: torch.Tensor
    spatial: list[int]
    batch_size: int

    @property
    def n(self) -> int:
        return int(self.coords.shape[0])

    def tensor(self, feats: torch.Tensor | None = None) -> SparseConvTensor:
        """The sites as a SparseConvTensor (its own features, or `feats` per site), unchecked."""
        return SparseConvTensor(self.feats if feats is None else feats, self.coords, self.spatial, self.batch_size,
                                check=False)


def _row_adder(rows: list, tag: str) -> Callable[..., dict]:
    """A function that appends a case's row to `rows` and prints it (`tag` before the name)."""
    def add(name, timing, **extra):
        row = {"case": name, **timing, **extra}
        rows.append(row)
        tqdm.write(f"{tag}{name:58s} {timing['ms']:9.2f} ms (best {timing['ms_best']:.2f})"
                   + (f"  {extra['gflops']:.1f} GFLOP/s" if "gflops" in extra else ""))
        return row
    return add


def voxelization_cases(scans: list[np.ndarray], spatial: list[int], run: BenchPass) -> Sites:
    """Hard voxelization (numba) and the dynamic voxelization + scatter-mean of a dynamic VFE (torch); returns the
    hard voxels as sparse sites."""
    s, device = run.s, run.device
    vox = timed(lambda: [voxelize(p, s.voxel_size, s.range, s.max_points, 150000) for p in scans],
                s.repeats, lambda: None)
    hv = [voxelize(p, s.voxel_size, s.range, s.max_points, 150000) for p in scans]
    run.add("hard voxelization (numba, all scans)", vox, voxels=int(sum(len(h.coords) for h in hv)))
    pts_t = [torch.from_numpy(p).to(device) for p in scans]

    def dynamic_mean():
        # Dynamic voxelization + unique voxels + scatter-mean (what a dynamic VFE does), torch path.
        per = [dynamic_voxelize(p, s.voxel_size, s.range) for p in pts_t]
        cc = torch.cat([torch.cat([torch.full_like(c[:, :1], b), c], 1) for b, c in enumerate(per)])
        cc[(cc[:, 1:] < 0).any(1)] = -1
        vc, inv = unique_voxels(cc)
        return scatter_mean(torch.cat(pts_t), inv, vc.shape[0])

    t = timed(dynamic_mean, s.repeats, run.sync)
    run.add("dynamic voxelization + unique + scatter_mean (torch)", t, voxels=int(dynamic_mean().shape[0]))
    run.steps.update()
    coords = torch.cat([torch.cat([torch.full((len(h.coords), 1), b, dtype=torch.int32),
                                   torch.from_numpy(h.coords)], 1) for b, h in enumerate(hv)]).to(device)
    feats = torch.cat([torch.from_numpy(h.voxels.sum(1) / np.maximum(h.num_points, 1)[:, None])
                       for h in hv]).float().to(device)
    return Sites(coords, feats, spatial, len(scans))


def rulebook_cases(sites: Sites, run: BenchPass) -> tuple[RuleBook, RuleBook]:
    """The rule-book builds of a SubM k3 and a strided SparseConv k3 s2 p1; returns both rule books."""
    s, n, b = run.s, sites.n, sites.batch_size
    rb_s = build_subm_rulebook(sites.coords, sites.spatial, 3, batch_size=b)
    t = timed(lambda: build_subm_rulebook(sites.coords, sites.spatial, 3, batch_size=b), s.repeats, run.sync)
    run.add("rule book SubM k3", t, sites_in=n, pairs=rb_s.num_pairs, neighbours_per_site=rb_s.num_pairs / max(n, 1))
    rb_c = build_conv_rulebook(sites.coords, sites.spatial, 3, 2, 1, batch_size=b)
    t = timed(lambda: build_conv_rulebook(sites.coords, sites.spatial, 3, 2, 1, batch_size=b), s.repeats, run.sync)
    run.add("rule book SparseConv k3 s2 p1", t, sites_in=n, sites_out=rb_c.num_out, pairs=rb_c.num_pairs)
    run.steps.update()
    return rb_s, rb_c


@torch.no_grad()
def layer_cases(sites: Sites, rb_s: RuleBook, rb_c: RuleBook, run: BenchPass) -> None:
    """Single layers: compute only (rule book cached), cold (rule book built in the call), and the implicit-GEMM
    alternative of the SubM layer."""
    s, device, n = run.s, run.device, sites.n
    for c in (16, 32):
        f = torch.randn(n, c, device=device)
        w = torch.randn(c, c, 3, 3, 3, device=device) * 0.05
        t = timed(lambda f=f, w=w: sparse_conv(f, w, rb_s), s.repeats, run.sync)
        run.add(f"SubMConv3d {c}->{c} k3 (rule book cached)", t, sites=n, pairs=rb_s.num_pairs,
                gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
        layer = SubMConv3d(c, c, 3, bias=False).to(device)
        t = timed(lambda layer=layer, f=f: layer(sites.tensor(f)), s.repeats, run.sync)
        run.add(f"SubMConv3d {c}->{c} k3 (incl. rule book build)", t, sites=n,
                gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
        run.steps.update()
        table = rb_s.neighbour_table()
        t = timed(lambda f=f, w=w, table=table: implicit_gemm(f, w, table), s.repeats, run.sync)
        run.add(f"  alternative: implicit GEMM {c}->{c} (not used)", t, sites=n,
                gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
        run.steps.update()
    f = torch.randn(n, 16, device=device)
    w = torch.randn(32, 16, 3, 3, 3, device=device) * 0.05
    t = timed(lambda: sparse_conv(f, w, rb_c), s.repeats, run.sync)
    run.add("SparseConv3d 16->32 k3 s2 p1 (rule book cached)", t, sites_in=n, sites_out=rb_c.num_out,
            pairs=rb_c.num_pairs, gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
    layer = SparseConv3d(16, 32, 3, 2, 1, bias=False).to(device)
    t = timed(lambda: layer(sites.tensor(f)), s.repeats, run.sync)
    run.add("SparseConv3d 16->32 k3 s2 p1 (incl. rule book build)", t, sites_in=n, sites_out=rb_c.num_out,
            gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
    run.steps.update()


def _backbone_macs(net: torch.nn.Module, sites: Sites) -> int:
    """Useful multiply-adds of every conv layer of `net`, from the rule books of one forward."""
    total, h = 0, sites.tensor()
    for blk in net:
        conv = blk[0]
        h2 = blk(h)
        total += h.indice_dict[conv.indice_key].num_pairs * conv.in_channels * conv.out_channels
        h = h2
    return total


def backbone_cases(sites: Sites, run: BenchPass) -> None:
    """The SECOND-style 3D backbone forward (eval, no grad) and forward + backward (train)."""
    s, n = run.s, sites.n
    net = backbone(4).to(run.device)
    convs = [m for m in net.modules() if isinstance(m, (SubMConv3d, SparseConv3d))]
    stats: dict = {}

    def run_backbone():
        y = net(sites.tensor())
        stats["keys"] = len(y.indice_dict)
        stats["out_sites"] = int(y.indices.shape[0])
        stats["out_shape"] = y.spatial_shape
        return y

    net.eval()
    with torch.no_grad():
        macs = _backbone_macs(net, sites)
        t = timed(run_backbone, s.repeats, run.sync)
    run.add("SECOND-style backbone forward (eval, no grad)", t, sites_in=n, sites_out=stats["out_sites"],
            out_spatial_shape=stats["out_shape"], conv_layers=len(convs), rule_books_built=stats["keys"],
            gflops=2.0 * macs / (t["ms"] * 1e-3) / 1e9, useful_gflop=2.0 * macs / 1e9)
    run.steps.update()
    net.train()

    def train_step():
        y = run_backbone()
        y.features.square().mean().backward()

    t = timed(train_step, max(1, s.repeats // 2), run.sync)
    run.add("SECOND-style backbone forward + backward (train)", t, sites_in=n, conv_layers=len(convs),
            rule_books_built=stats["keys"], gflops=3 * 2.0 * macs / (t["ms"] * 1e-3) / 1e9)
    net.zero_grad(set_to_none=True)
    run.steps.update()


def dense_crop_cases(sites: Sites, run: BenchPass) -> str | None:
    """A dense conv3d on the crop x in [XMIN, XMIN + dense_crop_x) against the sparse conv on the crop's sites;
    returns why it was skipped (its tensors above dense_max_gb), or None."""
    s, device, spatial, b = run.s, run.device, sites.spatial, sites.batch_size
    nx = min(spatial[2], int(round(s.dense_crop_x / s.voxel_size[0])))
    crop_shape = [spatial[0], spatial[1], nx]
    nbytes = 2 * b * 16 * math.prod(crop_shape) * 4
    if nbytes / 1e9 > s.dense_max_gb:
        return f"needs {nbytes / 1e9:.1f} GB > --dense-max-gb {s.dense_max_gb}"
    cc = sites.coords[sites.coords[:, 3] < nx]
    f = torch.randn(int(cc.shape[0]), 16, device=device)
    w = torch.randn(16, 16, 3, 3, 3, device=device) * 0.05
    xs = SparseConvTensor(f, cc, crop_shape, b, check=False)
    rb_crop = build_subm_rulebook(cc, crop_shape, 3, batch_size=b)
    dense_in = xs.dense()
    with torch.no_grad():
        td = timed(lambda: F.conv3d(dense_in, w, None, 1, 1), max(1, s.repeats // 2), run.sync)
        ts = timed(lambda: sparse_conv(f, w, rb_crop), s.repeats, run.sync)
    dense_macs = b * math.prod(crop_shape) * 27 * 16 * 16
    run.add(f"dense conv3d 16->16 k3 on crop {crop_shape} (x < {nx * s.voxel_size[0]:.0f} m)", td,
            grid_sites=b * math.prod(crop_shape), gflops_total=2.0 * dense_macs / (td["ms"] * 1e-3) / 1e9,
            gflops=gflops(rb_crop.num_pairs, 16, 16, td["ms"]))
    run.add(f"  sparse SubMConv3d 16->16 on the same crop ({int(cc.shape[0])} sites)", ts,
            sites=int(cc.shape[0]), pairs=rb_crop.num_pairs, gflops=gflops(rb_crop.num_pairs, 16, 16, ts["ms"]))
    return None


def measure(scans: list[np.ndarray], spatial: list[int], run: BenchPass, meta: dict) -> None:
    """Every case once, rows through `run.add`, facts about the run (active sites, a skipped dense comparison,
    spconv) into `meta`. Seeded, so the idle and the loaded pass see the same tensors."""
    s = run.s
    torch.manual_seed(s.seed)
    sites = voxelization_cases(scans, spatial, run)
    meta["active_sites"] = sites.n
    SparseConvTensor(sites.feats, sites.coords, spatial, sites.batch_size)  # checks the sites once; timed calls skip
    rb_s, rb_c = rulebook_cases(sites, run)
    layer_cases(sites, rb_s, rb_c, run)
    backbone_cases(sites, run)
    if s.dense_crop_x > 0:
        skipped = dense_crop_cases(sites, run)
        if skipped is not None:
            meta["dense_skipped"] = skipped
    run.steps.update()
    try:  # spconv is optional; this benchmark never installs it
        import spconv.pytorch as spconv

        meta["spconv"] = _bench_spconv(spconv, sites.feats, sites.coords, spatial, sites.batch_size, s, run.sync,
                                       sites.n, rb_s, run.add)
    except ImportError:
        meta["spconv"] = "not installed"
        tqdm.write("spconv: not installed")
    run.steps.update()


def run_sparse_bench(scans: list[np.ndarray], source: str, s: SparseBenchSettings,
                     device: torch.device) -> dict:
    """Every case on the voxels of `scans` (batched), idle and, with `s.load`, beside busy processes: the
    results dict of bench_sparse.json. ValueError for a voxel size and range that make no grid."""
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    torch.manual_seed(s.seed)
    grid_xyz = voxel_grid_size(s.voxel_size, s.range)
    # OpenPCDet adds one z layer so that the strided z sizes divide evenly: (Z + 1, Y, X).
    spatial = [grid_xyz[2] + 1, grid_xyz[1], grid_xyz[0]]
    results: dict = {
        "source": source, "scans": len(scans), "points": [int(len(p)) for p in scans],
        "voxel_size_m": s.voxel_size, "range_m": s.range, "grid_xyz": list(grid_xyz),
        "spatial_shape_zyx": spatial, "threads": torch.get_num_threads(), "device": str(device),
        "torch": torch.__version__, "cpu": platform.processor() or platform.machine(),
        "repeats": s.repeats, "flop_convention": "GFLOP/s = 2 * useful multiply-adds / time "
        "(forward + backward rows count 3x the forward multiply-adds)",
        "cases": [],
    }
    steps = tqdm(total=11 * (2 if s.load else 1), desc="bench_sparse", unit="case")

    def one_pass(tag: str) -> list[dict]:
        rows: list = []
        measure(scans, spatial, BenchPass(s, device, sync, _row_adder(rows, tag), steps), results)
        return rows

    tags = iter(["", "[loaded] "])
    idle, loaded, load_info = idle_and_loaded(lambda: one_pass(next(tags)), s.load)
    steps.close()
    results["cases"] = idle
    if loaded is not None:
        results["load"] = load_info
        by_case = {lrow["case"]: lrow for lrow in loaded}
        for row in idle:
            lrow = by_case[row["case"]]
            row.update(loaded_ms=lrow["ms"], loaded_ms_best=lrow["ms_best"], loaded_ratio=ratio(lrow["ms"], row["ms"]))
    results["runtime"] = runtime.describe()
    return results


def _bench_spconv(spconv, feats, coords, spatial, batch_size: int, s: SparseBenchSettings, sync, n_sites, rb_s,
                   add) -> dict:
    """Time spconv's SubMConv3d on the same sites (only when spconv happens to be installed)."""
    out = {}
    with torch.no_grad():
        for c in (16, 32):
            f = torch.randn(n_sites, c, device=feats.device)
            layer = spconv.SubMConv3d(c, c, 3, bias=False, indice_key="s").to(feats.device)
            x = spconv.SparseConvTensor(f, coords, spatial, batch_size)
            layer(x)  # builds and caches the pairs under "s"
            t = timed(lambda layer=layer, x=x: layer(x), s.repeats, sync)
            row = add(f"spconv SubMConv3d {c}->{c} k3 (pairs cached)", t, sites=n_sites,
                      gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
            out[f"subm{c}_ms"] = row["ms"]
            t = timed(lambda layer=layer, f=f: layer(spconv.SparseConvTensor(f, coords, spatial, batch_size)),
                      s.repeats, sync)
            row = add(f"spconv SubMConv3d {c}->{c} k3 (incl. pair build)", t, sites=n_sites,
                      gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
            out[f"subm{c}_incl_pairs_ms"] = row["ms"]
    return out


def sparse_bench_markdown(r: dict) -> str:
    """Human-readable report of the results dict."""
    lines = [
        "# Sparse convolution benchmark (tools/bench_sparse.py)", "",
        f"- scan source: {r['source']}",
        f"- scans (batch): {r['scans']}, points per scan: {r['points']}",
        f"- voxel size {r['voxel_size_m']} m, range {r['range_m']} m, grid (X, Y, Z) {r['grid_xyz']}, "
        f"sparse spatial_shape (Z+1, Y, X) {r['spatial_shape_zyx']}",
        f"- active sites (voxels): {r.get('active_sites')}",
        f"- device {r['device']}, torch threads {r['threads']}, torch {r['torch']}, {r['repeats']} timed runs "
        "after a warm-up; times in milliseconds (median, best)",
        f"- {r['flop_convention']}; useful multiply-adds = rule-book pairs x C_in x C_out",
        f"- spconv: {r['spconv'] if isinstance(r['spconv'], str) else 'installed, see table'}",
    ]
    if "dense_skipped" in r:
        lines.append(f"- dense comparison skipped: {r['dense_skipped']}")
    if "runtime" in r:
        lines.append(f"- thread runtimes: {runtime_line(r['runtime'])}")
    load = r.get("load")
    if load:
        lines.append(f"- loaded: each case again beside {load_line(load)}; 'x idle' = loaded median / idle median")
    timing = ["case", "median ms", "best ms"] + (["loaded median ms", "x idle"] if load else [])
    lines += ["", "| " + " | ".join(timing + ["GFLOP/s (useful)", "details"]) + " |",
              "|---|" + "---:|" * (len(timing)) + "---|"]
    skip = ("case", "ms", "ms_best", "gflops", "loaded_ms", "loaded_ms_best", "loaded_ratio")
    for row in r["cases"]:
        details = ", ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}"
                            for k, v in row.items() if k not in skip)
        g = f"{row['gflops']:.1f}" if "gflops" in row else ""
        cells = [row["case"].strip(), f"{row['ms']:.2f}", f"{row['ms_best']:.2f}"]
        if load:
            cells += [f"{row['loaded_ms']:.2f}", f"{row['loaded_ratio']:.2f}"]
        lines.append("| " + " | ".join(cells + [g, details]) + " |")
    return "\n".join(lines) + "\n"

