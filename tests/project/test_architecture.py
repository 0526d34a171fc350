"""The rules of docs/architecture.md, each checked over the package's source.

The package is a stack of floors (:data:`FLOORS`); a module imports only from its own folder and
from lower floors, the imports form no circle, and a learned method is chosen through the
method registry, never by comparing its kind to a name.  Each test's message says what broke
the rule and how to fix it.
"""

from __future__ import annotations

import ast
import importlib
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import pytest

from articulated_dataset.core import compat
from articulated_dataset.methods.protocol import KINDS
from helpers_core import ROOT

PACKAGE_DIR = ROOT / "articulated_dataset"
PACKAGE = PACKAGE_DIR.name
#: Folder (top-level unit) -> floor, bottom to top (docs/architecture.md).
FLOORS = {"core": 1, "format": 2, "classes": 3, "generation": 4, "ingest": 4, "training": 4, "benchmark": 5,
          "methods": 6, "tools": 6, "manipulation": 7, "cli": 8}
#: At most this many floors (the longest chain of folders importing one another).
MAX_FLOORS = 8
#: Files the package's top folder may hold besides the folders of FLOORS.
TOP_LEVEL_FILES = {"__init__.py", "py.typed"}
#: Third-party modules only cli/ imports.
CLI_ONLY_MODULES = {"click"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE_DIR.rglob("*.py"):
        if "__pycache__" in path.parts:
            continue
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            skip |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return skip


def _imports(module: str, path: Path) -> list[tuple[str, int]]:
    """(imported name, line) of every import the module runs (at load or in a function;
    ``if TYPE_CHECKING:`` blocks excluded)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = _type_checking_nodes(tree)
    base = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base.split(".")
                target = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found += [(f"{target}.{alias.name}", node.lineno) for alias in node.names] + [(target, node.lineno)]
    return found


def _resolve(name: str) -> str | None:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _internal_edges() -> dict[str, dict[str, int]]:
    edges: dict[str, dict[str, int]] = defaultdict(dict)
    for module, path in MODULES.items():
        for name, line in _imports(module, path):
            if name.split(".")[0] != PACKAGE:
                continue
            target = _resolve(name)
            if target and target != module and not module.startswith(target + "."):
                edges[module].setdefault(target, line)
    return edges


EDGES = _internal_edges()


def _unit(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_the_top_folder_holds_only_the_floors():
    loose = sorted(p.name for p in PACKAGE_DIR.iterdir()
                   if p.name not in TOP_LEVEL_FILES and p.name != "__pycache__" and p.name not in FLOORS)
    assert loose == [], (f"{loose}: every module lives in one of the floors' folders {sorted(FLOORS)} "
                         f"(docs/architecture.md); move it there or add its folder to FLOORS and the doc")


def test_every_import_goes_down_the_floors():
    """A module imports its own folder and lower floors only: never a higher floor, never a
    sibling folder on its own floor."""
    broken = []
    for module, targets in sorted(EDGES.items()):
        unit = _unit(module)
        if unit is None:
            continue
        for target, line in sorted(targets.items()):
            other = _unit(target)
            if other is None or other == unit:
                continue
            if FLOORS[other] >= FLOORS[unit]:
                broken.append(f"{MODULES[module].relative_to(PACKAGE_DIR.parent)}:{line} imports {target} "
                              f"(floor {FLOORS[other]} from floor {FLOORS[unit]})")
    assert broken == [], "imports that climb the floors (move the shared code down a floor):\n" + "\n".join(broken)


def test_the_floors_are_at_most_eight():
    assert max(FLOORS.values()) <= MAX_FLOORS and sorted(set(FLOORS.values())) == list(range(1, max(FLOORS.values()) + 1))


def _cycles() -> list[list[str]]:
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(MODULES)))

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in EDGES.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(MODULES):
        if v not in index:
            visit(v)
    return found


def test_no_import_circles():
    """No module imports (at load or inside a function) a module that imports it back."""
    assert _cycles() == [], "modules that import one another (move what they share into a lower module)"


def test_only_the_command_line_imports_click():
    users = sorted(str(path.relative_to(PACKAGE_DIR.parent)) for module, path in MODULES.items()
                   if _unit(module) != "cli"
                   and any(name.split(".")[0] in CLI_ONLY_MODULES for name, _ in _imports(module, path)))
    assert users == [], f"{users}: only cli/ knows the command line"


def test_no_dispatch_on_a_method_kind():
    """Methods are chosen through :func:`articulated_dataset.methods.protocol.get_method`: no
    ``x.kind == "dense"`` chains outside the method's own folder."""
    found = []
    for module, path in MODULES.items():
        parts = module.split(".")
        if parts[1:2] == ["methods"] and len(parts) > 2 and parts[2] in KINDS:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                names = {s.attr if isinstance(s, ast.Attribute) else getattr(s, "id", None) for s in sides}
                literals = {s.value for s in sides if isinstance(s, ast.Constant)}
                if names & {"kind", "model_kind"} and literals & set(KINDS):
                    found.append(f"{path.relative_to(PACKAGE_DIR.parent)}:{node.lineno}")
    assert found == [], f"dispatch on a method's kind (use the method registry's capabilities): {found}"


@pytest.mark.parametrize("old", sorted(compat.MOVED))
def test_an_old_import_path_gives_the_moved_module_with_a_warning(old):
    new = importlib.import_module(f"{PACKAGE}.{compat.MOVED[old]}")
    sys.modules.pop(f"{PACKAGE}.{old}", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(f"{PACKAGE}.{old}")
    assert module is new
    assert any(issubclass(w.category, DeprecationWarning) and compat.MOVED[old] in str(w.message) for w in caught)


def test_every_old_path_points_at_a_module():
    missing = sorted(old for old, new in compat.MOVED.items() if f"{PACKAGE}.{new}" not in MODULES)
    assert missing == [], f"compat.MOVED names modules that do not exist: {missing}"
