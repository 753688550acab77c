"""Issue 17, case 2: every shell example of README, docs/*.md and the ``--help`` texts runs.

The examples are extracted, not listed by hand: every ``kautztwin ...`` line of a fenced
block of README.md and docs/*.md (a ``$`` prompt is dropped, ``\\`` continuations joined,
``&&`` chains split, ``#`` comments cut) and every line under ``examples:`` in the
description or epilog of each (sub-)command's ``--help``.  The examples of one block (or one
help text) run in order, in-process, in one temporary folder that holds a copy of the
repository's ``data/`` and ``examples/`` -- what a plain clone has -- so a file an example
reads must be shipped or written by an earlier example of the same block.

Sizes are made small where the example allows it (the command has a ``--quick`` variant or a
size flag): ``reproduce`` runs ``--quick`` (marked ``slow``), ``twin run`` runs ``--quick``
without ``--duration`` and with ``--speedup`` at 1000, ``fleet run`` with at most 3 assets for
12 s, ``--grid`` is cut to 30; ``identify --model auto`` (minutes of training) is ``slow``.
Not run:
synopsis lines (``[--flag]``, ``(--a | --b)``, ``...``), long-lived services (``plant serve``,
``twin serve``, anything ending in ``&``; tests/test_twin_serve.py and tests/test_opcua.py run
them), commands for a Ray cluster (``--ray-address``), and lines that are not ``kautztwin``
commands.

On the code before the fix (``d678f0a``) README's ``kautztwin approx data.csv`` and
``kautztwin train --config spec.toml``, docs/cli.md's ``sensitivity run1.csv`` and
``approx data.csv``, docs/nn.md's ``estimate measured.csv`` and the help texts of
``kautztwin``, ``approx`` and ``sensitivity`` named files that a clone does not have.
"""

from __future__ import annotations

import argparse
import glob
import re
import shlex
import shutil
from pathlib import Path

import matplotlib
import pytest

from kautztwin.cli.main import build_parser, main

matplotlib.use("Agg")

REPO_ROOT = Path(__file__).resolve().parent.parent
DOC_FILES = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
_FENCE = re.compile(r"^\s{0,3}(`{3,}|~{3,})\s*([^\s`]*)")
_SYNOPSIS = re.compile(r"\[--|\(--|\.\.\.|\|")
_COMMAND = re.compile(r"^(?:\$ )?(?:\.venv/bin/)?kautztwin \S")
#: prefix of a command whose documented output is an error (exit 2)
FAILS = "!2 "


def _commands(lines: list[str]) -> list[str]:
    """``kautztwin`` command lines among ``lines`` (continuations joined, prompts dropped).

    A ``$ kautztwin ...`` line whose shown output is ``kautztwin: error: ...`` documents an
    error: it is returned with the prefix :data:`FAILS` (it must exit 2).
    """
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not _COMMAND.match(line):
            continue
        while line.endswith("\\") and i < len(lines):
            line = line[:-1].rstrip() + " " + lines[i].strip()
            i += 1
        fails = line.startswith("$ ") and i < len(lines) and lines[i].startswith(
            "kautztwin: error:")
        # a remark after the command, in parentheses, as in "--optimize-poles 3   (a step ...)"
        line = re.sub(r"\s{2,}\(.*$", "", line.removeprefix("$ "))
        out.append(FAILS + line if fails else line)
    return out


def doc_blocks() -> list[tuple[str, list[str]]]:
    """``(where, commands)`` of every fenced block of README and docs with a command.

    A ``python`` block right before a shell block (nothing but prose between them) prepares
    its files: it comes first, as one command ``python:<code>``.
    """
    blocks = []
    for path in DOC_FILES:
        lines = path.read_text(encoding="utf-8").splitlines()
        i = 0
        python: str | None = None
        while i < len(lines):
            if lines[i].startswith("#"):
                python = None  # a new section: the python block does not carry over
            m = _FENCE.match(lines[i])
            if not m:
                i += 1
                continue
            fence, info = m.group(1), m.group(2).lower()
            j = i + 1
            while j < len(lines) and not lines[j].strip().startswith(fence):
                j += 1
            if info in ("python", "py"):
                python = "\n".join(lines[i + 1:j])
            elif info not in ("toml", "json", "text"):  # text: output shown, not an example
                cmds = _commands(lines[i + 1:j])
                if cmds:
                    first = [f"python:{python}"] if python is not None else []
                    blocks.append((f"{path.relative_to(REPO_ROOT)}:{i + 2}", first + cmds))
                python = None
            i = j + 1
    return blocks


def _parsers(parser: argparse.ArgumentParser, name: str):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from _parsers(p, f"{name} {sub}")


def help_blocks() -> list[tuple[str, list[str]]]:
    """``(command --help, commands)`` of the ``examples:`` part of every help text."""
    blocks = []
    seen: set[int] = set()
    for name, parser in _parsers(build_parser(), "kautztwin"):
        if id(parser) in seen:
            continue
        seen.add(id(parser))
        text = "\n".join(t for t in (parser.description, parser.epilog) if t)
        part = text.split("examples:", 1)
        if len(part) == 2:
            cmds = _commands(part[1].splitlines())
            if cmds:
                blocks.append((f"{name} --help", cmds))
    return blocks


