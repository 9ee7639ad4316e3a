"""What README.md and docs/*.md say holds against the tree and against each other.

- The results page is a summary a user reads in two screens, the README a front page: line limits.
- The docs tell the present: no dev-log words (first person, "was", "now", "today", "bug", issue
  numbers ...) outside docs/results-archive.md, the dated record of past runs.
- Every module path (`detbench/...`, `tools/x.py`) and dotted name (`detbench.eval.evaluate`) the docs
  name exists, so a module that moves or goes takes its mentions with it.
- Every link to a section (`file.md#anchor`) names a heading that exists.
- The README's tables of figures agree, cell for cell, with docs/results.md, where the figures live.
- No install command in the docs replaces the editable install with a regular one.
"""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from tests.helpers import ROOT

ARCHIVE = "results-archive.md"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
CURRENT = [p for p in DOCS if p.name != ARCHIVE]

# Paths the docs name that are not this repository's: OpenPCDet's files and the example detector of
# docs/add-a-detector.md. `detbench/configs` is where configs/ is installed (pyproject.toml maps it).
FOREIGN_PATHS = {"docs/CUSTOM_DATASET_TUTORIAL.md", "tools/cfgs/dataset_configs/custom_dataset.yaml", "tools/test.py",
                 "tests/models/test_mydet.py", "detbench/configs"}
FOREIGN_NAMES = {"detbench.configs"}

# Words of a lab notebook, not of documentation in the present tense. "I" only as a word of its own
# (not "Table I"); "fixed" only as a verb (a fixed count is a count that does not change).
DEV_LOG = [
    (re.compile(r"(?<!Table )(?<!Tables )\bI\b"), "first person"),
    (re.compile(r"\b(?:we|We|our|Our|us)\b"), "first person"),
    (re.compile(r"\b(?:today|yesterday|now|this session|no longer|anymore|used to)\b", re.I), "time of writing"),
    (re.compile(r"\b(?:was|were)\b", re.I), "past tense"),
    (re.compile(r"\bbugs?\b", re.I), "dev-log"),
    (re.compile(r"\bfixed\b(?!\s+(?:count|number|size|seed|grid|keys|point|process|order|budget|set|rate))", re.I),
     "dev-log"),
    (re.compile(r"(?:\bissue\s*#?\d+|(?<![\w&/])#\d+\b)", re.I), "issue number"),
]


def prose_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of a Markdown file outside fenced code blocks, inline code removed."""
    out, fenced = [], False
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.lstrip("> ").startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.append((n, re.sub(r"`[^`]*`", "``", line)))
    return out


def test_the_results_page_and_the_readme_are_short():
    assert len((ROOT / "docs" / "results.md").read_text().splitlines()) <= 400
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def dev_log_words(path: Path) -> list[str]:
    """Each dev-log word of a file's prose as "file:line: why: word" (a phrase may span two lines)."""
    lines = prose_lines(path)
    text = "\n".join(line for _, line in lines)
    found = []
    for rx, why in DEV_LOG:
        for m in rx.finditer(text):
            n = lines[text.count("\n", 0, m.start())][0]
            found.append(f"{path.name}:{n}: {why}: {m.group(0)!r}")
    return found


@pytest.mark.parametrize("path", CURRENT, ids=[p.name for p in CURRENT])
def test_no_dev_log_words(path):
    found = dev_log_words(path)
    assert not found, "\n".join(found)


