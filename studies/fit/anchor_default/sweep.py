"""Probe: the fit's weights re-chosen for L_anchor on image references (issue 48 item 4).

Registers loss variants around the defaults (config/config.yaml, the schema) and runs the maintained benchmark
(benchmarks/bench_fit.py) with its own arguments: ``img_anchor_<w>`` (L_anchor's weight w),
``img_anchor_scale_<s>`` (its Cauchy scale s), ``img_normal_<w>``, ``img_prior_<w>`` (that term's weight w) and
``img_prior_100000_anchor_scale_0.1`` (both). The weights are absolute: after a default changes, a variant at the
new default is the pipeline itself. Run on the tuning suite only (config/fit_suite.yaml, --seed 23), e.g. one
half of it:

    .venv/bin/python studies/fit/anchor_default/sweep.py --suite <half of config/fit_suite.yaml> --views 4 \\
        --methods pipeline,pipeline_texture_anchor,img_anchor_30000 --no-sim --threads 1 --reuse --out /tmp/sweep
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402


def _weight(term: str, w: float) -> V.Variant:
    return V.Variant(f"the pipeline (image references) with L_{term}'s weight {w:g}",
                     lambda c: c.replace(weights={term: w}))


for _w in (3e4, 3e5):
    V.VARIANTS[f"img_anchor_{_w:g}"] = _weight("anchor", _w)
for _w in (100.0, 1000.0):
    V.VARIANTS[f"img_normal_{_w:g}"] = _weight("normal", _w)
for _w in (1e4, 1e5, 3e5):
    V.VARIANTS[f"img_prior_{_w:g}"] = _weight("prior", _w)
for _s in (0.1,):
    V.VARIANTS[f"img_anchor_scale_{_s:g}"] = V.Variant(
        f"the pipeline (image references) with L_anchor's Cauchy scale {_s:g}",
        lambda c, s=_s: c.replace(anchor_scale=s))
V.VARIANTS["img_prior_100000_anchor_scale_0.1"] = V.Variant(
    "the pipeline (image references) with L_prior's weight 1e+05 and L_anchor's Cauchy scale 0.1",
    lambda c: c.replace(weights={"prior": 1e5}, anchor_scale=0.1))

if __name__ == "__main__":
    bench_fit.PROG = ".venv/bin/python studies/fit/anchor_default/sweep.py"
    bench_fit.main()
