"""Where the files the package reads at run time live: the config schema and the report templates.

Each file exists ONCE in the repository, where the workflow reads it:
``workflow/schemas/config.schema.yaml`` (Snakemake's ``common.smk`` validates against it)
and ``reports/`` (``report.html.j2``, ``captions/``). An installed package (a regular,
non-editable ``pip install .``) carries the same files as package data,
``anidress_core/_data/schemas/`` and ``anidress_core/_data/reports/``: ``setup.py`` maps
those two packages onto the repository folders (``package_dir``), so the wheel copies
them at build time and the source tree holds no second copy that could drift.

Lookup order: the source checkout (this package's parent folder holds ``workflow/`` and
``reports/``: a clone, an editable install), else the installed package data
(:mod:`importlib.resources`).
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["REFERENCE_TABLES", "schema_path", "report_template_dir"]

_SOURCE_ROOT = Path(__file__).resolve().parent.parent

#: The committed reference tables the report shows beside a run's outputs (no rule of a run
#: makes them): key -> path relative to the working directory. Here, in a module without torch,
#: so that workflow/rules/helpers/report.smk names them as inputs at parse time cheaply.
REFERENCE_TABLES = {"tradeoffs": "benchmarks/tradeoffs.csv", "rig_sweep": "benchmarks/rig.csv"}


def _locate(source_rel: str, data_rel: str) -> Path:
    src = _SOURCE_ROOT / source_rel
    if src.exists():
        return src
    installed = resources.files("anidress_core").joinpath("_data", *data_rel.split("/"))
    if installed.is_file() or installed.is_dir():
        return Path(str(installed))
    raise FileNotFoundError(
        f"{source_rel} not found: neither in the source checkout ({src}) nor in the installed package "
        f"(anidress_core/_data/{data_rel}); reinstall the package (pip install .) from a full checkout"
    )


def schema_path() -> Path:
    """``config.schema.yaml``: the checkout's ``workflow/schemas/``, else the installed package's copy."""
    return _locate("workflow/schemas/config.schema.yaml", "schemas/config.schema.yaml")


def report_template_dir() -> Path:
    """The folder holding ``report.html.j2``: the checkout's ``reports/``, else the installed package's copy."""
    return _locate("reports", "reports")
