#!/usr/bin/env python3
"""Import OpenPCDet custom folders (one per LiDAR height) as one detbench dataset.

    python tools/import_openpcdet.py --src 1.8=/data/h3/1.8m [--src 0.5=...] --out data/height3

The same command as `python -m detbench.data.convert` (the conversion lives there; see its
--help and docs/data-format.md, "OpenPCDet's format and detbench's"). Writes OUT/dataset.json,
OUT/convert_report.json and OUT/convert_report.md; a problem is one 'error:' line naming the
file and the flag to set, exit status 2.
"""
from __future__ import annotations

import sys

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.data.convert import main
from detbench.utils.cli import run_main

if __name__ == "__main__":
    sys.exit(run_main(main))
