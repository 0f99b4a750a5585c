"""Stage runners: read inputs, call the math of one stage, write its artifacts.

This layer (with :mod:`anidress_core.cli`) is the only part of the package that
touches files besides :mod:`anidress_core.io`; the Snakemake scripts and the
``anidress`` command both call these functions.
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

__all__ = ["setup_logging"]


def setup_logging(log_file: str | Path | None = None, level: int = logging.INFO) -> logging.Logger:
    """Log ``anidress.*`` messages to stderr and, if given, to ``log_file`` (created)."""
    logger = logging.getLogger("anidress")
    logger.setLevel(level)
    for h in list(logger.handlers):
        logger.removeHandler(h)
    fmt = logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s", "%H:%M:%S")
    stream = logging.StreamHandler(sys.stderr)
    stream.setFormatter(fmt)
    logger.addHandler(stream)
    if log_file:
        Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_file, mode="w")
        fh.setFormatter(fmt)
        logger.addHandler(fh)
    logger.propagate = False
    return logger
