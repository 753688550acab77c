"""The documentation's Python examples run, and the API reference covers the public API.

Every fenced ```python block of README.md and docs/*.md is executed on its own,
in a fresh namespace, with the working directory set to a temporary folder.
A block can reach files of the repository through the injected name
``REPO_ROOT`` (a :class:`pathlib.Path`).  Blocks in other languages (``bash``,
``console``, ``text``) are not run.
"""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib
import pytest

import kautztwin

matplotlib.use("Agg")

REPO_ROOT = Path(__file__).resolve().parent.parent
DOC_FILES = [
    p for p in [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))] if p.is_file()
]

_FENCE = re.compile(r"^(?P<indent>[ ]{0,3})(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^\n`]*)$")


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """``(first line number, code)`` of every fenced block tagged ``python`` or ``py``."""
    blocks: list[tuple[int, str]] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, info = m["fence"], m["info"].strip().split()
        start = i + 1
        j = start
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        if info and info[0].lower() in ("python", "py"):
            n = len(m["indent"])  # an indented fence indents its content as well
            code = "\n".join(ln[n:] if ln[:n].isspace() else ln for ln in lines[start:j])
            blocks.append((start + 1, code))
        i = j + 1
    return blocks


CASES = [(path, line, code) for path in DOC_FILES for line, code in python_blocks(path)]


def test_docs_have_examples():
    assert any(path.parent.name == "docs" for path, _, _ in CASES), "no python blocks in docs/*.md"


@pytest.mark.parametrize(
    ("path", "line", "code"),
    CASES,
    ids=[f"{path.relative_to(REPO_ROOT)}:{line}" for path, line, _ in CASES],
)
def test_python_block_runs(path: Path, line: int, code: str, tmp_path: Path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # pad with blank lines so tracebacks show the line number inside the markdown file
    source = "\n" * (line - 1) + code
    namespace = {"__name__": "__docs__", "REPO_ROOT": REPO_ROOT}
    try:
        exec(compile(source, str(path), "exec"), namespace)
    finally:
        import matplotlib.pyplot as plt

        plt.close("all")


def test_api_reference_covers_public_names():
    """docs/api.md has a heading for every name in ``kautztwin.__all__``."""
    text = (REPO_ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    headings = {
        m.group(1)
        for m in re.finditer(r"^#{2,4} .*?`(?:kautztwin\.)?([A-Za-z_][A-Za-z0-9_]*)", text, re.M)
    }
    missing = sorted(set(kautztwin.__all__) - headings)
    assert not missing, f"docs/api.md has no section for: {', '.join(missing)}"
