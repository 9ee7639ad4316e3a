"""The import layering of docs/architecture.md, checked on the source (every import, also inside functions),
and its rule that models/stages/__init__.py exports every stage."""
import ast
import re
from pathlib import Path

from tests.helpers import ROOT


# detbench's subpackages, lowest first; a module may import its own subpackage and lower ones
# config sits just above utils: it quotes untrusted YAML through detbench.utils.untrusted
LAYERS = {"runtime": 0, "utils": 0, "config": 0.5, "ops": 1, "sparse": 1, "data": 2, "sim": 3, "eval": 3, "train": 4,
          "studies": 5, "benchmarks": 5}


def _imports(path: Path) -> list[str]:
    names = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def _part(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "detbench" and len(parts) > 1 else None


def test_detbench_imports_only_lower_layers():
    bad = []
    for path in sorted((ROOT / "detbench").rglob("*.py")):
        rel = path.relative_to(ROOT / "detbench")
        own = rel.parts[0].removesuffix(".py")
        if own not in LAYERS:
            continue
        for name in _imports(path):
            if name.split(".")[0] in ("models", "tools"):
                bad.append(f"{rel}: imports {name}")
            other = _part(name)
            if other in LAYERS and other != own and LAYERS[other] >= LAYERS[own]:
                bad.append(f"detbench/{rel}: {own} imports {name} (layer {LAYERS[other]} >= {LAYERS[own]})")
    assert not bad, "\n".join(bad)


def test_models_never_import_tools():
    bad = [f"{p.relative_to(ROOT)}: {n}" for p in sorted((ROOT / "models").rglob("*.py"))
           for n in _imports(p) if n.split(".")[0] == "tools"]
    assert not bad, "\n".join(bad)


def test_every_stage_module_is_exported():
    """models/stages/__init__.py imports from every stage module (losses.py holds plain functions, not a stage)."""
    stages = ROOT / "models" / "stages"
    tree = ast.parse((stages / "__init__.py").read_text(encoding="utf-8"))
    exported = {n.module for n in tree.body if isinstance(n, ast.ImportFrom) and n.level == 1}
    modules = {p.stem for p in stages.glob("*.py")} - {"__init__", "losses"}
    assert modules <= exported, f"not exported by models/stages/__init__.py: {sorted(modules - exported)}"


def _code_strings(path: Path) -> list[tuple[int, str]]:
    """(line, text) of the string constants of a module that are no docstring."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def test_detbench_runs_tools_by_path_from_one_module_only():
    """The imports cannot show that detbench runs a tool of tools/ (a study's job is the command a user types,
    and the tools import the detector registry, which detbench does not): a string naming a tool by path
    ("tools/train.py", "tools" joined with a file name, "tools.train") may stand only in
    detbench/studies/commands.py, and every tool named there exists."""
    tool_path = re.compile(r"^tools(/\w+\.py)?$|^tools\.\w+$")
    allowed = ROOT / "detbench" / "studies" / "commands.py"
    bad, named = [], []
    for path in sorted((ROOT / "detbench").rglob("*.py")):
        for line, text in _code_strings(path):
            if tool_path.match(text):
                (named if path == allowed else bad).append(f"{path.relative_to(ROOT)}:{line}: {text!r}")
                if path == allowed:
                    assert (ROOT / text).is_file(), f"{path.relative_to(ROOT)}:{line}: {text} does not exist"
    assert not bad, "detbench names a tool to run outside detbench/studies/commands.py:\n" + "\n".join(bad)
    assert named, "detbench/studies/commands.py names no tool: is this test still looking at the right module?"
