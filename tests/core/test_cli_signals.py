"""A tool killed with SIGTERM unwinds as on Ctrl-C (detbench.utils.cli.run_main): one 'interrupted' line,
status 130, and the file it was writing atomically is dropped, not left as a stray temporary."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from tests.helpers import ROOT

TOOL = """
import sys, time
from pathlib import Path
from detbench.utils.cli import run_main
from detbench.utils.atomic import atomic_path
out = Path(sys.argv[1])

def main(_argv):
    with atomic_path(out / "report.json") as tmp:
        tmp.write_text("half a report")
        (out / "writing").write_text("1")
        time.sleep(60)
    return 0

sys.exit(run_main(main))
"""


def test_sigterm_ends_a_tool_as_ctrl_c_does_and_drops_its_half_written_file(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", TOOL, str(tmp_path)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    for _ in range(600):
        if (tmp_path / "writing").exists():
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    assert out.strip().endswith("interrupted") and "Traceback" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["writing"]  # no report.json, no .tmp-report.json-*
