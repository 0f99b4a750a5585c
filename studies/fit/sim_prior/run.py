"""Probe: L_prior towards the rig's simulated pose of the observed motion at every frame
(fit/prior_reference sim), whole or tangential only (fit/prior_tangential), at several weights.

Registers those settings as loss variants ``simprior_<w>`` and ``simprior_t_<w>`` and runs the
maintained benchmark (benchmarks/bench_fit.py) with its own arguments, e.g. on the tuning suite:

    .venv/bin/python studies/fit/sim_prior/run.py --suite config/fit_suite.yaml --views 8 \\
        --methods pipeline,simprior_10000,simprior_t_10000 --threads 1 --out /tmp/simprior
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

WEIGHTS = (1e3, 3e3, 1e4, 3e4, 1e5)

for w in WEIGHTS:
    V.VARIANTS[f"simprior_{w:g}"] = V.Variant(
        f"the pipeline with L_prior towards the simulated pose at every frame, weight {w:g}",
        lambda c, w=w: c.replace(prior_reference="sim", prior_tangential=False, weights={"prior": w}))
    V.VARIANTS[f"simprior_t_{w:g}"] = V.Variant(
        f"the pipeline with tangential L_prior towards the simulated pose at every frame, weight {w:g}",
        lambda c, w=w: c.replace(prior_reference="sim", prior_tangential=True, weights={"prior": w}))

if __name__ == "__main__":
    bench_fit.PROG = ".venv/bin/python studies/fit/sim_prior/run.py"
    bench_fit.main()
