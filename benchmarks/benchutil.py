"""Helpers shared by the benchmark scripts. They run as ``python benchmarks/<name>.py``, so
this folder is on ``sys.path`` and the module imports by its name."""
from __future__ import annotations

import platform


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
