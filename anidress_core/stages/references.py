"""The committed reference tables the report shows beside a run's outputs (no rule of a run makes them).

Kept apart from :mod:`anidress_core.stages.report` (whose readers import torch) so that
``workflow/rules/report.smk`` names them as inputs while Snakemake parses the workflow without
importing torch: a no-op rerun stays a few seconds (issue 22).
"""
from __future__ import annotations

__all__ = ["REFERENCE_TABLES"]

#: Committed reference tables the report can show (key -> path relative to the working directory).
REFERENCE_TABLES = {"tradeoffs": "benchmarks/tradeoffs.csv", "rig_sweep": "benchmarks/rig.csv"}
