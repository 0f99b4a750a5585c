"""Package layout rules (issue 21): stage modules do not import each other (shared helpers live in the
foundation modules, e.g. anidress_core.io), and no module is over 800 lines without saying why at the top."""
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
