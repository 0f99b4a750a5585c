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
	$(SNAKEMAKE) --workflow-profile config/profiles/default

test: venv
	$(BIN)/pytest

bench: venv
	$(BIN)/python benchmarks/bench_raster.py

dag: venv
	$(SNAKEMAKE) -n --quiet rules

clean-results:
	rm -rf results logs benchmarks/runs .snakemake
