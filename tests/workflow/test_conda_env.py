"""Snakemake conventions for users who deploy with it (issue 24 build item 6).

- envs/anidress.yaml: a conda environment (python, pip, the pins of envs/requirements.txt) and a
  `conda:` directive naming it on every rule that runs Python in a job of its own, so that
  `snakemake --sdm conda` works. Creating the environment needs conda, which the test machines do not
  have (`snakemake -n --sdm conda` stops at "Error running conda info"): checked here are the file and
  the directives, not an environment built from them.
- profiles/default is found by Snakemake itself (beside the Snakefile): plain `snakemake` uses it.
- `snakemake --lint` finds nothing.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
ENV = REPO / "envs" / "anidress.yaml"
# rules that run no Python job of their own: `all` (no action)
NO_ENV = {"all"}


def _rule_blocks() -> dict[str, str]:
    """{rule name: its text} for every rule of the Snakefile and the files it includes."""
    out, todo = {}, [REPO / "Snakefile"]
    while todo:
        f = todo.pop()
        text = f.read_text()
        todo += [(f.parent / m).resolve() for m in re.findall(r"^include:\s*[\"'](.+?)[\"']", text, re.M)]
        for m in re.finditer(r"^rule (\w+):\n((?:[ \t]+.*\n|\n)*)", text, re.M):
            out[m.group(1)] = m.group(2)
    return out


def _pins(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def test_the_env_file_holds_python_pip_and_the_pinned_requirements():
    env = yaml.safe_load(ENV.read_text())
    deps = env["dependencies"]
    assert any(isinstance(d, str) and d.startswith("python=3.11") for d in deps) and "pip" in deps
    pip = next(d["pip"] for d in deps if isinstance(d, dict))
    assert [p for p in pip if not p.startswith("--")] == _pins(REPO / "envs" / "requirements.txt")
    assert "--extra-index-url https://download.pytorch.org/whl/cpu" in pip  # torch's CPU build
    assert "torch==2.13.0" in pip and "conda-forge" in env["channels"]


def test_every_rule_that_runs_python_names_the_env():
    blocks = _rule_blocks()
    assert {"synth", "validate_scene", "undistort", "fit", "train_field", "report", "bench"} <= set(blocks)
    for name, text in blocks.items():
        if name in NO_ENV:
            assert "conda:" not in text
            continue
        assert re.search(r"^    (script|shell):", text, re.M), f"rule {name}: neither script nor shell"
        m = re.search(r"^    conda:\n\s+\"(.+?)\"", text, re.M)
        assert m, f"rule {name}: no conda directive"
        assert m.group(1) == "../../envs/anidress.yaml"  # relative to workflow/rules/
    # the file listings start fast: a script on the standard library, not a `run:` block (a Snakemake process each)
    script = (REPO / "workflow" / "scripts" / "scene_files.py").read_text()
    assert not re.search(r"^\s*run:", blocks["scene_files"], re.M)
    assert not re.search(r"^\s*(import|from) (torch|anidress_core|numpy|snakemake)", script, re.M)


def _snakemake(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def test_the_default_profile_is_found_without_naming_it(tmp_path):
    res = _snakemake(tmp_path, "-n", "--quiet", "rules")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    assert f"Using workflow specific profile {REPO / 'profiles' / 'default'}" in out
    assert not (REPO / "config" / "profiles").exists()


def test_lint_is_clean(tmp_path):
    res = _snakemake(tmp_path, "--lint")
    assert res.returncode == 0 and "Congratulations, your workflow is in a good condition!" in res.stdout + res.stderr, \
        (res.stdout + res.stderr)[-4000:]
