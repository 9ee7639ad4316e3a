"""Every command shown in README.md and docs/*.md exists as written.

The commands are taken from the ```bash / ```sh blocks (continuation lines joined, comments
dropped, `;` and `&&` split) and from inline code that starts with `python tools/...` or
`python -m detbench...`. Each one is parsed by its tool's own argument parser (the tool's
`main` runs until its `parse_args` returns, then stops), so a flag or a choice that does not
exist fails here with the file and line that show it, and so does a `--set KEY=VALUE` whose key
the config it overrides does not have. Placeholders the docs use on purpose
(`...`, `[--flag X]` for an optional part) are read as such.

The slow test runs a chain of the README's commands for real, at the smoke preset and a few
frames where the real command is long.

docs/results-archive.md, the dated record of past runs, keeps each run's command as it ran on its day;
its commands are not parsed against today's tools (its links are checked like every page's).
"""
from __future__ import annotations

import argparse
import importlib
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT

DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
ARCHIVE = ROOT / "docs" / "results-archive.md"  # a record of past runs: its commands are history
# `python -m MODULE` commands the docs show, and the module whose main parses them.
MODULES = {"detbench.data.convert": "detbench.data.convert", "detbench.data.validate": "detbench.data.validate"}
# Not detbench's: shown in the docs to say what to run elsewhere or how the suite runs.
FOREIGN = ("pytest", "ruff", "pcdet.")
FENCE = re.compile(r"^```(\w*)\s*$")
INLINE = re.compile(r"`((?:python3?|torchrun)\s[^`]*?(?:tools/\w+\.py|-m\s+detbench[\w.]*)[^`]*)`", re.S)


class _Parsed(Exception):
    """Raised by the patched parse_args once a tool's arguments are parsed: nothing else runs."""


def _segments(text: str) -> list[str]:
    """Shell lines of a code block: continuations joined, comments dropped, `;` / `&&` split."""
    out, cur = [], ""
    for raw in text.splitlines():
        line = raw.rstrip()
        if cur:
            cur += " " + line.strip()
        else:
            cur = line.strip()
        if cur.endswith("\\"):
            cur = cur[:-1].rstrip()
            continue
        out.append(cur)
        cur = ""
    if cur:
        out.append(cur)
    cmds = []
    for line in out:
        try:
            lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
            lexer.whitespace_split = True
            lexer.commenters = "#"
            tokens = list(lexer)
        except ValueError:
            continue
        part: list[str] = []
        for tok in tokens + [";"]:
            if tok in (";", "&&", "||", "|", "&"):
                if part:
                    cmds.append(shlex.join(part))
                part = []
            else:
                part.append(tok)
    return cmds


