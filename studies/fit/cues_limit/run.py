"""Probe: the fit with the ground truth's optical flows in place of the pipeline's (``GT_FLOWS=1``; the pipeline's
masks and the shipped normals kept), or with any of the ground truth's cues (``GT_CUES=masks,flows,normals``: the
named ones from data/<scene>/<seq>/gt, the others as the pipeline has them), and with a larger budget per frame: how
much of the fit's error is the cues', how much the optimiser's? Registers ``prior_<w>``
(the pipeline with L_prior's weight w, for w in 0, 1000; ``pipeline`` is the defaults), ``it15_fa10`` (15 loss
evaluations per frame t > 0 and 10 Gauss-Newton steps of the flow alignment, instead of 5 and 3) and
``p0_it15_fa10`` (that without L_prior), ``it15_fa10_tol1e-2`` (that stopping when a step gains less than
1 % instead of 0.1 %), ``images_only`` (the pipeline without L_prior and L_flow: the per-frame image loss), and
with ``OPTIMUM_OF=<variant>`` makes the ``optimum`` row that variant started on the rig floor; runs the maintained
benchmark (benchmarks/bench_fit.py) with its own arguments and ``--cues pipeline`` (with ``GT_FLOWS=1`` the flows
swapped). E.g.

    GT_FLOWS=1 PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/run.py --suite <half of config/fit_suite.yaml> \\
        --views 8 --methods pipeline,prior_0 --no-sim --threads 1 --runs /tmp/gt_flow --out /tmp/gt_flow
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import variants as V  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

for w in (0.0, 1e3):
    V.VARIANTS[f"prior_{w:g}"] = V.Variant(f"the pipeline with L_prior's weight {w:g}",
                                                   lambda c, w=w: c.replace(weights={"prior": w}))
V.VARIANTS["it15_fa10"] = V.Variant("the pipeline with 15 loss evaluations per frame t > 0 and 10 flow-alignment steps",
                                    lambda c: c.replace(max_iters=15, flow_align_iters=10))
V.VARIANTS["p0_it15_fa10"] = V.Variant("the pipeline without L_prior, 15 loss evaluations per frame t > 0, 10 "
                                       "flow-alignment steps",
                                       lambda c: c.replace(weights={"prior": 0.0}, max_iters=15, flow_align_iters=10))
V.VARIANTS["it15_fa10_tol1e-2"] = V.Variant("the pipeline with up to 15 loss evaluations per frame t > 0, 10 "
                                           "flow-alignment steps, converged below a 1 % gain per step",
                                           lambda c: c.replace(max_iters=15, flow_align_iters=10, rel_tol=1e-2))
V.VARIANTS["images_only"] = V.Variant("the pipeline without L_prior and L_flow (the per-frame image loss)",
                                      lambda c: c.replace(weights={"prior": 0.0, "flow": 0.0}))
_pipeline_cues = bench_fit.cue_dirs


CUES = ("masks", "flows", "normals")


def gt_cues() -> tuple[str, ...]:
    """The cues to take from the ground truth, from ``GT_CUES`` (comma list of CUES) or ``GT_FLOWS=1`` (flows)."""
    names = [c for c in os.environ.get("GT_CUES", "").split(",") if c]
    if os.environ.get("GT_FLOWS") == "1":
        names.append("flows")
    bad = sorted(set(names) - set(CUES))
    if bad:
        raise SystemExit(f"GT_CUES: unknown cue(s) {bad}; choose from {list(CUES)}")
    return tuple(c for c in CUES if c in names)


def cue_dirs(scene: str, seq: str, source: str) -> dict:
    """The pipeline's cues with those of :func:`gt_cues` from the synthetic scene's ground truth
    (data/<scene>/<seq>/gt/<cue>)."""
    d = _pipeline_cues(scene, seq, source)
    swap = gt_cues()
    d = {**d, **{c: f"data/{scene}/{seq}/gt/{c}" for c in swap}}
    label = {"masks": "pipeline masks", "flows": "pipeline flows", "normals": "shipped degraded normals"}
    d["label"] = " + ".join(f"ground-truth {c}" if c in swap else label[c] for c in CUES)
    return d


if __name__ == "__main__":
    swap = gt_cues()
    if swap:
        bench_fit.cue_dirs = cue_dirs
    env = ("GT_FLOWS=1 " if swap == ("flows",) else f"GT_CUES={','.join(swap)} ") if swap else ""
    of = os.environ.get("OPTIMUM_OF")
    if of:
        bench_fit.OPTIMUM_DESCRIPTION = bench_fit.OPTIMUM_DESCRIPTION.replace(f"`{bench_fit.OPTIMUM_OF}`", f"`{of}`")
        bench_fit.OPTIMUM_OF = of
        env += f"OPTIMUM_OF={of} "
    bench_fit.PROG = f"{env}PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/run.py"
    bench_fit.main()
