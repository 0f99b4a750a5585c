"""Probe: does the stiffness ensemble's spread say where its mean is wrong? Per tuning scene, every frame and
vertex through the rig (``rig.fit_transforms`` of the members and of their mean, as the fit's L_prior sees them):
the members' RMS distance sigma from the mean's rig mesh, and the mean's error against the ground truth; their
Spearman correlation, sigma's 10th / 50th / 90th percentile, the mean error below and above the median sigma.
Members from members.py (``<folder>/<scene>-<seq>-<bend>.npz``).

    PYTHONPATH=. .venv/bin/python studies/fit/sim_ensemble/spread_error.py --members /tmp/members > spread_error.txt
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import yaml
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.io.rig import read_rig  # noqa: E402
from anidress_core.rig import fit_transforms  # noqa: E402
from anidress_core.stages.fit_eval import gt_template_vertices  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", default="config/fit_suite.yaml")
    ap.add_argument("--members", required=True, help="members.py's folder")
    ap.add_argument("--bend", default="1e-4,3e-4,1e-3,3e-3,1e-2", help="the members' bending stiffnesses (J)")
    a = ap.parse_args()
    suite = yaml.safe_load(Path(a.suite).read_text())["scenes"]
    bends = [float(b) for b in a.bend.split(",")]
    print(f"# {' '.join(sys.argv)}")
    print("# scene seq: Spearman(sigma, error of the mean); sigma p10/p50/p90 (mm); mean error (mm) where sigma is "
          "below / above its median")
    for scene in sorted(suite):
        seq = next(s["name"] for s in suite[scene]["sequences"] if s.get("role", "train") == "train")
        art = read_rig(f"results/{scene}/rig.npz", dtype=torch.float64)
        Y = gt_template_vertices(f"data/{scene}", seq, art.model.rest)[0]
        T = Y.shape[0]

        def rig_mesh(X: torch.Tensor) -> torch.Tensor:
            return lbs(art.model.rest, art.model.weights, fit_transforms(art.model, X[:T]).double())

        M = [torch.as_tensor(np.load(Path(a.members) / f"{scene}-{seq}-{b:g}.npz")["frames"][:T]).double()
             for b in bends]
        mean = rig_mesh(sum(M) / len(M))
        sig = torch.stack([((rig_mesh(m) - mean) ** 2).sum(-1) for m in M]).mean(0).sqrt()  # (T, V)
        err = ((mean - Y) ** 2).sum(-1).sqrt()
        r = spearmanr(sig.flatten().numpy(), err.flatten().numpy()).correlation
        q = torch.quantile(sig.flatten(), torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)) * 1e3
        lo, hi = err[sig < q[1] / 1e3].mean() * 1e3, err[sig >= q[1] / 1e3].mean() * 1e3
        print(f"{scene} {seq}: {r:.2f}; {q[0]:.1f} / {q[1]:.1f} / {q[2]:.1f}; {lo:.1f} / {hi:.1f}", flush=True)


if __name__ == "__main__":
    main()
