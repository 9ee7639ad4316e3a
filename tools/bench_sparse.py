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
import sys
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

import detbench  # noqa: F401  (first: sets the thread runtimes' defaults before torch starts)
import torch

from detbench.benchmarks.sparse import SparseBenchSettings, run_sparse_bench, sparse_bench_markdown
from detbench.ops.voxelize import voxel_grid_size
from detbench.sim.scans import load_scans
from detbench.utils.cli import UserError, check_out_dir, require, run_main, torch_device
from detbench.utils.atomic import atomic_write_json, atomic_write_text


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    D = SparseBenchSettings()  # the defaults
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/bench_sparse",
                    help="output folder for bench_sparse.json and bench_sparse.md (default: %(default)s)")
    ap.add_argument("--scans", type=int, default=1,
                    help="number of 1.8 m scans batched together (batch size; default %(default)s)")
    ap.add_argument("--source", choices=["auto", "sim", "synthetic"], default="auto",
                    help="scan source: detbench.sim when importable (auto), force sim, or the built-in synthetic scan")
    ap.add_argument("--seed", type=int, default=D.seed, help="random seed of the scan and the weights")
    ap.add_argument("--repeats", type=int, default=D.repeats,
                    help="timed runs per case after one warm-up (default %(default)s)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads (default: detbench's, OMP_NUM_THREADS; see docs/benchmarks.md)")
    ap.add_argument("--load", type=int, default=D.load, metavar="N",
                    help="also measure every case beside N busy-loop processes started for it (and stopped "
                         "after), reported next to the idle figures with the ratio (default %(default)s: idle only)")
    ap.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default %(default)s)")
    ap.add_argument("--voxel-size", type=float, nargs=3, default=D.voxel_size, metavar=("VX", "VY", "VZ"),
                    help="voxel size in metres (default: %(default)s, SECOND-like)")
    ap.add_argument("--range", type=float, nargs=6, default=D.range,
                    metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                    help="point-cloud range in metres, ego frame (default: %(default)s)")
    ap.add_argument("--max-points", type=int, default=D.max_points,
                    help="hard voxelization: points per voxel (default %(default)s)")
    ap.add_argument("--dense-crop-x", type=float, default=D.dense_crop_x,
                    help="x extent in metres of the crop (from XMIN) for the dense conv3d comparison; 0 skips it "
                         "(default %(default)s)")
    ap.add_argument("--dense-max-gb", type=float, default=D.dense_max_gb,
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
    try:
        voxel_grid_size(args.voxel_size, args.range)
    except ValueError as e:
        raise UserError(f"--voxel-size / --range: {e}") from None
    scans, source = load_scans(args.scans, args.seed, args.source)
    settings = SparseBenchSettings(voxel_size=args.voxel_size, range=args.range, max_points=args.max_points,
                                   seed=args.seed, repeats=args.repeats, dense_crop_x=args.dense_crop_x,
                                   dense_max_gb=args.dense_max_gb, load=args.load)
    results = run_sparse_bench(scans, source, settings, device)

    out = Path(args.out)
    atomic_write_json(out / "bench_sparse.json", results)
    atomic_write_text(out / "bench_sparse.md", sparse_bench_markdown(results))
    print(f"wrote {out / 'bench_sparse.json'} and {out / 'bench_sparse.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
