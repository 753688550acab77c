"""The package layout of docs/architecture.md: one-way dependencies, no cycles, sizes.

Imports are read from the source with :mod:`ast` (module-level and function-level alike), so
the check does not depend on what a test run happens to import.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "kautztwin"

# the layers, bottom to top: a layer imports only from layers below it and from the shared
# modules beside them
LAYERS = ["basis", "approx", "ident", "nn", "export", "mpc", "twin", "service", "experiments",
          "cli"]
# modules beside the layers, used by all; they import only from each other and from the
# lowest layers (basis, approx), never from ident upwards
SHARED = {"_validation", "_quadrature", "_json", "exceptions", "metrics", "plotting", "data",
          "datasets", "simulators"}
SHARED_MAY_IMPORT = {"basis", "approx"}
ROOT = {"__init__", "__main__"}

# inside the twin: the paper's modules, bottom to top
TWIN_LAYERS = [
    {"physical", "history", "digital"},
    {"update"},
    {"prediction"},
    {"optimization"},
    {"runtime"},
    {"report", "fleet"},
]


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(["kautztwin", *parts]), path))
    return out


def _imports(name: str, path: Path) -> set[str]:
    """Absolute kautztwin module names imported by the module ``name`` at ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                   for n in ast.walk(node)}
    for node in ast.walk(tree):
        if id(node) in typing_only:  # annotations only: not an import at run time
            continue
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("kautztwin"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("kautztwin"):
                found.add(mod)
    return found


def _top(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _edges() -> list[tuple[str, str]]:
    return [(name, imp) for name, path in _modules() for imp in _imports(name, path)]


def test_layers_point_one_way():
    bad = []
    for src, dst in _edges():
        a, b = _top(src), _top(dst)
        if a == b or a in ROOT or b in ROOT and src.count(".") == 0:
            continue
        if b == "__init__":
            continue  # the public API: basis, approx and metrics (checked below)
        if a in SHARED:
            if b not in SHARED and b not in SHARED_MAY_IMPORT:
                bad.append(f"{src} (shared) imports {dst}")
        elif b in SHARED:
            continue
        elif LAYERS.index(b) > LAYERS.index(a):
            bad.append(f"{src} ({a}) imports {dst} ({b}, a higher layer)")
    assert not bad, "\n".join(bad)


def test_top_level_package_reexports_only_the_core():
    allowed = {"basis", "approx", "metrics", "exceptions", "_validation", "_quadrature"}
    name, path = "kautztwin", SRC / "__init__.py"
    assert {_top(m) for m in _imports(name, path)} - {"__init__"} <= allowed


def test_twin_modules_point_one_way():
    rank = {name: i for i, layer in enumerate(TWIN_LAYERS) for name in layer}
    bad = []
    for src, dst in _edges():
        if not (src.startswith("kautztwin.twin.") and dst.startswith("kautztwin.twin.")):
            continue
        a, b = src.split(".")[2], dst.split(".")[2]
        assert a in rank, f"kautztwin.twin.{a} is not in the architecture's twin layers"
        assert b in rank, f"kautztwin.twin.{b} is not in the architecture's twin layers"
        if a != b and rank[b] > rank[a]:
            bad.append(f"{src} imports {dst} (a later module of the twin)")
    assert not bad, "\n".join(bad)


def test_no_import_cycles_between_modules():
    graph: dict[str, set[str]] = {}
    names = {n for n, _ in _modules()}
    for src, dst in _edges():
        # "from kautztwin.x import y" may name a module y: resolve to the deepest module
        target = dst if dst in names else dst.rpartition(".")[0]
        if target in names and target != src:
            graph.setdefault(src, set()).add(target)
    # a package __init__ re-exports its children: edges parent -> child are expected, and a
    # child that imports its own parent package would be the cycle to catch
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("old", ["plants", "twin/plants.py", "twin/signals.py",
                                 "twin/optimize.py", "twin/digital_model.py"])
def test_one_name_per_room(old):
    # the simulators and the links to plants do not share a word; moved modules stay moved
    assert not (SRC / old).exists()


def _long_without_reason(limit_file: int = 600, limit_class: int = 400) -> list[str]:
    """Modules and classes over the size guide whose docstring has no ``Size:`` paragraph."""
    out = []
    for name, path in _modules():
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text)
        doc = (ast.get_docstring(tree) or "").lower()
        n = len(text.splitlines())
        if n > limit_file and "size:" not in doc:
            out.append(f"{name}: {n} lines and no reason in its docstring")
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                size = node.end_lineno - node.lineno + 1
                cdoc = (ast.get_docstring(node) or "").lower()
                if size > limit_class and "size:" not in cdoc and "size:" not in doc:
                    out.append(f"{name}.{node.name}: {size} lines and no reason given")
    return out


def test_big_modules_and_classes_say_why():
    assert _long_without_reason() == []


def test_every_module_names_its_job():
    missing = [name for name, path in _modules()
               if not ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))]
    assert missing == []
