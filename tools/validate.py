#!/usr/bin/env python3
"""Check a whole dataset in one pass and list every problem with its file (and line).

    python tools/validate.py ROOT [--heights 0.5 1.8] [--max-errors 50]

The same as `python -m detbench.data.validate` (the check lives there). Exit status 0 when
the dataset is clean, 1 when problems were found.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

# Not installed (run from a checkout): the repository root holds detbench.
if importlib.util.find_spec("detbench") is None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from detbench.data.validate import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