def test_the_dev_log_check_can_fail(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("The bug was fixed today (#44).\nTable I and a fixed\ncount are fine.\n```\nI was here\n```\n")
    hits = dev_log_words(page)
    assert [h.split(": ")[1] for h in hits] == ["time of writing", "past tense", "dev-log", "dev-log", "issue number"]
    assert all(h.startswith("page.md:1:") for h in hits)


PATH = re.compile(r"(?<![\w./-])((?:detbench|models|tools|tests|configs|docs)/[\w./<>-]*[\w>])")
PLACEHOLDER = re.compile(r"<\w+>|\b[A-Z]{2,}\b")  # `configs/<model>.yaml`, `configs/presets/NAME.yaml`
NAME = re.compile(r"(?<![\w./-])((?:detbench|models)(?:\.\w+)+)")


def named_paths_and_names(path: Path):
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        for m in PATH.finditer(line):
            if not PLACEHOLDER.search(m.group(1)):
                yield n, "path", m.group(1).rstrip(".")
        for m in NAME.finditer(line):
            yield n, "name", m.group(1).rstrip(".")


def _exists(kind: str, ref: str) -> bool:
    if kind == "path":
        return ref in FOREIGN_PATHS or (ROOT / ref).exists() or (ROOT / f"{ref}.py").exists()
    if ref in FOREIGN_NAMES:
        return True
    parts = ref.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


@pytest.mark.parametrize("path", CURRENT, ids=[p.name for p in CURRENT])
def test_every_module_the_docs_name_exists(path):
    missing = [f"{path.name}:{n}: {kind} {ref}" for n, kind, ref in named_paths_and_names(path)
               if not _exists(kind, ref)]
    assert not missing, "\n".join(missing)


def test_the_module_check_can_fail():
    assert _exists("name", "detbench.studies.calibration.check_counts") and _exists("path", "tools/eval.py")
    assert not _exists("name", "detbench.eval.calibration") and not _exists("path", "detbench/eval/calibration.py")
    page = ROOT / "docs" / "add-a-detector.md"
    refs = {ref for _, _, ref in named_paths_and_names(page)}
    assert "models/__init__.py" in refs and not any("<" in r or "NAME" in r for r in refs)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose_lines(path):
        m = re.match(r"#{1,6}\s+(.*)", line)
        if m:
            base = slug(m.group(1))
            k = seen.get(base, 0)
            seen[base] = k + 1
            out.add(base if k == 0 else f"{base}-{k}")
    return out


def test_links_to_sections_name_existing_headings():
    broken = []
    for path in DOCS:
        for target, anchor in re.findall(r"\]\(([^)#\s]*)#([^)\s]+)\)", path.read_text(encoding="utf-8")):
            page = path if not target else (path.parent / target)
            if page.suffix == ".md" and page.exists() and anchor not in anchors(page):
                broken.append(f"{path.name}: {target}#{anchor}")
    assert not broken, broken
    assert slug("Speed / accuracy trade") == "speed--accuracy-trade"
    assert slug("Do the presets' splits represent the world?") == "do-the-presets-splits-represent-the-world"


def tables(path: Path) -> list[list[dict[str, str]]]:
    """The Markdown tables of a file outside code blocks, each a list of rows {header: cell}."""
    out, rows, header, fenced = [], [], None, False
    for line in path.read_text(encoding="utf-8").splitlines() + [""]:
        if line.startswith("```"):
            fenced = not fenced
        if line.startswith("|") and not fenced:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header = cells
            elif not all(re.fullmatch(r":?-+:?", c) for c in cells):
                rows.append(dict(zip(header, cells)))
            continue
        if header is not None and rows:
            out.append(rows)
        rows, header = [], None
    return out


def test_the_readmes_figures_are_the_results_pages():
    results = tables(ROOT / "docs" / "results.md")
    checked = 0
    for table in tables(ROOT / "README.md"):
        cols = list(table[0])
        twin = [t for t in results if set(cols) <= set(t[0])]
        assert twin, f"README table with columns {cols} has no table in docs/results.md with those columns"
        for row in table:
            key = {c: row[c] for c in cols if c.lower() in ("detector", "height", "level", "range")} or {
                cols[0]: row[cols[0]]}
            match = [r for t in twin for r in t if all(r[c] == v for c, v in key.items())]
            assert match, f"README row {key} is not in docs/results.md"
            assert any(all(r[c] == row[c] for c in cols) for r in match), (
                f"README row {row} differs from docs/results.md's {match[0]}")
            checked += 1
    assert checked >= 20  # the ability table, the detector table and the latency table


def test_no_install_replaces_the_editable_one():
    regular = re.compile(r"pip install (?:--quiet )?(?:\.\[|\.(?=[\s`'\"]|$)|'\.\[)")
    found = [f"{p.name}:{n}" for p in DOCS for n, line in enumerate(p.read_text().splitlines(), 1)
             if regular.search(line)]
    assert not found, found
    assert regular.search("pip install .[cluster]") and regular.search("pip install .")
    assert not regular.search("pip install -e '.[cluster]'")
