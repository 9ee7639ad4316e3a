"""Benchmark detbench.sparse and detbench.ops.voxelize on the voxels of a 1.8 m LiDAR scan.

Times (milliseconds, median and best of --repeats runs after one warm-up):
  voxelization; rule-book builds; SubMConv3d 16->16 and 32->32; a strided SparseConv3d;
  a SECOND-style 3D backbone (OpenPCDet VoxelBackBone8x topology) forward, and forward +
  backward; a dense conv3d on a cropped grid (where it fits in memory) against the sparse
  conv on the same crop; the implicit-GEMM alternative kernel; spconv when installed.
With --load N every case is measured twice: on the machine as it is, then beside N busy-loop
processes (started for the measurement, stopped after); the report has both and their ratio.
Reports active sites, rule-book pairs and achieved GFLOP/s of the useful multiply-adds
(one multiply-add = 2 FLOP; useful = one per active (input, output, offset) pair and
channel pair). Writes bench_sparse.json and bench_sparse.md to --out.

Usage: python tools/bench_sparse.py [--out DIR] [--scans N] [--repeats N] [--load N] ...  (see --help)
spconv for the comparison: `pip install spconv==2.3.8` (its CPU build), or into a separate folder
so nothing installed changes (then run with PYTHONPATH=/tmp/spconv_site):
  pip install --target /tmp/spconv_site --no-deps spconv==2.3.8 cumm==0.7.11 ccimport==0.4.4
      pccm==0.4.16 fire lark portalocker pybind11 termcolor ninja
"""
from __future__ import annotations

import argparse
import math
import platform
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401

import detbench  # noqa: E402,F401  (first: sets the thread runtimes' defaults before torch starts)
import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from tqdm import tqdm  # noqa: E402

from detbench.ops.voxelize import (dynamic_voxelize, scatter_mean, unique_voxels, voxel_grid_size,  # noqa: E402
                                   voxelize)
from detbench.sim.scans import load_scans  # noqa: E402
from detbench.sparse import (SparseConv3d, SparseConvTensor, SubMConv3d, build_conv_rulebook,  # noqa: E402
                             build_subm_rulebook, sparse_conv)
