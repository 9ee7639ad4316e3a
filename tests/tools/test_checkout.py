"""How the commands in tools/ start: `python tools/<name>.py` from a checkout that is not installed puts
the checkout root on sys.path (tools/_checkout.py); tests import them as `tools.<name>`."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from tools import _checkout
from tests.helpers import ROOT

TOOLS = sorted(p.stem for p in (ROOT / "tools").glob("*.py") if not p.name.startswith("_"))


def test_checkout_root_goes_on_the_path_when_detbench_is_not_importable(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "detbench" else real(name, *a))
    path = ["/somewhere"]
    assert _checkout.add_checkout_root(path) is True
    assert path == [str(ROOT), "/somewhere"]
    assert _checkout.add_checkout_root(path) is True and path.count(str(ROOT)) == 1  # added once


def test_nothing_is_added_when_detbench_and_models_import():
    path: list[str] = []
    assert _checkout.add_checkout_root(path) is False and path == []


def test_every_tool_starts_through_the_shared_helper():
    """No tool carries its own sys.path code; each imports tools/_checkout.py when run as a file."""
    for name in TOOLS:
        text = (ROOT / "tools" / f"{name}.py").read_text(encoding="utf-8")
        assert "if not __package__:" in text and "import _checkout" in text, name
        assert "sys.path.insert" not in text, name


@pytest.mark.parametrize("name", ["validate", "export_openpcdet"])
def test_a_tool_runs_as_a_file_from_another_folder(name, tmp_path):
    """`python /path/to/tools/<name>.py --help` from an unrelated working directory."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / f"{name}.py"), "--help"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "usage:" in proc.stdout


@pytest.mark.parametrize("name", TOOLS)
def test_every_tool_answers_help_in_process(name, capsys):
    """`main(["--help"])` of each tool: its options, exit status 0."""
    import importlib

    with pytest.raises(SystemExit) as exc:
        importlib.import_module(f"tools.{name}").main(["--help"])
    assert exc.value.code == 0
    assert "usage:" in capsys.readouterr().out
