"""Shared pytest set-up: the `slow` marker is skipped unless --runslow is given. Tests import the commands
as `tools.<name>` (pyproject.toml puts the repository root on the path) and call their `main(argv)`."""
import os
from pathlib import Path

import pytest

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
# Before any test module imports torch or numba: the library's thread-runtime defaults
# (detbench/runtime.py: thread counts and a short OpenMP spin, so a busy machine does not
# slow the tests several-fold).
import detbench  # noqa: F401

# Child processes (tools run as scripts, killed trainings, jobs of a study) import this tree's detbench,
# not whichever checkout an editable install points at.
_ROOT = str(Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join([_ROOT, *[p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                    if p and p != _ROOT]])


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)

