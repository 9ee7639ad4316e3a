"""Shared pytest set-up: the `slow` marker is skipped unless --runslow is given; `load_tool` fixture."""
import importlib.util
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

os.environ.setdefault("NUMBA_NUM_THREADS", "2")
# Before any test module imports torch or numba: the library's thread-runtime defaults
# (detbench/runtime.py: thread counts and a short OpenMP spin, so a busy machine does not
# slow the tests several-fold).
import detbench  # noqa: E402,F401


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture
def load_tool():
    """`load_tool("analyze")`: tools/analyze.py loaded as a fresh module, so a test runs its `main(argv)`
    in this process (no interpreter and numba start-up per call). Tools hold argument parsing and
    output; what they compute is library code, which tests import directly."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(f"detbench_tools_{name}", ROOT / "tools" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # dataclasses defined by the tool look their module up here
        spec.loader.exec_module(mod)
        return mod

    return load