from detbench.sparse.bench import backbone, implicit_gemm  # noqa: E402
from detbench import runtime  # noqa: E402
from detbench.utils.bench import gflops, idle_and_loaded, load_line, ratio, runtime_line, timed  # noqa: E402
from detbench.utils.cli import UserError, check_out_dir, require, run_main, torch_device  # noqa: E402
from detbench.utils.io import atomic_write_json, atomic_write_text  # noqa: E402


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/bench_sparse",
                    help="output folder for bench_sparse.json and bench_sparse.md (default: %(default)s)")
    ap.add_argument("--scans", type=int, default=1,
                    help="number of 1.8 m scans batched together (batch size; default %(default)s)")
    ap.add_argument("--source", choices=["auto", "sim", "synthetic"], default="auto",
                    help="scan source: detbench.sim when importable (auto), force sim, or the built-in synthetic scan")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the scan and the weights")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case after one warm-up (default %(default)s)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads (default: detbench's, OMP_NUM_THREADS; see docs/architecture.md)")
    ap.add_argument("--load", type=int, default=0, metavar="N",
                    help="also measure every case beside N busy-loop processes started for it (and stopped "
                         "after), reported next to the idle figures with the ratio (default %(default)s: idle only)")
    ap.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default %(default)s)")
    ap.add_argument("--voxel-size", type=float, nargs=3, default=[0.1, 0.1, 0.15], metavar=("VX", "VY", "VZ"),
                    help="voxel size in metres (default: %(default)s, SECOND-like)")
    ap.add_argument("--range", type=float, nargs=6, default=[0.0, -15.0, -1.0, 150.0, 15.0, 4.0],
                    metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                    help="point-cloud range in metres, ego frame (default: %(default)s)")
    ap.add_argument("--max-points", type=int, default=5, help="hard voxelization: points per voxel (default %(default)s)")
    ap.add_argument("--dense-crop-x", type=float, default=30.0,
                    help="x extent in metres of the crop (from XMIN) for the dense conv3d comparison; 0 skips it "
                         "(default %(default)s)")
    ap.add_argument("--dense-max-gb", type=float, default=2.0,
                    help="skip the dense comparison when its input + output tensors exceed this many GB")
    args = ap.parse_args(argv)
    for flag in ("scans", "repeats", "threads", "max_points"):
        v = getattr(args, flag)
        require(v is None or v >= 1, f"--{flag.replace('_', '-')} {v}: must be an integer >= 1")
    require(args.load >= 0, f"--load {args.load}: must be an integer >= 0 (busy processes beside the second run)")
    require(args.dense_crop_x > 0 and args.dense_max_gb > 0, "--dense-crop-x and --dense-max-gb must be > 0")
    check_out_dir(args.out)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch_device(args.device)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    torch.manual_seed(args.seed)

    try:
        grid_xyz = voxel_grid_size(args.voxel_size, args.range)
    except ValueError as e:
        raise UserError(f"--voxel-size / --range: {e}") from None
    scans, source = load_scans(args.scans, args.seed, args.source)
    # OpenPCDet adds one z layer so that the strided z sizes divide evenly: (Z + 1, Y, X).
    spatial = [grid_xyz[2] + 1, grid_xyz[1], grid_xyz[0]]
    results: dict = {
        "source": source, "scans": args.scans, "points": [int(len(s)) for s in scans],
        "voxel_size_m": args.voxel_size, "range_m": args.range, "grid_xyz": list(grid_xyz),
        "spatial_shape_zyx": spatial, "threads": torch.get_num_threads(), "device": str(device),
        "torch": torch.__version__, "cpu": platform.processor() or platform.machine(),
        "repeats": args.repeats, "flop_convention": "GFLOP/s = 2 * useful multiply-adds / time "
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
        torch.manual_seed(args.seed)
        # Voxelization (numba) and the mean-VFE input features.
        vox = timed(lambda: [voxelize(s, args.voxel_size, args.range, args.max_points, 150000) for s in scans],
                    args.repeats, lambda: None)
        hv = [voxelize(s, args.voxel_size, args.range, args.max_points, 150000) for s in scans]
        add("hard voxelization (numba, all scans)", vox, voxels=int(sum(len(h.coords) for h in hv)))
        pts_t = [torch.from_numpy(s).to(device) for s in scans]

        def dynamic_mean():
            # Dynamic voxelization + unique voxels + scatter-mean (what a dynamic VFE does), torch path.
            per = [dynamic_voxelize(p, args.voxel_size, args.range) for p in pts_t]
            cc = torch.cat([torch.cat([torch.full_like(c[:, :1], b), c], 1) for b, c in enumerate(per)])
            cc[(cc[:, 1:] < 0).any(1)] = -1
            vc, inv = unique_voxels(cc)
            return scatter_mean(torch.cat(pts_t), inv, vc.shape[0])

        t = timed(dynamic_mean, args.repeats, sync)
        add("dynamic voxelization + unique + scatter_mean (torch)", t, voxels=int(dynamic_mean().shape[0]))
        steps.update()
        coords = torch.cat([torch.cat([torch.full((len(h.coords), 1), b, dtype=torch.int32),
                                       torch.from_numpy(h.coords)], 1) for b, h in enumerate(hv)]).to(device)
        feats = torch.cat([torch.from_numpy(h.voxels.sum(1) / np.maximum(h.num_points, 1)[:, None])
                           for h in hv]).float().to(device)
        n_sites = int(coords.shape[0])
        meta["active_sites"] = n_sites
        x4 = SparseConvTensor(feats, coords, spatial, args.scans)

        # Rule books.
        rb_s = build_subm_rulebook(coords, spatial, 3, batch_size=args.scans)
        t = timed(lambda: build_subm_rulebook(coords, spatial, 3, batch_size=args.scans), args.repeats, sync)
        add("rule book SubM k3", t, sites_in=n_sites, pairs=rb_s.num_pairs,
            neighbours_per_site=rb_s.num_pairs / max(n_sites, 1))
        rb_c = build_conv_rulebook(coords, spatial, 3, 2, 1, batch_size=args.scans)
        t = timed(lambda: build_conv_rulebook(coords, spatial, 3, 2, 1, batch_size=args.scans), args.repeats, sync)
        add("rule book SparseConv k3 s2 p1", t, sites_in=n_sites, sites_out=rb_c.num_out, pairs=rb_c.num_pairs)
        steps.update()

        # Single layers: compute only (cached rule book), and cold (rule book built in the call).
        with torch.no_grad():
            for c in (16, 32):
                f = torch.randn(n_sites, c, device=device)
                w = torch.randn(c, c, 3, 3, 3, device=device) * 0.05
                t = timed(lambda: sparse_conv(f, w, rb_s), args.repeats, sync)
                add(f"SubMConv3d {c}->{c} k3 (rule book cached)", t, sites=n_sites, pairs=rb_s.num_pairs,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                layer = SubMConv3d(c, c, 3, bias=False).to(device)
                t = timed(lambda: layer(SparseConvTensor(f, coords, spatial, args.scans, check=False)), args.repeats, sync)
                add(f"SubMConv3d {c}->{c} k3 (incl. rule book build)", t, sites=n_sites,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                steps.update()
                table = rb_s.neighbour_table()
                t = timed(lambda: implicit_gemm(f, w, table), args.repeats, sync)
                add(f"  alternative: implicit GEMM {c}->{c} (not used)", t, sites=n_sites,
                    gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
                steps.update()
            f = torch.randn(n_sites, 16, device=device)
            w = torch.randn(32, 16, 3, 3, 3, device=device) * 0.05
            t = timed(lambda: sparse_conv(f, w, rb_c), args.repeats, sync)
            add("SparseConv3d 16->32 k3 s2 p1 (rule book cached)", t, sites_in=n_sites, sites_out=rb_c.num_out,
                pairs=rb_c.num_pairs, gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
            layer = SparseConv3d(16, 32, 3, 2, 1, bias=False).to(device)
            t = timed(lambda: layer(SparseConvTensor(f, coords, spatial, args.scans, check=False)), args.repeats, sync)
            add("SparseConv3d 16->32 k3 s2 p1 (incl. rule book build)", t, sites_in=n_sites, sites_out=rb_c.num_out,
                gflops=gflops(rb_c.num_pairs, 16, 32, t["ms"]))
            steps.update()

        # SECOND-style backbone.
        net = backbone(4).to(device)
        convs = [m for m in net.modules() if isinstance(m, (SubMConv3d, SparseConv3d))]
        stats: dict = {}

        def run_backbone():
            x = SparseConvTensor(feats, coords, spatial, args.scans, check=False)
            y = net(x)
            stats["keys"] = len(y.indice_dict)
            stats["out_sites"] = int(y.indices.shape[0])
            stats["out_shape"] = y.spatial_shape
            return y

        def backbone_flops() -> int:
            # Useful multiply-adds of every conv layer, from the rule books of one forward.
            x = SparseConvTensor(feats, coords, spatial, args.scans, check=False)
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
            t = timed(run_backbone, args.repeats, sync)
        add("SECOND-style backbone forward (eval, no grad)", t, sites_in=n_sites, sites_out=stats["out_sites"],
            out_spatial_shape=stats["out_shape"], conv_layers=len(convs), rule_books_built=stats["keys"],
            gflops=2.0 * macs / (t["ms"] * 1e-3) / 1e9, useful_gflop=2.0 * macs / 1e9)
        steps.update()
        net.train()

        def train_step():
            y = run_backbone()
            y.features.square().mean().backward()

        t = timed(train_step, max(1, args.repeats // 2), sync)
        add("SECOND-style backbone forward + backward (train)", t, sites_in=n_sites, conv_layers=len(convs),
            rule_books_built=stats["keys"], gflops=3 * 2.0 * macs / (t["ms"] * 1e-3) / 1e9)
        net.zero_grad(set_to_none=True)
        steps.update()

        # Dense conv3d on a crop x in [XMIN, XMIN + crop) against the sparse conv on the crop's sites.
        dense_row = None
        if args.dense_crop_x > 0:
            nx = min(spatial[2], int(round(args.dense_crop_x / args.voxel_size[0])))
            crop_shape = [spatial[0], spatial[1], nx]
            nbytes = 2 * args.scans * 16 * math.prod(crop_shape) * 4
            if nbytes / 1e9 > args.dense_max_gb:
                meta["dense_skipped"] = f"needs {nbytes / 1e9:.1f} GB > --dense-max-gb {args.dense_max_gb}"
            else:
                keep = coords[:, 3] < nx
                cc = coords[keep]
                f = torch.randn(int(cc.shape[0]), 16, device=device)
                w = torch.randn(16, 16, 3, 3, 3, device=device) * 0.05
                xs = SparseConvTensor(f, cc, crop_shape, args.scans, check=False)
                rb_crop = build_subm_rulebook(cc, crop_shape, 3, batch_size=args.scans)
                dense_in = xs.dense()
                with torch.no_grad():
                    td = timed(lambda: F.conv3d(dense_in, w, None, 1, 1), max(1, args.repeats // 2), sync)
                    ts = timed(lambda: sparse_conv(f, w, rb_crop), args.repeats, sync)
                dense_macs = args.scans * math.prod(crop_shape) * 27 * 16 * 16
                dense_row = add(f"dense conv3d 16->16 k3 on crop {crop_shape} (x < {nx * args.voxel_size[0]:.0f} m)", td,
                                grid_sites=args.scans * math.prod(crop_shape),
                                gflops_total=2.0 * dense_macs / (td["ms"] * 1e-3) / 1e9,
                                gflops=gflops(rb_crop.num_pairs, 16, 16, td["ms"]))
                add(f"  sparse SubMConv3d 16->16 on the same crop ({int(cc.shape[0])} sites)", ts,
                    sites=int(cc.shape[0]), pairs=rb_crop.num_pairs, gflops=gflops(rb_crop.num_pairs, 16, 16, ts["ms"]))
                del dense_in
        steps.update()

        # spconv (optional; never installed by this script).
        try:
            import spconv.pytorch as spconv  # noqa: F401

            meta["spconv"] = _bench_spconv(spconv, feats, coords, spatial, args, sync, n_sites, rb_s, add)
        except ImportError:
            meta["spconv"] = "not installed"
            tqdm.write("spconv: not installed")
        steps.update()

    steps = tqdm(total=11 * (2 if args.load else 1), desc="bench_sparse", unit="case")

    def run(tag: str):
        rows: list = []
        measure(adder(rows, tag), steps, results)
        return rows

    tags = iter(["", "[loaded] "])
    idle, loaded, load_info = idle_and_loaded(lambda: run(next(tags)), args.load)
    steps.close()
    results["cases"] = idle
    if loaded is not None:
        results["load"] = load_info
        by_case = {lrow["case"]: lrow for lrow in loaded}
        for row in idle:
            lrow = by_case[row["case"]]
            row.update(loaded_ms=lrow["ms"], loaded_ms_best=lrow["ms_best"], loaded_ratio=ratio(lrow["ms"], row["ms"]))
    results["runtime"] = runtime.describe()

    out = Path(args.out)
    atomic_write_json(out / "bench_sparse.json", results)
    atomic_write_text(out / "bench_sparse.md", markdown(results))
    print(f"wrote {out / 'bench_sparse.json'} and {out / 'bench_sparse.md'}")
    return 0


def _bench_spconv(spconv, feats, coords, spatial, args, sync, n_sites, rb_s, add) -> dict:
    """Time spconv's SubMConv3d on the same sites (only when spconv happens to be installed)."""
    out = {}
    with torch.no_grad():
        for c in (16, 32):
            f = torch.randn(n_sites, c, device=feats.device)
            layer = spconv.SubMConv3d(c, c, 3, bias=False, indice_key="s").to(feats.device)
            x = spconv.SparseConvTensor(f, coords, spatial, args.scans)
            layer(x)  # builds and caches the pairs under "s"
            t = timed(lambda: layer(x), args.repeats, sync)
            row = add(f"spconv SubMConv3d {c}->{c} k3 (pairs cached)", t, sites=n_sites,
                      gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
            out[f"subm{c}_ms"] = row["ms"]
            t = timed(lambda: layer(spconv.SparseConvTensor(f, coords, spatial, args.scans)), args.repeats, sync)
            row = add(f"spconv SubMConv3d {c}->{c} k3 (incl. pair build)", t, sites=n_sites,
                      gflops=gflops(rb_s.num_pairs, c, c, t["ms"]))
            out[f"subm{c}_incl_pairs_ms"] = row["ms"]
    return out


def markdown(r: dict) -> str:
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


if __name__ == "__main__":
    sys.exit(run_main(main))
