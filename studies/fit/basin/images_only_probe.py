"""Probe: the per-frame image loss's minimum near the truth: no L_prior, no L_flow, every frame started on the rig floor."""
import sys
from anidress_core.fit.variants import VARIANTS, Variant
VARIANTS["probe_images_only"] = Variant("probe: no L_prior, no L_flow",
                                        lambda c: c.replace(weights={"prior": 0.0, "flow": 0.0}))
import benchmarks.bench_fit as B
B.OPTIMUM_OF = "probe_images_only"
sys.argv = ["bench_fit"] + sys.argv[1:]
B.main()
