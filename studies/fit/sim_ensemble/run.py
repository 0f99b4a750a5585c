"""Probe: L_prior's weight with the stiffness ensemble's mean as its reference. Registers ``prior_<w>`` (the
pipeline with L_prior's weight w, for w in 3e3, 3e4, 1e5; ``pipeline`` is the defaults: 1e4 when prior_a/b.md ran,
3e4 since) and runs the
maintained benchmark (benchmarks/bench_fit.py) with its own arguments, e.g.

    PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/run.py --suite <half of config/fit_suite.yaml> \\
        --views 8 --methods pipeline,prior_30000 --no-sim --threads 1 --runs /tmp/prior --out /tmp/prior
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

for w in (3e3, 3e4, 1e5):
    V.VARIANTS[f"prior_{w:g}"] = V.Variant(f"the pipeline with L_prior's weight {w:g}",
                                           lambda c, w=w: c.replace(weights={"prior": w}))

if __name__ == "__main__":
    bench_fit.PROG = "PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/run.py"
    bench_fit.main()
