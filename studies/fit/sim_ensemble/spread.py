"""Probe: L_prior's weight per vertex from the stiffness ensemble's spread. At frame t and vertex v the
members' spread sigma_tv = sqrt(mean_m |X_m,tv - mean_m X_m,tv|^2) (m over members.py's simulations at
``BENDS``, ``MEMBERS=<folder>`` of ``<scene>-<seq>-<bend>.npz``, the members the stage's mean is made of);
L_prior's factor s_tv = 1 / (sigma_tv^2 + sigma_0^2), scaled to a mean of 1 over the frame's vertices (the
frame's total weight unchanged: a confident mean pulls harder, a disputed one less), sigma_0 = ``FLOOR``
times the median of sigma over the sequence (default 1); ``WEIGHT``: L_prior's weight (default the
pipeline's). Registers ``spread`` (the pipeline's settings, the factor set in place of
``fit/prior_information``'s, uniform by default; the product's ``fit/prior_spread_floor``, adopted from
this probe, switched off in it) and runs bench_fit, e.g.

    MEMBERS=/tmp/members FLOOR=1 PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/spread.py \\
        --suite <half of config/fit_suite.yaml> --views 8 --methods spread --no-sim --threads 1 \\
        --runs /tmp/sp --out /tmp/sp
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.fit import sequence as SEQ  # noqa: E402
from anidress_core.fit import variants as V  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.stages import fit as stage  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

MEMBERS = Path(os.environ["MEMBERS"])
FLOOR = float(os.environ.get("FLOOR", "1"))
WEIGHT = os.environ.get("WEIGHT")  # L_prior's weight, if not the pipeline's
BENDS = [float(b) for b in os.environ.get("BENDS", "1e-4,3e-4,1e-3,3e-3,1e-2").split(",")]
_ensemble_transforms = stage.ensemble_transforms
_with_prior_information = SEQ.with_prior_information
_current: dict = {}  # the sequence being fitted: its reference meshes (T, V, 3) and factors (T, V)
_applied = [0, 0]  # frames given the spread's factor, frames left as they were


def ensemble_transforms(path, art, frames, device):
    """The stage's (the mean's rig transforms), and the members' spread of the same sequence kept aside."""
    G, note = _ensemble_transforms(path, art, frames, device)
    scene, seq = Path(path).parts[-3], Path(path).stem[len("seq-"):]
    T = G.shape[0]
    X = []
    for b in BENDS:
        p = MEMBERS / f"{scene}-{seq}-{b:g}.npz"
        if not p.is_file():
            raise SystemExit(f"{p}: no such member (members.py makes it)")
        X.append(torch.as_tensor(np.load(p)["frames"][:T], dtype=torch.float64))
    X = torch.stack(X)  # (M, T, V, 3)
    sig2 = ((X - X.mean(0)) ** 2).sum(-1).mean(0)  # (T, V)
    s = 1.0 / (sig2 + (FLOOR * sig2.sqrt().median()) ** 2)
    s = s / s.mean(1, keepdim=True)
    ref = lbs(art.model.rest.double(), art.model.weights.double(), G.cpu())  # (T, V, 3) L_prior's references
    _current.update(ref=ref, scale=s)
    return G, note + f"; L_prior's factor from the spread of {len(BENDS)} members (FLOOR {FLOOR:g})"


def with_prior_information(pb, verts):
    """The frame's spread factor, the frame found by its L_prior reference."""
    pb = _with_prior_information(pb, verts)
    if pb.prior is None or "ref" not in _current:
        return pb
    d = (_current["ref"] - pb.prior.cpu()[None]).abs().amax((1, 2))
    t = int(torch.argmin(d))
    if float(d[t]) > 1e-9:  # frame 0's start with another reference, or a proposal: left as it is
        _applied[1] += 1
        return pb
    _applied[0] += 1
    return pb._replace(prior_scale=_current["scale"][t].to(pb.prior.device))


stage.ensemble_transforms = ensemble_transforms
SEQ.with_prior_information = with_prior_information
V.VARIANTS["spread"] = V.Variant(
    "the pipeline with L_prior's weight per vertex from the ensemble's spread (studies/fit/sim_ensemble/spread.py, "
    f"FLOOR {FLOOR:g}{'' if WEIGHT is None else ', L_prior ' + WEIGHT})",
    lambda c: c.replace(prior_spread_floor=None, weights={} if WEIGHT is None else {"prior": float(WEIGHT)}))

if __name__ == "__main__":
    bench_fit.PROG = (f"MEMBERS={MEMBERS} FLOOR={FLOOR:g}{'' if WEIGHT is None else ' WEIGHT=' + WEIGHT} "
                      "PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/spread.py")
    bench_fit.main()
    print(f"spread.py: the spread's factor set on {_applied[0]} frames, {_applied[1]} left uniform", flush=True)
