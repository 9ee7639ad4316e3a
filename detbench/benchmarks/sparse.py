"""The sparse-convolution benchmark (tools/bench_sparse.py): voxelization, rule-book builds, single
sparse layers, a SECOND-style 3D backbone forward and backward, a dense conv3d on a crop against the
sparse conv on the same sites, the implicit-GEMM alternative, and spconv when it is installed.

Times are milliseconds (median and best of `repeats` runs after one warm-up); GFLOP/s count the useful
multiply-adds (one per active (input, output, offset) pair and channel pair; one multiply-add = 2 FLOP).
"""
from __future__ import annotations

import math
import platform
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from detbench import runtime
from detbench.ops.voxelize import dynamic_voxelize, scatter_mean, unique_voxels, voxel_grid_size, voxelize
from detbench.sparse import (SparseConv3d, SparseConvTensor, SubMConv3d, build_conv_rulebook, build_subm_rulebook,
                             sparse_conv)
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


def run_sparse_bench(scans: list[np.ndarray], source: str, s: SparseBenchSettings,
                     device: torch.device) -> dict:
    """Every case on the voxels of `scans` (batched), idle and, with `s.load`, beside busy processes: the
    results dict of bench_sparse.json. ValueError for a voxel size and range that make no grid."""
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    torch.manual_seed(s.seed)
    grid_xyz = voxel_grid_size(s.voxel_size, s.range)
    n_scans = len(scans)
    # OpenPCDet adds one z layer so that the strided z sizes divide evenly: (Z + 1, Y, X).
    spatial = [grid_xyz[2] + 1, grid_xyz[1], grid_xyz[0]]
    results: dict = {
        "source": source, "scans": n_scans, "points": [int(len(p)) for p in scans],
        "voxel_size_m": s.voxel_size, "range_m": s.range, "grid_xyz": list(grid_xyz),
        "spatial_shape_zyx": spatial, "threads": torch.get_num_threads(), "device": str(device),
        "torch": torch.__version__, "cpu": platform.processor() or platform.machine(),
        "repeats": s.repeats, "flop_convention": "GFLOP/s = 2 * useful multiply-adds / time "
        "(forward + backward rows count 3x the forward multiply-adds)",
        "cases": [],
    }

    def adder(rows: list, tag: str):
        def add(name, timing, **extra):
            row = {"case": name, **timing, **extra}
            rows.append(row)
            tqdm.write(f"{tag}{name:58s} {timing['ms']:9.2f} ms (best {timing['ms_best']:.2f})"
                       + (f"  {extra['gflops']:.1f} GFLOP/s" if "gflops" in extra else ""))
            return row
        return add

    def measure(add, steps, meta: dict) -> None:
        """Every case once, rows through `add`, facts about the run into `meta` (run idle, then
        again beside --load busy processes). Seeded, so both runs see the same tensors."""
        torch.manual_seed(s.seed)
        # Voxelization (numba) and the mean-VFE input features.
        vox = timed(lambda: [voxelize(p, s.voxel_size, s.range, s.max_points, 150000) for p in scans],
                    s.repeats, lambda: None)
        hv = [voxelize(p, s.voxel_size, s.range, s.max_points, 150000) for p in scans]
        add("hard voxelization (numba, all scans)", vox, voxels=int(sum(len(h.coords) for h in hv)))
        pts_t = [torch.from_numpy(p).to(device) for p in scans]

        def dynamic_mean():
            # Dynamic voxelization + unique voxels + scatter-mean (what a dynamic VFE does), torch path.
            per = [dynamic_voxelize(p, s.voxel_size, s.range) for p in pts_t]
            cc = torch.cat([torch.cat([torch.full_like(c[:, :1], b), c], 1) for b, c in enumerate(per)])
            cc[(cc[:, 1:] < 0).any(1)] = -1
            vc, inv = unique_voxels(cc)
            return scatter_mean(torch.cat(pts_t), inv, vc.shape[0])

        t = timed(dynamic_mean, s.repeats, sync)
        add("dynamic voxelization + unique + scatter_mean (torch)", t, voxels=int(dynamic_mean().shape[0]))
        steps.update()
        coords = torch.cat([torch.cat([torch.full((len(h.coords), 1), b, dtype=torch.int32),
                                       torch.from_numpy(h.coords)], 1) for b, h in enumerate(hv)]).to(device)
        feats = torch.cat([torch.from_numpy(h.voxels.sum(1) / np.maximum(h.num_points, 1)[:, None])
                           for h in hv]).float().to(device)
        n_sites = int(coords.shape[0])
        meta["active_sites"] = n_sites
        SparseConvTensor(feats, coords, spatial, n_scans)  # checks the sites once; the timed calls skip the check

        # Rule books.
        rb_s = build_subm_rulebook(coords, spatial, 3, batch_size=n_scans)
        t = timed(lambda: build_subm_rulebook(coords, spatial, 3, batch_size=n_scans), s.repeats, sync)
        add("rule book SubM k3", t, sites_in=n_sites, pairs=rb_s.num_pairs,
            neighbours_per_site=rb_s.num_pairs / max(n_sites, 1))
        rb_c = build_conv_rulebook(coords, spatial, 3, 2, 1, batch_size=n_scans)
        t = timed(lambda: build_conv_rulebook(coords, spatial, 3, 2, 1, batch_size=n_scans), s.repeats, sync)
        add("rule book SparseConv k3 s2 p1", t, sites_in=n_sites, sites_out=rb_c.num_out, pairs=rb_c.num_pairs)
        steps.update()

        # Single layers: compute only (cached rule book), and cold (rule book built in the call).
        with torch.no_grad():
            for c in (16, 32):
                f = torch.randn(n_sites, c, device=device)
                w = torch.randn(c, c, 3, 3, 3, device=device) * 0.05
                t = timed(lambda f=f, w=w: sparse_conv(f, w, rb_s), s.repeats, sync)
                add(f"SubMConv3d {c}->{c} k3 (rule book cached)", t, sites=n_sites, pairs=rb_s.num_pairs,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                layer = SubMConv3d(c, c, 3, bias=False).to(device)
                t = timed(lambda layer=layer, f=f: layer(SparseConvTensor(f, coords, spatial, n_scans, check=False)),
                          s.repeats, sync)
                add(f"SubMConv3d {c}->{c} k3 (incl. rule book build)", t, sites=n_sites,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                steps.update()
                table = rb_s.neighbour_table()
                t = timed(lambda f=f, w=w, table=table: implicit_gemm(f, w, table), s.repeats, sync)
                add(f"  alternative: implicit GEMM {c}->{c} (not used)", t, sites=n_sites,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                steps.update()
            f = torch.randn(n_sites, 16, device=device)
            w = torch.randn(32, 16, 3, 3, 3, device=device) * 0.05
            t = timed(lambda: sparse_conv(f, w, rb_c), s.repeats, sync)
            add("SparseConv3d 16->32 k3 s2 p1 (rule book cached)", t, sites_in=n_sites, sites_out=rb_c.num_out,
                pairs=rb_c.num_pairs, gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
            layer = SparseConv3d(16, 32, 3, 2, 1, bias=False).to(device)
            t = timed(lambda: layer(SparseConvTensor(f, coords, spatial, n_scans, check=False)), s.repeats, sync)
            add("SparseConv3d 16->32 k3 s2 p1 (incl. rule book build)", t, sites_in=n_sites, sites_out=rb_c.num_out,
                gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
            steps.update()

        # SECOND-style backbone.
        net = backbone(4).to(device)
        convs = [m for m in net.modules() if isinstance(m, (SubMConv3d, SparseConv3d))]
        stats: dict = {}

        def run_backbone():
            x = SparseConvTensor(feats, coords, spatial, n_scans, check=False)
            y = net(x)
            stats["keys"] = len(y.indice_dict)
            stats["out_sites"] = int(y.indices.shape[0])
            stats["out_shape"] = y.spatial_shape
            return y

        def backbone_flops() -> int:
            # Useful multiply-adds of every conv layer, from the rule books of one forward.
            x = SparseConvTensor(feats, coords, spatial, n_scans, check=False)
            total, h = 0, x
            for blk in net:
                conv = blk[0]
                h2 = blk(h)
                rb = h.indice_dict[conv.indice_key]
                total += rb.num_pairs * conv.in_channels * conv.out_channels
                h = h2
            return total

        net.eval()
        with torch.no_grad():
            macs = backbone_flops()
            t = timed(run_backbone, s.repeats, sync)
        add("SECOND-style backbone forward (eval, no grad)", t, sites_in=n_sites, sites_out=stats["out_sites"],
            out_spatial_shape=stats["out_shape"], conv_layers=len(convs), rule_books_built=stats["keys"],
            gflops=2.0 * macs / (t["ms"] * 1e-3) / 1e9, useful_gflop=2.0 * macs / 1e9)
        steps.update()
        net.train()

        def train_step():
            y = run_backbone()
            y.features.square().mean().backward()

        t = timed(train_step, max(1, s.repeats // 2), sync)
        add("SECOND-style backbone forward + backward (train)", t, sites_in=n_sites, conv_layers=len(convs),
            rule_books_built=stats["keys"], gflops=3 * 2.0 * macs / (t["ms"] * 1e-3) / 1e9)
        net.zero_grad(set_to_none=True)
        steps.update()

        # Dense conv3d on a crop x in [XMIN, XMIN + crop) against the sparse conv on the crop's sites.
        if s.dense_crop_x > 0:
            nx = min(spatial[2], int(round(s.dense_crop_x / s.voxel_size[0])))
            crop_shape = [spatial[0], spatial[1], nx]
            nbytes = 2 * n_scans * 16 * math.prod(crop_shape) * 4
            if nbytes / 1e9 > s.dense_max_gb:
                meta["dense_skipped"] = f"needs {nbytes / 1e9:.1f} GB > --dense-max-gb {s.dense_max_gb}"
            else:
                keep = coords[:, 3] < nx
                cc = coords[keep]
                f = torch.randn(int(cc.shape[0]), 16, device=device)
                w = torch.randn(16, 16, 3, 3, 3, device=device) * 0.05
                xs = SparseConvTensor(f, cc, crop_shape, n_scans, check=False)
                rb_crop = build_subm_rulebook(cc, crop_shape, 3, batch_size=n_scans)
                dense_in = xs.dense()
                with torch.no_grad():
                    td = timed(lambda: F.conv3d(dense_in, w, None, 1, 1), max(1, s.repeats // 2), sync)
                    ts = timed(lambda: sparse_conv(f, w, rb_crop), s.repeats, sync)
                dense_macs = n_scans * math.prod(crop_shape) * 27 * 16 * 16
                add(f"dense conv3d 16->16 k3 on crop {crop_shape} (x < {nx * s.voxel_size[0]:.0f} m)", td,
                    grid_sites=n_scans * math.prod(crop_shape),
                    gflops_total=2.0 * dense_macs / (td["ms"] * 1e-3) / 1e9,
                    gflops=gflops(rb_crop.num_pairs, 16, 16, td["ms"]))
                add(f"  sparse SubMConv3d 16->16 on the same crop ({int(cc.shape[0])} sites)", ts,
                    sites=int(cc.shape[0]), pairs=rb_crop.num_pairs, gflops=gflops(rb_crop.num_pairs, 16, 16, ts["ms"]))
                del dense_in
        steps.update()

        # spconv (optional; never installed by this benchmark).
        try:
            import spconv.pytorch as spconv

            meta["spconv"] = _bench_spconv(spconv, feats, coords, spatial, n_scans, s, sync, n_sites, rb_s, add)
        except ImportError:
            meta["spconv"] = "not installed"
            tqdm.write("spconv: not installed")
        steps.update()

    steps = tqdm(total=11 * (2 if s.load else 1), desc="bench_sparse", unit="case")

    def run(tag: str):
        rows: list = []
        measure(adder(rows, tag), steps, results)
        return rows

    tags = iter(["", "[loaded] "])
    idle, loaded, load_info = idle_and_loaded(lambda: run(next(tags)), s.load)
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