def skip_reason(argv: list[str]) -> str | None:
    """Why an example is not run (``None``: it runs)."""
    text = " ".join(argv)
    if _SYNOPSIS.search(text):
        return "synopsis"
    if argv[-1:] == ["&"] or "serve" in argv[1:3]:
        return "long-lived service"
    if "--ray-address" in argv:
        return "needs a running Ray cluster (tests/test_fleet.py starts a local one, slow)"
    return None


def shrink(argv: list[str]) -> list[str]:
    """The example with small sizes, where the command offers them."""
    argv = list(argv)
    if argv[1:2] == ["reproduce"] and "--quick" not in argv:
        argv.append("--quick")
    if argv[1:3] == ["twin", "run"]:
        timed = any("@" in a or ":" in a and not a.startswith("replay:") for a in argv)
        if "--duration" in argv and not timed:  # event times fix the run's length
            i = argv.index("--duration")
            del argv[i:i + 2]
        if "--speedup" in argv:
            argv[argv.index("--speedup") + 1] = "1000"
        small = ("--no-plots", "--no-progress") if timed else ("--quick", "--no-plots",
                                                                "--no-progress")
        argv += [a for a in small if a not in argv]
    if argv[1:3] == ["fleet", "run"]:  # 3 assets for 12 s: identification and closed loop
        for flag, small in (("--assets", 3), ("--duration", 12)):
            if flag in argv:
                i = argv.index(flag) + 1
                argv[i] = str(min(float(argv[i]), small)).removesuffix(".0")
            else:
                argv += [flag, str(small)]
    if "--grid" in argv:
        i = argv.index("--grid") + 1
        argv[i] = str(min(int(argv[i]), 30))
    return argv


def split(line: str) -> list[list[str]]:
    """``a && b`` -> ``[a, b]``, each as argv (``#`` comments cut, globs expanded)."""
    words = shlex.split(line, comments=True)
    out, cur = [], []
    for w in words:
        if w == "&&":
            out.append(cur)
            cur = []
        elif any(c in w for c in "*?[") and glob.glob(w):
            cur += sorted(glob.glob(w))
        else:
            cur.append(w)
    out.append(cur)
    return [c for c in out if c]


BLOCKS = doc_blocks() + help_blocks()


def _runs_something(cmds: list[str]) -> bool:
    """Whether a block holds a line that is run (not only synopsis lines or services)."""
    for line in cmds:
        if line.startswith("python:"):
            continue
        for argv in split(line.removeprefix(FAILS)):
            argv[0] = "kautztwin"
            if not skip_reason(argv):
                return True
    return False


def cases() -> list:
    """One case per block; its ``reproduce`` lines (minutes even with --quick) apart, ``slow``.

    Blocks with nothing to run (synopsis lines, long-lived services, which
    tests/test_twin_serve.py and tests/test_opcua.py run instead) are left out here.
    """
    out = []
    for where, cmds in BLOCKS:
        if not _runs_something(cmds):
            continue
        # reproduce (minutes even with --quick) and identify --model auto (3 structures x 2
        # pole counts x 6 folds of torch training: minutes by design, as the docs say)
        slow = [c for c in cmds if re.search(r"^\S*kautztwin reproduce\b", c)
                or re.search(r"^\S*kautztwin identify\b.*--model auto\b", c)]
        rest = [c for c in cmds if c not in slow]
        if rest:
            out.append(pytest.param(where, rest, id=where))
        out += [pytest.param(where, [c], id=f"{where}:{c.split()[2]}", marks=pytest.mark.slow)
                for c in slow]
    return out


CASES = cases()


def test_examples_are_found():
    """The extraction sees the README, the docs and the help texts."""
    wheres = {w.split(":")[0] for w, _ in BLOCKS}
    assert "README.md" in wheres and "docs/cli.md" in wheres and "docs/twin.md" in wheres
    helps = {w for w, _ in BLOCKS if w.endswith("--help")}
    for cmd in ("kautztwin", "kautztwin approx", "kautztwin sensitivity",
                "kautztwin simulate hydraulic", "kautztwin twin run", "kautztwin twin history"):
        assert f"{cmd} --help" in helps, sorted(helps)


@pytest.mark.parametrize(("where", "cmds"), CASES)
def test_example_block_runs(where, cmds, tmp_path, monkeypatch, capsys):
    """Every example of a block runs (exit 0) from a plain clone, in order."""
    for folder in ("data", "examples"):
        shutil.copytree(REPO_ROOT / folder, tmp_path / folder)
    monkeypatch.chdir(tmp_path)
    ran = 0
    for line in cmds:
        if line.startswith("python:"):  # the python block that writes the shell block's files
            exec(compile(line[7:], where, "exec"), {"__name__": "__docs__", "REPO_ROOT": REPO_ROOT})
            continue
        expected = 2 if line.startswith(FAILS) else 0
        for argv in split(line.removeprefix(FAILS)):
            argv[0] = "kautztwin"
            if skip_reason(argv):
                continue
            argv = shrink(argv)
            code = main(argv[1:])
            err = capsys.readouterr().err
            assert code == expected, f"{where}: {shlex.join(argv)} exited {code}:\n{err}"
            assert "unexpected" not in err and "Traceback" not in err, err
            ran += 1
    assert ran > 0, f"{where}: no example was run"
