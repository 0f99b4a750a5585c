"""Runnable only at git 4491214: it calls fit_sequence with the plan's parts, which now takes the FitPlan (issue 48).

Probe: the pipeline with frame 0 started on the rig floor (the ground truth's best rig pose) and every later frame
chained as usual: how much of the fit's error is frame 0's start? Runs bench_fit with its ``optimum`` row changed so
that only frame 0 takes the oracle's start (``anidress_core.fit.fit_sequence`` is called with ``init`` = the rig
floor of frame 0 and no per-frame starts); the rows' descriptions still name the every-frame oracle. E.g.

    PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/frame0_oracle.py --suite <half of config/fit_heldout.yaml> \\
        --views 8 --methods optimum --no-sim --threads 1 --runs /tmp/frame0 --out /tmp/frame0
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core import fit as FIT  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

_fit_sequence = FIT.fit_sequence


def frame0_only(*args, starts=None, **kwargs):
    """fit_sequence with the oracle's starts dropped: ``init`` (run_fit sets it to ``starts[0]``) starts frame 0."""
    return _fit_sequence(*args, **kwargs)


if __name__ == "__main__":
    FIT.fit_sequence = frame0_only
    bench_fit.PROG = "PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/frame0_oracle.py"
    bench_fit.OPTIMUM_DESCRIPTION = ("probe, not a method: `pipeline` with frame 0 started on the rig floor (the "
                                     "ground truth's best rig pose), later frames chained as usual")
    bench_fit.main()
