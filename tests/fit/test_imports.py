"""No import circle inside anidress_core.fit: every import (top level, inside functions, under TYPE_CHECKING)
of every module of the package, read with ast, as edges between the package's modules."""
from __future__ import annotations

import ast
from pathlib import Path

import anidress_core

BASE = Path(anidress_core.__file__).parent.parent  # the folder holding anidress_core


def modules(package: str, base: Path, skip: tuple[str, ...] = ()) -> dict[str, Path]:
    """Dotted name -> file of every module of ``package`` under ``base`` (a package is its __init__.py), leaving
    out the sub-folders named in ``skip``."""
    out = {}
    for p in sorted((base / package.replace(".", "/")).rglob("*.py")):
        parts = p.relative_to(base).with_suffix("").parts
        if set(parts[1:-1]) & set(skip):
            continue
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that module ``name`` imports anywhere in its file; ``from X import Y``
    counts as X.Y when that is a module, else as X."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[:len(base) - node.level + (1 if is_pkg else 0)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module
            for a in node.names:
                out.add(f"{src}.{a.name}" if f"{src}.{a.name}" in known else src)
    return {m for m in out if m in known and m != name}


def cycles(package: str, base: Path = BASE, skip: tuple[str, ...] = ()) -> list[list[str]]:
    """The import circles among the modules of ``package``: the strongly connected components of more than
    one module, each sorted."""
    mods = modules(package, base, skip)
    graph = {m: imports(m, p, set(mods)) for m, p in mods.items()}
    index, low, stack, on, comps = {}, {}, [], set(), []

    def visit(v):  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return comps


def test_no_import_circle_in_the_fit():
    assert cycles("anidress_core.fit") == []


def test_no_import_circle_in_the_package():
    """The same check over all of anidress_core (issue 48: "the same check holds for the whole tree")."""
    assert cycles("anidress_core") == []


def test_no_import_circle_in_the_benchmarks():
    """And over benchmarks/ (its git-ignored runs/, which holds other commits' checkouts, left out)."""
    assert cycles("benchmarks", skip=("runs",)) == []


def test_the_check_sees_a_circle(tmp_path):
    """The check finds a circle through an import inside a function and one under TYPE_CHECKING."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from .b import g\n")
    (pkg / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n")
    (pkg / "c.py").write_text("from . import a\n")
    assert cycles("pkg", tmp_path) == [["pkg.a", "pkg.b"]]
