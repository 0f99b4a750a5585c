"""The SLURM profile (profiles/slurm) against the workflow's rules and the SLURM executor plugin.

SLURM itself is not run here (no daemons in CI): scripts/slurm-smoke.sh does that.
"""
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
PROFILE = REPO / "profiles" / "slurm" / "config.yaml"

# Resources snakemake-executor-plugin-slurm 2.8 turns into sbatch options (runtime -> -t,
# mem_mb -> --mem, cpus_per_task -> --cpus-per-task, gpu -> --gpus, ...), plus Snakemake's own.
PLUGIN_RESOURCES = {
    "runtime", "mem_mb", "mem_mb_per_cpu", "cpus_per_task", "cpus_per_gpu", "gpu", "gpu_model", "gres",
    "slurm_partition", "slurm_account", "slurm_extra", "constraint", "qos", "nodes", "tasks", "tasks_per_gpu",
    "tasks_per_node", "mpi", "clusters", "slurm_cluster",
}
SNAKEMAKE_RESOURCES = {"mem", "disk", "disk_mb", "tmpdir"}
REQUIRED = ("runtime", "mem_mb", "cpus_per_task")


def _included_files(snakefile: Path) -> list[Path]:
    """The Snakefile and every file it includes (recursively), as Snakemake reads them."""
    out, todo = [], [snakefile]
    while todo:
        f = todo.pop()
        out.append(f)
        for m in re.finditer(r"^include:\s*[\"'](.+?)[\"']", f.read_text(), re.M):
            todo.append((f.parent / m.group(1)).resolve())
    return out


def _workflow_rules() -> tuple[set[str], set[str]]:
    """(rules, localrules) declared by the workflow's Snakefile and includes."""
    rules, local = set(), set()
    for f in _included_files(REPO / "Snakefile"):
        text = f.read_text()
        rules |= set(re.findall(r"^(?:rule|checkpoint)\s+(\w+)\s*:", text, re.M))
        for m in re.finditer(r"^localrules:\s*(.+)$", text, re.M):
            local |= {n.strip() for n in m.group(1).split("#")[0].split(",") if n.strip()}
    return rules, local


@pytest.fixture(scope="module")
def profile():
    prof = yaml.safe_load(PROFILE.read_text())
    assert isinstance(prof, dict), f"{PROFILE}: not a YAML mapping"
    return prof


def test_rule_parser_finds_the_workflow_rules():
    rules, _ = _workflow_rules()
    assert {"all", "synth", "template", "motions", "simulate", "rig"} <= rules


def test_profile_globals_select_the_slurm_executor(profile):
    assert profile["executor"] == "slurm"
    assert isinstance(profile["jobs"], int) and profile["jobs"] > 0
    default = profile["default-resources"]
    for key in REQUIRED:
        assert isinstance(default[key], int) and default[key] > 0, f"default-resources {key}: {default.get(key)!r}"
    assert set(default) <= PLUGIN_RESOURCES | SNAKEMAKE_RESOURCES, set(default) - PLUGIN_RESOURCES


def test_profile_names_only_rules_of_the_workflow(profile):
    rules, _ = _workflow_rules()
    for section in ("set-resources", "set-threads"):
        unknown = set(profile.get(section) or {}) - rules
        assert not unknown, f"{PROFILE} {section} names rules the workflow does not have: {sorted(unknown)}"


def test_every_rule_declares_runtime_memory_and_cpus(profile):
    rules, local = _workflow_rules()
    res, threads = profile.get("set-resources") or {}, profile.get("set-threads") or {}
    for rule in sorted(rules - local - {"all"}):
        entry = res.get(rule)
        assert entry, f"{PROFILE}: no set-resources entry for rule {rule}"
        for key in REQUIRED:
            v = entry.get(key)
            assert isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{rule}: {key} = {v!r}"
        gpu = entry.get("gpu", 0)
        assert isinstance(gpu, int) and gpu >= 0, f"{rule}: gpu = {gpu!r}"
        unknown = set(entry) - PLUGIN_RESOURCES - SNAKEMAKE_RESOURCES
        assert not unknown, f"{rule}: resources the SLURM plugin does not know: {sorted(unknown)}"
        # SLURM allocates cpus_per_task CPUs; Snakemake runs the job with `threads`
        assert threads.get(rule) == entry["cpus_per_task"], (
            f"{rule}: set-threads {threads.get(rule)} != cpus_per_task {entry['cpus_per_task']}")


@pytest.mark.skipif(importlib.util.find_spec("snakemake_executor_plugin_slurm") is None,
                    reason="snakemake-executor-plugin-slurm not installed (envs/requirements-slurm.txt)")
def test_snakemake_accepts_the_profile_in_a_dry_run(tmp_path):
    """Snakemake parses every profile key (plugin settings included) and plans the tiny scene."""
    (tmp_path / "tiny.yaml").write_text((REPO / "scripts" / "slurm" / "tiny.yaml").read_text())
    cmd = [sys.executable, "-m", "snakemake", "data/tinyskirt", "results/tinyskirt/rig.npz", "-s", str(REPO / "Snakefile"),
           "--directory", str(tmp_path), "--configfile", str(tmp_path / "tiny.yaml"),
           "--workflow-profile", str(PROFILE.parent), "-n", "--quiet", "rules"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    counts = {p[0]: int(p[1]) for p in (ln.split() for ln in out.splitlines()) if len(p) == 2 and p[1].isdigit()}
    assert counts.get("simulate") == 2 and counts.get("rig") == 1 and counts.get("synth") == 1, counts
