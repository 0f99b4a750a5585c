"""The maintained benchmark scripts (benchmarks/, run as ``python -m benchmarks.<name>``) import
and parse their arguments: a change of the package's API that breaks one shows here, not at its
next (long) run. The runs themselves are not tests."""
from __future__ import annotations

import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: every script with a command line: the per-stage benchmarks and the pipeline collector
#: (bench_sim_newton is bench_sim's reference, called from it)
SCRIPTS = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py")
                 if p.stem.startswith("bench_") and p.stem != "bench_sim_newton") + ["collect_pipeline"]


def test_every_stage_has_a_benchmark():
    stages = {"raster", "sim", "rig", "cues", "fit", "field", "validate"}
    assert {f"bench_{s}" for s in stages} <= set(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_benchmark_parses_help(name, monkeypatch, capsys):
    mod = importlib.import_module(f"benchmarks.{name}")
    monkeypatch.setattr("sys.argv", [f"benchmarks.{name}", "--help"])
    with pytest.raises(SystemExit) as exit_:
        mod.main()
    assert exit_.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_sim_reference_imports():
    mod = importlib.import_module("benchmarks.bench_sim_newton")
    assert callable(mod.run_newton)