def doc_commands() -> list[tuple[str, int, str]]:
    """(file, line, command) of every detbench command in the README and docs."""
    found = []
    for path in DOCS:
        if path == ARCHIVE:
            continue
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        i = 0
        while i < len(lines):
            m = FENCE.match(lines[i])
            if m:
                j = i + 1
                while j < len(lines) and not lines[j].startswith("```"):
                    j += 1
                if m.group(1) in ("bash", "sh", "shell", "console", ""):
                    block = "\n".join(lines[i + 1:j])
                    for cmd in _segments(block):
                        found.append((path.name, i + 1, cmd))
                i = j + 1
                continue
            i += 1
        prose = re.sub(r"```.*?```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)
        for m in INLINE.finditer(prose):
            line_no = prose.count("\n", 0, m.start()) + 1
            for cmd in _segments(m.group(1).replace("\n", " ")):
                target = _target(cmd)
                if target is not None and target[1]:  # a bare `python tools/x.py` in prose names the tool
                    found.append((path.name, line_no, cmd))
    return [(f, n, c) for f, n, c in found if _target(c) is not None]


def _target(cmd: str) -> tuple[str, list[str]] | None:
    """(module whose main parses it, argv) of a detbench command; None for anything else."""
    tokens = shlex.split(cmd)
    if not tokens:
        return None
    if tokens[0] == "torchrun":
        tokens = [t for t in tokens[1:] if not t.startswith("--nproc") and not t.startswith("--nnodes")]
        tokens = ["python", *tokens]
    if tokens[0] not in ("python", "python3"):
        return None
    if len(tokens) > 2 and tokens[1] == "-m":
        if tokens[2].startswith(FOREIGN) or tokens[2] not in MODULES:
            return None if tokens[2].startswith(FOREIGN) else ("?" + tokens[2], tokens[3:])
        return MODULES[tokens[2]], tokens[3:]
    if len(tokens) > 1 and re.fullmatch(r"tools/\w+\.py", tokens[1]):
        return "tools." + tokens[1][len("tools/"):-3], tokens[2:]
    return None


def _argv(argv: list[str]) -> list[str] | None:
    """The arguments with the docs' placeholders read: `[--flag X]` is an optional part (kept, brackets off);
    None when the command is elided (`...` standing for arguments) and cannot be parsed whole."""
    if "..." in argv:
        return None
    out, optional = [], False
    for a in argv:
        if a.startswith("[-"):  # `[--flag X]`: the brackets mark an optional part, the values inside stay
            a, optional = a[1:], True
        if optional and a.endswith("]"):
            a, optional = a[:-1], False
        if a:
            out.append(a)
    return out


def parse_with_tool(module: str, argv: list[str]) -> argparse.Namespace:
    """Run `module.main(argv)` until its parser returns; the parsed namespace. SystemExit on a bad flag."""
    mod = importlib.import_module(module)
    original = argparse.ArgumentParser.parse_args

    def parse_and_stop(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    argparse.ArgumentParser.parse_args = parse_and_stop
    try:
        mod.main(argv)
    except _Parsed as done:
        return done.args[0]
    finally:
        argparse.ArgumentParser.parse_args = original
    raise AssertionError(f"{module}.main returned without parsing its arguments")


COMMANDS = doc_commands()


def test_the_docs_show_commands():
    tools = {_target(c)[0] for _, _, c in COMMANDS}
    assert len(COMMANDS) > 40 and {"tools.study", "tools.train", "tools.eval", "tools.simulate"} <= tools


@pytest.mark.parametrize("where,line,cmd", COMMANDS, ids=[f"{f}:{n}" for f, n, _ in COMMANDS])
def test_doc_command_parses(where, line, cmd, capsys):
    module, argv = _target(cmd)
    assert not module.startswith("?"), f"{where}:{line}: `{cmd}`: no detbench module {module[1:]}"
    assert importlib.util.find_spec(module) is not None, f"{where}:{line}: `{cmd}`: no such tool {module}"
    argv = _argv(argv)
    if argv is None:
        pytest.skip("elided command (`...`)")
    try:
        ns = parse_with_tool(module, argv)
    except SystemExit as e:
        if e.code == 0 and "--help" in argv:
            return
        raise AssertionError(f"{where}:{line}: `{cmd}` is refused by {module}'s parser: "
                             f"{capsys.readouterr().err.strip().splitlines()[-1:]}") from e
    problem = check_overrides(ns)
    assert problem is None, f"{where}:{line}: `{cmd}`: {problem}"


def check_overrides(ns: argparse.Namespace) -> str | None:
    """The --set KEY=VALUE of a parsed command checked against the config it overrides (a run config for the
    training tools, the simulator's for the simulator tools): the loader's error, or None when every key exists.
    Placeholder values (upper-case words such as VALUE) are not checked."""
    sets = [o for o in getattr(ns, "overrides", None) or [] if not re.fullmatch(r"[\w.]+=[A-Z_]+", o)]
    if not sets:
        return None
    from detbench.config import ConfigError
    from detbench.utils.cli import UserError
    try:
        if hasattr(ns, "sim_preset"):
            from detbench.sim import load_sim_config
            if hasattr(ns, "lidar"):  # tools/sweep.py: sensor.FIELD=VALUE changes the swept sensor
                from detbench.studies.sweep_sim import split_overrides
                _, sets = split_overrides(sets)
            load_sim_config(ns.sim_preset, overrides=tuple(sets))
        else:
            from detbench.train.run_config import load_run_config
            from models import REGISTRY
            model = getattr(ns, "model", None) or (getattr(ns, "models", None) or ["second"])[0]
            model = model if model in REGISTRY else "second"  # a placeholder (`--model M`): any detector's config
            load_run_config(model, getattr(ns, "preset", None), overrides=sets)
    except (ConfigError, UserError) as e:
        return f"--set {' '.join(sets)}: {e}"
    return None


def help_commands() -> list[tuple[str, str]]:
    """(tool, command) of every example in the tools' --help texts and module docstrings."""
    found = []
    for name in sorted(p.stem for p in (ROOT / "tools").glob("[a-z]*.py")):
        mod = importlib.import_module(f"tools.{name}")
        text = (mod.build_parser().format_help() if hasattr(mod, "build_parser") else "") + "\n" + (mod.__doc__ or "")
        lines = [ln.strip() for ln in text.splitlines()]
        joined, cur = [], ""
        for ln in lines:
            cur = f"{cur} {ln}" if cur else ln
            if cur.endswith("\\"):
                cur = cur[:-1].rstrip()
                continue
            joined.append(cur)
            cur = ""
        for ln in joined:
            if re.match(r"(python3? |torchrun )", ln):
                found.extend((name, c) for c in _segments(ln) if _target(c) is not None)
    return list(dict.fromkeys(found))


HELP_COMMANDS = help_commands()


@pytest.mark.parametrize("tool,cmd", HELP_COMMANDS, ids=[f"{t}:{i}" for i, (t, _) in enumerate(HELP_COMMANDS)])
def test_help_example_parses(tool, cmd, capsys):
    module, argv = _target(cmd)
    argv = _argv(argv)
    if argv is None or module.startswith("?"):
        pytest.skip("elided command (`...`)")
    try:
        ns = parse_with_tool(module, argv)
    except SystemExit as e:
        raise AssertionError(f"tools/{tool}.py --help shows `{cmd}`, which {module}'s parser refuses: "
                             f"{capsys.readouterr().err.strip().splitlines()[-1:]}") from e
    problem = check_overrides(ns)
    assert problem is None, f"tools/{tool}.py --help shows `{cmd}`: {problem}"


def test_a_wrong_flag_fails_the_parse(capsys):
    # the check can fail: a flag no tool has, a choice that does not exist
    with pytest.raises(SystemExit):
        parse_with_tool("tools.train", ["--model", "second", "--height", "1.8", "--no-such-flag"])
    with pytest.raises(SystemExit):
        parse_with_tool("tools.study", ["--preset", "huge"])
    ns = parse_with_tool("tools.sweep", ["--frames", "8", "--sim-preset", "v1"])
    assert ns.sim_preset == "v1" and ns.frames == 8
    # and a --set key the config does not have, for a training tool and for a simulator tool
    assert "no_such_key" in check_overrides(parse_with_tool("tools.train", ["--height", "1.8", "--set",
                                                                            "train.no_such_key=1"]))
    assert check_overrides(parse_with_tool("tools.train", ["--height", "1.8", "--set", "train.epochs=3"])) is None
    assert "no_such_key" in check_overrides(parse_with_tool("tools.simulate", ["--out", "x", "--set",
                                                                                "traffic.no_such_key=1"]))
    assert _argv(["[--resume]", "--set", "k=[1,2]", "[--jobs", "2]"]) == ["--resume", "--set", "k=[1,2]", "--jobs", "2"]
    cmds = _segments("python tools/a.py --x 1 \\\n    --y 2   # note\npython tools/b.py; python tools/c.py && echo hi")
    assert cmds == ["python tools/a.py --x 1 --y 2", "python tools/b.py", "python tools/c.py", "echo hi"]


TOOLS = sorted(p.stem for p in (ROOT / "tools").glob("[a-z]*.py"))


@pytest.mark.parametrize("name", TOOLS)
def test_every_tool_has_help(name, capsys):
    # in-process: the tool's main with --help prints its usage and exits 0
    mod = importlib.import_module(f"tools.{name}")
    with pytest.raises(SystemExit) as e:
        mod.main(["--help"])
    assert e.value.code == 0 and "usage:" in capsys.readouterr().out


@pytest.mark.slow
def test_every_tool_help_runs_as_a_file():
    # each tool's --help as a user runs it (the file, not the module: the checkout-root import path)
    for path in sorted((ROOT / "tools").glob("[a-z]*.py")):
        out = subprocess.run([sys.executable, str(path), "--help"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0 and "usage:" in out.stdout, (path.name, out.stderr[-500:])


def test_python_examples_in_the_guides_run(tmp_path, monkeypatch):
    # the ```python blocks of the guides run as written (in an empty folder: they write data/...)
    monkeypatch.chdir(tmp_path)
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "your-data.md").read_text(), re.S)
    assert blocks
    for code in blocks:
        exec(compile(code, "docs/your-data.md", "exec"), {"__name__": "doc_example"})
    from detbench.data.validate import main as validate
    assert validate([str(tmp_path / "data" / "mine")]) == 0


def test_relative_links_in_the_docs_exist():
    broken = []
    for path in DOCS:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text(encoding="utf-8")):
            if "://" not in target and not (path.parent / target).exists():
                broken.append(f"{path.name}: {target}")
    assert not broken, broken
    for name in ("LICENSE", "CITATION.cff"):
        assert (ROOT / name).is_file(), name


def test_citation_file_states_the_paper_and_the_license():
    import yaml

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT" and cff["authors"]
    paper = cff["preferred-citation"]
    assert paper["title"].startswith("Forehead or Headlights") and paper["authors"] and paper["type"] == "article"
    assert "MIT" in (ROOT / "LICENSE").read_text() and 'license = { text = "MIT" }' in (
        ROOT / "pyproject.toml").read_text()


# ------------------------------------------------------------------ run for real (slow)

def _run(argv: list[str], cwd: Path) -> str:
    out = subprocess.run([sys.executable, *argv], cwd=cwd, capture_output=True, text=True, timeout=900,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, (argv, out.stderr[-2000:])
    return out.stdout


@pytest.mark.slow
def test_readme_tool_chain_runs_at_smoke_size(tmp_path):
    """The README's simulate -> analyze -> train -> eval -> cross-height -> combine -> validate chain, as written
    but at the smoke preset and a few frames (the real sizes take minutes to hours)."""
    t = str(ROOT / "tools")
    _run([f"{t}/simulate.py", "--out", "data/sim", "--frames", "48", "--frames-per-scene", "8", "--heights", "0.5",
          "1.8", "--seed", "0", "--no-progress"], tmp_path)
    _run([f"{t}/validate.py", "data/sim"], tmp_path)
    _run([f"{t}/analyze.py", "--data", "data/sim", "--out", "runs/ability_disk", "--no-figures", "--no-progress"],
         tmp_path)
    _run([f"{t}/train.py", "--model", "second", "--height", "1.8", "--preset", "smoke", "--data", "data/sim",
          "--out", "runs/second_1.8", "--no-progress"], tmp_path)
    ckpts = sorted((tmp_path / "runs/second_1.8/checkpoints").glob("epoch_*.pt"))
    assert ckpts, "train.py wrote no epoch_EEE.pt"
    _run([f"{t}/eval.py", "--ckpt", str(ckpts[-1]), "--no-progress"], tmp_path)
    _run([f"{t}/eval.py", "--ckpt", str(ckpts[-1]), "--test-height", "0.5", "--no-progress"], tmp_path)
    reports = sorted(str(p) for p in (tmp_path / "runs").glob("*/eval_*/report.json"))
    assert len(reports) == 2
    bad = subprocess.run([sys.executable, f"{t}/eval.py", "--combine", *reports, "--out", "runs/combined",
                          "--no-figures"], cwd=tmp_path, capture_output=True, text=True,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert bad.returncode == 2 and "--with-variants" in bad.stderr
    _run([f"{t}/eval.py", "--combine", *reports, "--out", "runs/combined", "--no-figures", "--with-variants"],
         tmp_path)
    assert (tmp_path / "runs/combined/combined.md").is_file()
