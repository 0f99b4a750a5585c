"""Reference for benchmarks/fit.md: the garment driven by the rig's poses of the *simulated*
sequence (no fitting to the images), and any garment_poses.npz, against the ground truth.

    .venv/bin/python benchmarks/fit_sim_reference.py --scene skirt --seq walk --frames 30 [POSES.npz ...]

Prints per-frame vertex RMSE (every 3rd frame) and the mean over the first --frames frames;
same correspondence and metric as stages.fit.run_fit_eval. Not a test.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from anidress_core.io import files  # noqa: E402
from anidress_core.io.mesh import read_mesh  # noqa: E402
from anidress_core.metrics import mesh as MM  # noqa: E402
from anidress_core.rig import fit_transforms, reconstruct  # noqa: E402
from anidress_core.stages.fit import gt_correspondence, load_garment_poses  # noqa: E402
from anidress_core.stages.rig import load_rig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--seq", default="walk")
    ap.add_argument("--frames", type=int, default=0)
    ap.add_argument("poses", nargs="*")
    a = ap.parse_args()
    d = ROOT / "data" / a.scene
    m, _ = files.load_npz(d / a.seq / "gt" / "meshes.npz", required=("garment_vertices", "garment_faces"))
    gt = torch.as_tensor(m["garment_vertices"]).double()
    gf = torch.as_tensor(m["garment_faces"].astype(np.int64))
    rv, rf, _ = read_mesh(d / "garment" / "template.obj")
    art = load_rig(ROOT / "results" / a.scene / "rig.npz", dtype=torch.float64)
    face, bary, _ = gt_correspondence(art.model.rest.numpy(), rv, rf)
    Y = MM.barycentric_transfer(gt, gf, torch.as_tensor(face), torch.as_tensor(bary))
    T = a.frames or Y.shape[0]
    Y = Y[:T]
    floor = MM.vertex_rmse(reconstruct(art.model.rest, art.model.weights, fit_transforms(art.model, Y)), Y)
    sim = MM.vertex_rmse(reconstruct(art.model.rest, art.model.weights, art.transforms_of("seq-" + a.seq).double()[:T]),
                         Y)
    print(f"{a.scene}/{a.seq}, first {T} frames (vertex RMSE, mm)")
    print(f"  rig floor: mean {1e3 * float(floor.mean()):.2f}")
    print(f"  simulated sequence's rig poses (no fitting): mean {1e3 * float(sim.mean()):.2f}; every 3rd frame "
          f"{np.round(1e3 * sim.numpy()[::3], 1).tolist()}")
    for p in a.poses:
        f, _ = load_garment_poses(p)
        X = torch.as_tensor(f["verts"]).double()[:T]
        r = MM.vertex_rmse(X, Y[:X.shape[0]])
        print(f"  {p}: mean {1e3 * float(r.mean()):.2f}; every 3rd frame {np.round(1e3 * r.numpy()[::3], 1).tolist()}")


if __name__ == "__main__":
    main()
