"""Parsing the workflow imports no torch, so that a no-op rerun takes about a second (issue 22: <= 5 s).

The rules' parse-time and DAG-time helpers use light modules (anidress_core.config,
anidress_core.resources); anidress_core.fit.variants (torch) is imported only where a loss
variant other than the default must be checked, anidress_core.io.scene only for a captured scene.
Measured on the tiny run with profiles/default (README/issue 22): 2.3 s -> 1.0 s per no-op run.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time

import yaml

from tests.workflow.tiny import REPO, TINY, snakemake, snakemake_cmd

NOOP_LIMIT_S = 5.0  # issue 22's bound; measured about 1 s on the tiny run (2-core machine)


def _imported_modules(cmd: list[str]) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``cmd`` (a ``python -m snakemake ...`` command) with -X importtime: the result and every module imported."""
    res = subprocess.run([cmd[0], "-X", "importtime", *cmd[1:]], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
    mods = {ln.rsplit("|", 1)[1].strip() for ln in res.stderr.splitlines() if ln.startswith("import time:")}
    return res, mods


def test_the_demo_config_parses_without_torch(tmp_path):
    """The default config (config/config.yaml, synthetic scenes not built yet): a dry run of everything."""
    cmd = [sys.executable, "-m", "snakemake", "-n", "--quiet", "rules", "-s", str(REPO / "Snakefile"),
           "--directory", str(tmp_path), "--cores", "2"]
    res, mods = _imported_modules(cmd)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert "synth" in res.stdout + res.stderr and "anidress_core.config" in mods
    assert "torch" not in mods, sorted(m for m in mods if m.startswith("anidress_core"))


def test_a_noop_rerun_is_fast_and_imports_no_torch(tiny_run):
    res, mods = _imported_modules(snakemake_cmd(tiny_run, "-n"))
    assert res.returncode == 0 and "Nothing to be done" in res.stdout + res.stderr, res.stderr[-2000:]
    assert "torch" not in mods and "anidress_core.fit.variants" not in mods
    t0 = time.perf_counter()  # a real no-op run with the workstation profile (its rerun triggers)
    res = snakemake(tiny_run, "--workflow-profile", str(REPO / "profiles" / "default"))
    wall = time.perf_counter() - t0
    assert res.returncode == 0 and "Nothing to be done" in res.stdout + res.stderr, res.stderr[-2000:]
    assert wall <= NOOP_LIMIT_S, f"no-op rerun took {wall:.1f} s"


def test_a_non_default_loss_variant_is_checked_at_parse(tiny_run):
    """fit/ablations names are checked while parsing (importing the variants then), an unknown one refused."""
    cfg = dict(TINY, fit={**TINY["fit"], "ablations": ["paper", "no_such_loss"]})
    (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    try:
        res = snakemake(tiny_run, "-n")
        cfg["fit"]["ablations"] = ["paper"]
        (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(cfg))
        ok = snakemake(tiny_run, "-n", "--quiet", "rules")
    finally:
        (tiny_run / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    assert res.returncode != 0 and "unknown loss variant 'no_such_loss'" in res.stdout + res.stderr
    assert ok.returncode == 0 and "fit_ablation" in ok.stdout + ok.stderr, ok.stderr[-2000:]


def test_the_default_variant_the_rules_skip_checking_is_a_variant():
    from anidress_core.fit.variants import VARIANTS

    smk = (REPO / "workflow" / "rules" / "helpers" / "fit.smk").read_text()
    schema = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
    default = schema["properties"]["fit"]["properties"]["loss"]["default"]
    assert f'_DEFAULT_FIT_VARIANT = "{default}"' in smk and default in VARIANTS
