"""Helpers shared by the benchmark scripts, which run as modules from the repository root:
``.venv/bin/python -m benchmarks.<name> ...``. This module imports no benchmark script; what two scripts
both need lives here, so that no script imports another that imports it back."""
from __future__ import annotations

import csv
import math
import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo, else :func:`platform.processor`, else the machine type."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_rev(paths=("anidress_core",)) -> str:
    """Short HEAD commit of the repository, with " + working tree" when any of ``paths``
    (relative to the repository root) has uncommitted changes; "?" without git."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True).stdout
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *paths], cwd=root, capture_output=True,
                               text=True).stdout
    except OSError:
        return "?"
    return (rev.strip() or "?") + (" + working tree" if dirty.strip() else "")



def cuda_summary(csv_path: Path) -> str:
    """One line for benchmarks/scaling.md (bench_scaling): the CUDA speed-ups at the paper point, from the
    cuda.csv that bench_cuda writes."""
    with open(csv_path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["point"] == "paper"]
    return ", ".join(f"{r['stage']} {float(r['speedup']):.2g}x" for r in rows if math.isfinite(float(r["speedup"])))
