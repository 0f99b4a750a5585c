"""Runnable only at git d6e895a: it imports anidress_core.fit.proposals.score_poses, which left the package
after that commit (issue 48; its findings: studies/fit/README.md section 16).

Probe: the pipeline with L_prior's reference and frame 0's start taken from one member of the stiffness
ensemble (members.py's simulations, ``MEMBERS=<folder>`` of ``<scene>-<seq>-<bend>.npz``) instead of the members'
mean. ``PICK=true``: the member at the scene's own stiffness (an oracle, from ``SUITE=<overlay>``);
``PICK=images``: the member whose rig poses score lowest on the images, L_silhouette + L_normal
(``anidress_core.fit.proposals.score_poses``) summed over every 4th frame, among the members at ``BENDS``
(default 1e-4,3e-4,1e-3,3e-3,1e-2); ``PICK=<bend>``: that member. Swaps the stage's
``ensemble_transforms`` in its own process; runs bench_fit with its own arguments, e.g.

    MEMBERS=/tmp/members PICK=images PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/prior_from.py \\
        --suite <overlay> --views 8 --methods pipeline --no-sim --threads 1 --runs /tmp/pick --out /tmp/pick
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core import fit as FIT  # noqa: E402
from anidress_core.fit.proposals import score_poses  # noqa: E402
from anidress_core.rig import fit_transforms  # noqa: E402
from anidress_core.stages import fit as stage  # noqa: E402
from benchmarks import bench_fit  # noqa: E402

MEMBERS, PICK = Path(os.environ["MEMBERS"]), os.environ["PICK"]
BENDS = [float(b) for b in os.environ.get("BENDS", "1e-4,3e-4,1e-3,3e-3,1e-2").split(",")]
STRIDE = 4
_fit_sequence = FIT.fit_sequence
_current: dict = {}  # the scene being fitted: its members' rig transforms


def member_transforms(path, art, frames, device):
    """Stands in for the stage's ensemble_transforms: the scene and sequence from the ensemble's path
    (results/<scene>/sim_ensemble/seq-<seq>.npz); returns the picked member (PICK=images: the mean's, replaced in
    fit_sequence once the cues are there)."""
    scene, seq = Path(path).parts[-3], Path(path).stem[len("seq-"):]
    if PICK == "true":
        suite = yaml.safe_load(Path(os.environ["SUITE"]).read_text())["scenes"]
        bends = [float(suite[scene]["garment"]["cloth"]["bend_stiffness"])]
    else:
        bends = BENDS if PICK == "images" else [float(PICK)]
    G = {}
    for b in bends:
        p = MEMBERS / f"{scene}-{seq}-{b:g}.npz"
        if not p.is_file():
            raise SystemExit(f"{p}: no such member (members.py makes it)")
        X = torch.as_tensor(np.load(p)["frames"][:frames], device=device, dtype=torch.float64)
        G[b] = fit_transforms(art.model, X).double()
    _current.clear()
    _current.update(scene=scene, members=G)
    if PICK == "images":
        return stage.ensemble_transforms.__wrapped__(path, art, frames, device)
    return G[bends[0]], f"{MEMBERS}/{scene}-{seq}-{bends[0]:g}.npz (PICK={PICK}), rig transforms fitted to it"


def fit_sequence(rig, views, num_frames, cues_of, flow_of, init, cfg=None, **kw):
    """PICK=images: score every member on the frames' cues, follow the lowest."""
    if PICK != "images" or kw.get("starts") is not None or kw.get("sim_transforms") is None:
        return _fit_sequence(rig, views, num_frames, cues_of, flow_of, init, cfg, **kw)
    scfg = cfg.replace(weights={"flow": 0.0, "anchor": 0.0, "stretch": 0.0, "collision": 0.0})
    bends = sorted(_current["members"])
    scores = torch.zeros(len(bends), dtype=torch.float64)
    for t in range(0, num_frames, STRIDE):
        G = torch.stack([_current["members"][b][t] for b in bends]).to(init.device)
        scores += score_poses(rig, views, cues_of(t), G, scfg)
    pick = bends[int(torch.argmin(scores))]
    print("prior_from:", json.dumps({"scene": _current["scene"], "pick": f"{pick:g}",
                                     "scores": {f"{b:g}": round(float(s), 1) for b, s in zip(bends, scores)}}),
          flush=True)
    S = _current["members"][pick].to(init.device)
    return _fit_sequence(rig, views, num_frames, cues_of, flow_of, S[0], cfg, **{**kw, "sim_transforms": S})


member_transforms.__wrapped__ = stage.ensemble_transforms
stage.ensemble_transforms = member_transforms
FIT.fit_sequence = fit_sequence

if __name__ == "__main__":
    bench_fit.PROG = (f"MEMBERS={MEMBERS} PICK={PICK}{' SUITE=' + os.environ['SUITE'] if PICK == 'true' else ''} "
                      "PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/prior_from.py")
    bench_fit.main()
