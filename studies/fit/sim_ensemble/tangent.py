"""Probe: L_prior's tangent planes from the frame's start mesh (the previous result, flow-aligned) instead of from
the reference's surface. Registers ``tangent_start`` (the pipeline's settings, this projection),
``tangent_start_prior_30000`` (that with L_prior's weight 3e4) and runs the
maintained benchmark with its own arguments; the projection is swapped in this process only, for that variant.

    PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/tangent.py --suite <half of config/fit_suite.yaml> \\
        --views 8 --methods pipeline,tangent_start --no-sim --threads 1 --reuse --runs /tmp/t --out /tmp/t
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import sequence as S  # noqa: E402
from anidress_core.fit import variants as V  # noqa: E402
from anidress_core.geometry import vertex_normals  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

V.VARIANTS["tangent_start"] = V.Variant("the pipeline with L_prior's tangent planes at the frame's start mesh",
                                        lambda c: c)
V.VARIANTS["tangent_start_prior_30000"] = V.Variant("tangent_start with L_prior's weight 3e4",
                                                    lambda c: c.replace(weights={"prior": 3e4}))
_with_prior_information = S.with_prior_information


def with_prior_information(pb, x_start):
    if pb.cfg.loss.startswith("tangent_start") and pb.prior_proj is not None:
        n = vertex_normals(x_start.double(), pb.rig.faces)
        proj = torch.eye(3, dtype=n.dtype, device=n.device) - n[:, :, None] * n[:, None, :]
        pb = pb._replace(prior_proj=proj)
    return _with_prior_information(pb, x_start)


S.with_prior_information = with_prior_information

if __name__ == "__main__":
    bench_fit.PROG = "PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/tangent.py"
    bench_fit.main()
