"""tools/install.sh: torch only when it is not importable, from TORCH_INDEX_URL when given, then detbench."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers import ROOT

# A stand-in for python3: `-c` exits with TORCH_OK (the import check and the final version line), every
# `-m pip ...` call is written to the log instead of being run.
FAKE_PY = """#!/usr/bin/env bash
if [ "$1" = "-c" ]; then
  case "$2" in *"print("*) echo "torch 2.13.0"; exit 0;; esac
  exit "${TORCH_OK:-1}"
fi
echo "$*" >> "$PIP_LOG"
"""


def run_install(tmp_path: Path, *args: str, **env: str) -> list[str]:
    fake = tmp_path / "python"
    fake.write_text(FAKE_PY)
    fake.chmod(0o755)
    log = tmp_path / "pip.log"
    subprocess.run(["bash", str(ROOT / "tools" / "install.sh"), *args], check=True, capture_output=True, text=True,
                   env={**os.environ, "PYTHON": str(fake), "PIP_LOG": str(log), **env})
    return log.read_text().splitlines()


@pytest.mark.parametrize("index, extra", [(None, ""), ("https://download.pytorch.org/whl/cpu", "--dev")])
def test_torch_is_installed_first_when_missing_from_the_index_given(tmp_path, index, extra):
    env = {"TORCH_INDEX_URL": index} if index else {}
    calls = run_install(tmp_path, *([extra] if extra else []), **env)
    assert len(calls) == 2 and calls[0].startswith("-m pip install --quiet torch==2.13.0")
    assert calls[0].endswith(f"--index-url {index}") if index else "--index-url" not in calls[0]
    assert calls[1] == "-m pip install --quiet -e ." + ("[dev,cluster]" if extra else "")


def test_an_importable_torch_is_kept(tmp_path):
    calls = run_install(tmp_path, TORCH_OK="0", TORCH_INDEX_URL="https://download.pytorch.org/whl/cpu")
    assert calls == ["-m pip install --quiet -e ."]
