"""The layout's rules, checked on the source: no import cycle, and certpose uses only public solvers.

Every import counts, also those inside functions (a lazy import is still a dependency) and those
under ``if TYPE_CHECKING:`` (a type is a dependency too).
"""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("certpose", "solvers")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imports(tree: ast.AST, module: str, is_pkg: bool) -> list[tuple[str, str | None]]:
    """(imported module, imported name) pairs, wherever the import statement is."""
    found: list[tuple[str, str | None]] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((a.name, None) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    pkg = module.split(".") if is_pkg else module.split(".")[:-1]
                    pkg = pkg[: len(pkg) - (child.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                found.extend((base, a.name) for a in child.names)
            visit(child)

    visit(tree)
    return found


def _graph() -> tuple[nx.DiGraph, list[tuple[str, str, str | None]]]:
    mods = _modules()
    g = nx.DiGraph()
    edges = []
    for name, path in mods.items():
        g.add_node(name)
        tree = ast.parse(path.read_text(), filename=str(path))
        for base, attr in _imports(tree, name, path.name == "__init__.py"):
            target = f"{base}.{attr}" if attr and f"{base}.{attr}" in mods else base
            edges.append((name, base, attr))
            if target in mods and target != name:
                g.add_edge(name, target)
    return g, edges


def test_no_import_cycle_between_modules() -> None:
    g, _ = _graph()
    # A package's __init__ re-exporting its own submodules is not a cycle of concerns.
    for u, v in list(g.edges):
        if v.startswith(u + "."):
            g.remove_edge(u, v)
    cycles = list(nx.simple_cycles(g))
    assert not cycles, f"import cycles: {cycles[:5]}"


def test_certpose_uses_only_public_names_of_solvers() -> None:
    _, edges = _graph()
    private = [
        (mod, base, attr)
        for mod, base, attr in edges
        if mod.startswith("certpose")
        and base.startswith("solvers")
        and (
            any(p.startswith("_") for p in base.split("."))
            or (attr is not None and attr.startswith("_"))
        )
    ]
    assert not private, f"certpose imports private names of solvers: {private}"


def test_solvers_never_imports_certpose() -> None:
    _, edges = _graph()
    bad = [(m, b) for m, b, _ in edges if m.startswith("solvers") and b.startswith("certpose")]
    assert not bad, bad


@pytest.mark.parametrize("pkg", [p for p in _modules() if p.count(".") == 1
                                 and (ROOT / p.replace(".", "/") / "__init__.py").exists()])
def test_every_subpackage_says_what_it_owns(pkg: str) -> None:
    path = ROOT / pkg.replace(".", "/") / "__init__.py"
    doc = ast.get_docstring(ast.parse(path.read_text()))
    assert doc and len(doc.split()) >= 15, f"{pkg} has no docstring saying what it owns"
