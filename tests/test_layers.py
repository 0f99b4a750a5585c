"""Package layout rules (issue 21): stage modules do not import each other (shared helpers live in the
foundation modules, e.g. anidress_core.io), no module is over 800 lines without saying why at the top, and tests
and benchmarks use no private (``_``-prefixed) name of another module."""
import ast
from pathlib import Path

import anidress_core

PKG = Path(anidress_core.__file__).parent
MAX_LINES = 800


def test_stage_modules_do_not_import_each_other():
    stages = {p.stem for p in (PKG / "stages").glob("*.py") if p.stem != "__init__"}
    found = []
    for p in sorted((PKG / "stages").glob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                names = {a.name for a in node.names}
                if node.level == 1 and (mod.split(".")[0] in stages or (not mod and names & stages)):
                    found.append(f"{p.name}:{node.lineno} imports .{mod or names}")
                if node.level == 0 and mod.startswith("anidress_core.stages.") and mod.split(".")[2] in stages:
                    found.append(f"{p.name}:{node.lineno} imports {mod}")
    assert not found, found


def test_long_modules_say_why_at_the_top():
    long = []
    for p in sorted(PKG.rglob("*.py")):
        n = len(p.read_text().splitlines())
        if n > MAX_LINES:
            doc = ast.get_docstring(ast.parse(p.read_text())) or ""
            if "over 800 lines" not in "\n".join(doc.splitlines()[:4]):
                long.append(f"{p.relative_to(PKG)}: {n} lines")
    assert not long, f"modules over {MAX_LINES} lines without a reason in the first lines of the docstring: {long}"


# ---- tests and benchmarks import no private name of another module (issue 21)
ROOT = PKG.parent
OWN = ("anidress_core", "tests", "benchmarks")  # the project's own packages


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _is_module(dotted: str) -> bool:
    base = ROOT.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _absolute(rel: Path, node: ast.ImportFrom) -> str:
    """The absolute module name of ``from <node.module> import ...`` in file ``rel`` (a path relative to the
    repository root; relative imports resolved)."""
    if not node.level:
        return node.module or ""
    pkg = list(rel.parent.parts)
    pkg = pkg[: len(pkg) - (node.level - 1)]
    return ".".join(pkg + ([node.module] if node.module else []))


def private_imports(path: Path, rel: Path | None = None) -> list[str]:
    """Every use in ``path`` of a ``_``-prefixed (not dunder) name of one of the project's modules, as
    ``file:line: name``: ``from <own module> import _name`` anywhere in the file (also inside functions), and
    ``alias._name`` where ``alias`` (or a dotted chain from it) is bound in the file to one of the project's
    modules (``import anidress_core.x as alias``, ``from anidress_core import x as alias``, ``from
    anidress_core.x import y`` with ``y`` a module). Attributes of other objects (NamedTuple's ``_replace``,
    ``_asdict`` ...) are not module attributes and are not flagged. ``rel``: the file's path relative to the
    repository root (default: ``path``'s)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    rel = path.relative_to(ROOT) if rel is None else rel
    bound: dict[str, str] = {}  # local name -> module it is bound to
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in OWN:
                    if a.asname:
                        bound[a.asname] = a.name
                    else:
                        bound[a.name.split(".")[0]] = a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            mod = _absolute(rel, node)
            if mod.split(".")[0] not in OWN:
                continue
            for a in node.names:
                if _is_private(a.name) or any(_is_private(p) for p in mod.split(".")):
                    found.append(f"{rel}:{node.lineno}: from {mod} import {a.name}")
                elif _is_module(f"{mod}.{a.name}"):
                    bound[a.asname or a.name] = f"{mod}.{a.name}"

    def module_of(expr) -> str | None:
        if isinstance(expr, ast.Name):
            return bound.get(expr.id)
        if isinstance(expr, ast.Attribute):
            base = module_of(expr.value)
            if base and _is_module(f"{base}.{expr.attr}"):
                return f"{base}.{expr.attr}"
        return None

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            mod = module_of(node.value)
            if mod is not None:
                found.append(f"{rel}:{node.lineno}: {mod}.{node.attr}")
    return sorted(set(found), key=lambda s: (s.split(":")[0], int(s.split(":")[1]), s))


def test_private_imports_finds_each_form(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import anidress_core.geometry as g\n"
        "import anidress_core.stages.validate\n"
        "from anidress_core import raster as R\n"
        "from anidress_core.stages import cues\n"
        "from anidress_core.camera import Cameras, _hidden\n"
        "from .test_rig import _helper\n"
        "x = g._skew(1) + R._pair_crossings() + cues._Prior + anidress_core.stages.validate._check_smpl\n"
        "def f(cams):\n"
        "    from anidress_core.stages.validate import _check_cameras\n"
        "    return cams._replace(K=1), cams._asdict(), g.__name__, Cameras._fields, g.skew\n")
    got = private_imports(probe, rel=Path("tests/probe.py"))
    names = [s.split(": ", 1)[1] for s in got]
    assert names == ["from anidress_core.camera import _hidden", "from tests.test_rig import _helper",
                     "anidress_core.geometry._skew", "anidress_core.raster._pair_crossings",
                     "anidress_core.stages.cues._Prior", "anidress_core.stages.validate._check_smpl",
                     "from anidress_core.stages.validate import _check_cameras"], got


def test_tests_and_benchmarks_import_no_private_name():
    runs = ROOT / "benchmarks" / "runs"  # benchmark outputs (git-ignored), e.g. a reference checkout
    found = [s for d in ("tests", "benchmarks") for p in sorted((ROOT / d).rglob("*.py"))
             if not p.is_relative_to(runs) for s in private_imports(p)]
    assert not found, "private names of another module used by tests/benchmarks:\n" + "\n".join(found)
