#!/usr/bin/env python3
"""Check a whole dataset in one pass and list every problem with its file (and line).

    python tools/validate.py ROOT [--heights 0.5 1.8 headlights] [--max-errors 50]

The same as `python -m detbench.data.validate` (the check lives there). Exit status 0 when
the dataset is clean, 1 when problems were found.
"""
from __future__ import annotations

import sys

if not __package__:  # run as a file (python tools/<name>.py): the checkout root on sys.path when not installed
    import _checkout  # noqa: F401  (imported for its side effect: sys.path)

from detbench.data.validate import main

if __name__ == "__main__":
    sys.exit(main())
