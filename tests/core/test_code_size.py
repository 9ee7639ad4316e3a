"""The size bars of the code review: no module over 600 lines and no function over 120 lines, so each reads in
a sitting. Checked on the source of the packages listed in CHECKED."""
import ast

import pytest

from tests.helpers import ROOT

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 120
CHECKED = ("detbench/eval", "detbench/utils", "detbench/train")


@pytest.mark.parametrize("package", CHECKED)
def test_modules_and_functions_stay_under_the_bars(package):
    too_long = []
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"{package}: no Python files"
    for path in files:
        text = path.read_text(encoding="utf-8")
        rel = path.relative_to(ROOT)
        if text.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{rel}: {text.count(chr(10))} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    too_long.append(f"{rel}:{node.lineno} {node.name}: {n} lines (at most {MAX_FUNCTION_LINES})")
    assert not too_long, "\n".join(too_long)
