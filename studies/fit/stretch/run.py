"""Probe: L_stretch (fit/weights/stretch, anidress_core.fit.terms.stretch) and the settings around it.

Registers loss variants and runs the maintained benchmark (benchmarks/bench_fit.py) with its own arguments:
``stretch_<w>`` (the pipeline with L_stretch's weight w); with L_stretch at its default,
``stretch_prior_<w>``, ``stretch_flow_<w>``, ``stretch_normal_<w>`` (that term's weight w),
``stretch_iters_10`` (10 loss evaluations per frame t > 0) and ``stretch_images_only`` (no L_prior, no L_flow).
E.g. on half of the tuning suite:

    .venv/bin/python studies/fit/stretch/run.py --suite <half of config/fit_suite.yaml> --views 8 \\
        --methods pipeline_no_stretch,stretch_100,stretch_1000 --threads 1 --reuse --out /tmp/stretch
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

for w in (100.0, 300.0, 1000.0, 3000.0):
    V.VARIANTS[f"stretch_{w:g}"] = V.Variant(f"the pipeline with L_stretch, weight {w:g}",
                                             lambda c, w=w: c.replace(weights={"stretch": w}))
for w in (1e3, 3e3, 3e4):
    V.VARIANTS[f"stretch_prior_{w:g}"] = V.Variant(f"the pipeline (L_stretch 300) with L_prior's weight {w:g}",
                                                   lambda c, w=w: c.replace(weights={"prior": w}))
for w in (1.0, 10.0):
    V.VARIANTS[f"stretch_flow_{w:g}"] = V.Variant(f"the pipeline (L_stretch 300) with L_flow's weight {w:g}",
                                                  lambda c, w=w: c.replace(weights={"flow": w}))
for w in (100.0, 1000.0):
    V.VARIANTS[f"stretch_normal_{w:g}"] = V.Variant(f"the pipeline (L_stretch 300) with L_normal's weight {w:g}",
                                                    lambda c, w=w: c.replace(weights={"normal": w}))
V.VARIANTS["stretch_iters_10"] = V.Variant("the pipeline (L_stretch 300) with 10 loss evaluations per frame t > 0",
                                           lambda c: c.replace(max_iters=10))
V.VARIANTS["stretch_images_only"] = V.Variant("the pipeline (L_stretch 300) without L_prior and L_flow",
                                              lambda c: c.replace(weights={"prior": 0.0, "flow": 0.0}))

if __name__ == "__main__":
    bench_fit.PROG = ".venv/bin/python studies/fit/stretch/run.py"
    bench_fit.main()
