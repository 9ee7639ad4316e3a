"""Shared pytest set-up: the `slow` marker is skipped unless --runslow is given."""
import os

import pytest

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
# OpenMP threads sleep instead of spinning while they wait: on a busy 2-core machine spinning
# threads starve each other (measured 10x slower test runs), on an idle one it costs nothing.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)
