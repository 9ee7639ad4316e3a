#!/usr/bin/env python3
"""Export one LiDAR height of a detbench dataset as an OpenPCDet custom dataset.

    python tools/export_openpcdet.py ROOT --height 1.8 --out DIR [--frame ground|sensor] [--class-map SPEC]

DIR gets OpenPCDet's custom layout (points/<id>.npy, labels/<id>.txt, ImageSets/train.txt and
val.txt), a custom_dataset.yaml for it, create_infos.sh, and detbench_export.json + .md (what
was written, in which frame, and the commands into OpenPCDet and back). Details:
docs/data-format.md, "OpenPCDet's format and detbench's".
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.data.errors import DatasetError
from detbench.data.frame import height_or_rig_arg, is_rig_key
from detbench.data.openpcdet import CLASS_MAP_PRESETS, DEFAULT_EXPORT_CLASS_MAP, class_count_lines, parse_class_map
from detbench.data.openpcdet_export import EXPORT_MANIFEST, EXPORT_MARKDOWN, export_openpcdet
from detbench.utils.cli import UserError, run_main


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="tools/export_openpcdet.py",
        description="Write one mounting height of a detbench dataset as an OpenPCDet custom dataset that "
                    "OpenPCDet's own reader (pcdet/datasets/custom/custom_dataset.py) loads unchanged.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  python tools/export_openpcdet.py data/sim --height 1.8 --out data/openpcdet_1.8\n"
               "  python tools/export_openpcdet.py data/sim --height 0.5 --out data/opc_0.5_sensor --frame sensor\n"
               "  python tools/export_openpcdet.py data/sim --height 1.8 --out data/opc_kitti "
               "--class-map 'van=Van,*=Car'\n"
               "then, in OpenPCDet: sh DIR/create_infos.sh /path/to/OpenPCDet (commands in DIR/detbench_export.md)\n"
               "and back: python tools/eval.py --data ROOT --height H --pred .../result.pkl --pred-frame FRAME\n\n"
               "Units: metres and radians; points (N, 4) float32 x y z intensity.\n"
               "Frames without boxes are left out of ImageSets: OpenPCDet's info generation cannot read an empty\n"
               "label file.")
    ap.add_argument("root", metavar="ROOT", help="detbench dataset folder (holds dataset.json)")
    ap.add_argument("--height", type=height_or_rig_arg, required=True,
                    help="the LiDAR mounting height to export, metres, or a rig the dataset holds by name "
                         "(docs/rigs.md; ground frame only)")
    ap.add_argument("--out", required=True, metavar="DIR", help="output folder (new or empty, or an earlier export "
                                                                "with --overwrite)")
    ap.add_argument("--frame", choices=("ground", "sensor"), default="ground",
                    help="frame of the written points and labels: 'ground' (default; detbench's ego ground frame, "
                         "road at z = 0, exact boxes) or 'sensor' (the LiDAR's own frame, road at z = -height; boxes "
                         "stay upright, so a pitched sensor's box tilt is dropped). Recorded in the manifest and "
                         "the yaml")
    ap.add_argument("--class-map", action="append", default=None, metavar="SPEC",
                    help=f"rename or drop classes: comma-separated SRC=DST (SRC a class or '*' for every other; DST "
                         f"a name, '-' to drop, '*' to keep) or a preset ({', '.join(CLASS_MAP_PRESETS)}); default "
                         f"{DEFAULT_EXPORT_CLASS_MAP!r}: every vehicle type -> Vehicle, OpenPCDet's custom class")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier export in DIR (and the OpenPCDet "
                                                             "infos made from it)")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cmap = parse_class_map(args.class_map, DEFAULT_EXPORT_CLASS_MAP)
    except ValueError as e:
        raise UserError(str(e)) from None
    t0 = time.perf_counter()
    try:
        m = export_openpcdet(args.root, args.height, args.out, frame=args.frame, class_map=cmap,
                             overwrite=args.overwrite, progress=not args.no_progress)
    except (DatasetError, FileNotFoundError, ValueError) as e:
        raise UserError(str(e)) from None
    out = Path(args.out)
    sp = m["splits"]
    where = m["source"]["height"] + ("" if is_rig_key(m["source"]["height"]) else " m")
    print(f"{out}: {where} in the {m['frame']} frame; train {sp['train']['frames']} frames, val "
          f"{sp['val']['frames']} frames; {m['boxes']} boxes; classes {', '.join(m['classes']) or '(none)'} "
          f"({time.perf_counter() - t0:.1f} s)")
    print(f"label lines per class (map {m['class_map']}):")
    for line in class_count_lines(m["class_counts"]):
        print("  " + line)
    for n in m["notes"]:
        print("note: " + n)
    c = m["commands"]
    print("into OpenPCDet (OPENPCDET = your OpenPCDet checkout; or: sh "
          f"{out / 'create_infos.sh'} OPENPCDET):")
    print("  " + c["link"])
    print("  " + c["create_infos"])
    print(f"  then train with {out / 'custom_dataset.yaml'} as the dataset config and CLASS_NAMES: {m['classes']}")
    print("back into detbench:")
    print("  " + c["evaluate_in_detbench"])
    print(f"wrote {out / EXPORT_MANIFEST}, {out / EXPORT_MARKDOWN}, {out / 'custom_dataset.yaml'}, "
          f"{out / 'create_infos.sh'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
