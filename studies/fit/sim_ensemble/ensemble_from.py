"""Probe: the pipeline with the stiffness ensemble's mean and spread made from other members (members.py's
simulations, ``MEMBERS=<folder>`` of ``<scene>-<seq>-<bend>[-<tag>].npz``): every stiffness of ``BENDS`` (default
the config's ``simulate/ensemble_bend_stiffness``) with each tag of ``TAGS`` (comma list; an empty entry is the
member with the config's cloth, e.g. ``TAGS=,damping0.25,damping1``). Writes the ensemble files to
``ENSEMBLES=<folder>/<scene>/seq-<seq>.npz`` as rule simulate_ensemble does (mean, RMS spread) and runs bench_fit,
with its own arguments, on them instead of results/<scene>/sim_ensemble. ``PRIOR=1e4,3e3`` adds the methods
``pipeline_prior_<w>``: the pipeline with L_prior's weight w.

    MEMBERS=/tmp/members TAGS=,damping0.25,damping1 ENSEMBLES=/tmp/ens PYTHONPATH=. .venv/bin/python \\
        studies/fit/sim_ensemble/ensemble_from.py --suite <overlay> --views 8 --methods pipeline --no-sim \\
        --threads 1 --runs /tmp/damp --out /tmp/damp
"""
from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from anidress_core.io.sim import read_sim, write_sim  # noqa: E402
from anidress_core.fit.variants import VARIANTS, Variant  # noqa: E402
from benchmarks import bench_fit  # noqa: E402
from members import load_members  # noqa: E402

MEMBERS, ENSEMBLES = Path(os.environ["MEMBERS"]), Path(os.environ["ENSEMBLES"])
TAGS = os.environ.get("TAGS", "").split(",")
_config = yaml.safe_load(Path("config/config.yaml").read_text())["simulate"]
BENDS = [float(b) for b in os.environ["BENDS"].split(",")] if os.environ.get("BENDS") else \
    [float(b) for b in _config["ensemble_bend_stiffness"]]


def ensemble_npz(scene: str, seq: str) -> str:
    """The ensemble of MEMBERS x TAGS, written once next to the pipeline's file's header."""
    out = ENSEMBLES / scene / f"seq-{seq}.npz"
    if not out.is_file():
        X = load_members(MEMBERS, scene, seq, BENDS, TAGS, "members.py --vary makes it")  # (M, T, V, 3)
        mean = X.mean(0)
        base = read_sim(bench_fit.ensemble_npz.__wrapped__(scene, seq))
        out.parent.mkdir(parents=True, exist_ok=True)
        write_sim(out, dataclasses.replace(base, frames=mean.astype(np.float32),
                                           spread=np.sqrt(((X - mean) ** 2).sum(-1).mean(0)).astype(np.float32)),
                  config={"members": str(MEMBERS), "bends": BENDS, "tags": TAGS})
        print(f"ensemble_from: {out} from {len(X)} members", flush=True)
    return str(out)


for _w in filter(None, os.environ.get("PRIOR", "").split(",")):
    VARIANTS[f"pipeline_prior_{_w}"] = Variant(f"the pipeline with L_prior's weight {_w}",
                                               lambda c, w=float(_w): c.replace(weights={"prior": w}))
ensemble_npz.__wrapped__ = bench_fit.ensemble_npz
bench_fit.PROG = (f"MEMBERS={MEMBERS} TAGS={','.join(TAGS)} ENSEMBLES={ENSEMBLES}"
                  + (f" BENDS={os.environ['BENDS']}" if os.environ.get("BENDS") else "")
                  + (f" PRIOR={os.environ['PRIOR']}" if os.environ.get("PRIOR") else "")
                  + " PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/ensemble_from.py")
bench_fit.ensemble_npz = ensemble_npz

if __name__ == "__main__":
    bench_fit.main()
