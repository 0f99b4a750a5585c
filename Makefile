# Two commands set up a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SNAKEMAKE := $(BIN)/snakemake

.PHONY: venv demo test bench dag clean-results

venv: $(STAMP)

# torch is pinned to 2.13.0 (the CPU build on the project machines).
$(STAMP): envs/requirements.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --disable-pip-version-check -q -r envs/requirements.txt
	$(BIN)/pip install --disable-pip-version-check -q --no-deps -e .
	touch $(STAMP)

demo: venv
	$(SNAKEMAKE) --workflow-profile profiles/default
	@echo "report: $(CURDIR)/results/report.html"

test: venv
	$(BIN)/pytest

# Run-time-vs-error sweeps on the demo scene (builds it first): benchmarks/tradeoffs.{csv,md}.
# The per-stage benchmarks are modules run from the repository root, each writing
# benchmarks/<stage>.{md,csv}: .venv/bin/python -m benchmarks.bench_<stage> --help, for <stage> in
# raster, sim, rig, cues, fit, field, validate (and benchmarks.collect_pipeline after `make demo`);
# their references need envs/requirements-bench.txt. Research probes and findings: studies/.
bench: venv
	$(BIN)/pip install --disable-pip-version-check -q -r envs/requirements-bench.txt
	$(SNAKEMAKE) --workflow-profile profiles/default bench

# Numerical stress tests alone (they also run in `make test`): extreme motions, degenerate
# meshes and sequences, wrong scales, float32 vs float64 (tests/stress).
.PHONY: stress
stress: venv
	$(BIN)/pytest tests/stress

dag: venv
	$(SNAKEMAKE) -n --quiet rules

# SLURM smoke test (root; installs Debian SLURM + envs/requirements-slurm.txt, starts a
# single-node cluster, runs the tiny scene with profiles/slurm, stops it again);
# writes benchmarks/slurm.{md,csv}. SLURM_SMOKE_ARGS: e.g. --keep, --no-reference.
.PHONY: slurm-smoke
slurm-smoke: venv
	bash scripts/slurm-smoke.sh $(SLURM_SMOKE_ARGS)

clean-results:
	rm -rf results logs benchmarks/runs .snakemake
