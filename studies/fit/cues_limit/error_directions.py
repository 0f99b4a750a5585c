"""Probe: how much of a fit's vertex error lies along the true surface and how much across it.

Images see a surface's placement across itself (silhouettes, normals) and, on a plain fabric, little of how the
material slides along it. Per scene and fit: the error e = x_fit - y of every template vertex (y: the ground truth
carried onto the template, as bench_fit scores it) split into its component along the true vertex normal n of y
(e.n, "across") and the rest ("along"), root mean square over vertices and frames (mm), for the rig floor and each
fit, and each over the floor's. Reads the fits bench_fit wrote (``<runs>/<scene>/<seq>/pipeline/v<views>/<method>/
garment_poses.npz``); fits with fewer frames than the scene are left out.

    PYTHONPATH=. .venv/bin/python studies/fit/cues_limit/error_directions.py --runs <bench_fit --runs> \\
        --methods pipeline,sim suite_00/jump suite_03/twirl > out.txt
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.geometry import lbs, vertex_normals  # noqa: E402
from anidress_core.io.rig import read_rig  # noqa: E402
from anidress_core.rig import fit_transforms  # noqa: E402
from anidress_core.stages.fit_eval import gt_template_vertices  # noqa: E402


def split_error(X: torch.Tensor, Y: torch.Tensor, N: torch.Tensor) -> tuple[float, float, float]:
    """RMS (mm) of the error X - Y (T, V, 3), its component along the unit normals N (T, V, 3) and the rest."""
    e = X - Y
    across = (e * N).sum(-1)  # (T, V)
    along = e - across[..., None] * N
    return 1e3 * float(e.pow(2).sum(-1).mean().sqrt()), 1e3 * float(across.pow(2).mean().sqrt()), \
        1e3 * float(along.pow(2).sum(-1).mean().sqrt())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="bench_fit's --runs folder")
    ap.add_argument("--methods", default="pipeline", help="comma list of the fits to read")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("scenes", nargs="+", help="<scene>/<seq>")
    a = ap.parse_args()
    print(f"# {' '.join(sys.argv)}")
    print("# RMS over vertices and frames, mm: all / across the true surface (along its normal) / along it; "
          "then each over the rig floor's")
    print(f"{'scene':18s} {'fit':22s} {'all':>7s} {'across':>7s} {'along':>7s} | {'all':>5s} {'across':>6s} {'along':>5s}")
    for sc in a.scenes:
        scene, seq = sc.split("/")
        art = read_rig(f"results/{scene}/rig.npz", dtype=torch.float64)
        Y = gt_template_vertices(f"data/{scene}", seq, art.model.rest)[0]  # (T, V, 3)
        N = vertex_normals(Y, torch.as_tensor(np.asarray(art.faces)).long())
        floor = split_error(lbs(art.model.rest, art.model.weights, fit_transforms(art.model, Y).double()), Y, N)
        print(f"{sc:18s} {'rig floor':22s} {floor[0]:7.2f} {floor[1]:7.2f} {floor[2]:7.2f} |")
        for m in a.methods.split(","):
            p = Path(a.runs) / scene / seq / "pipeline" / f"v{a.views}" / m / "garment_poses.npz"
            if not p.is_file():
                continue
            X = torch.as_tensor(np.load(p)["verts"]).double()
            if X.shape != Y.shape:
                continue
            r = split_error(X, Y, N)
            print(f"{sc:18s} {m:22s} {r[0]:7.2f} {r[1]:7.2f} {r[2]:7.2f} | "
                  f"{r[0] / floor[0]:5.2f} {r[1] / floor[1]:6.2f} {r[2] / floor[2]:5.2f}")


if __name__ == "__main__":
    main()
