"""Probe: how much the fits stretch the garment's edges, against the truth, the rig floor and the simulation.

Per method, the root mean square over edges of the relative stretch |x_a - x_b| / l_ab - 1 (l_ab: the
template's rest length), averaged over frames, and the vertex RMSE against the ground truth in template
topology. Reads a bench_fit runs folder (8 views, pipeline cues):

    PYTHONPATH=. .venv/bin/python studies/fit/stretch/strain.py <runs> <method,...> <scene/seq> ...
"""
from __future__ import annotations

import sys

import numpy as np
import torch

from anidress_core import raster
from anidress_core.geometry import lbs
from anidress_core.io.rig import read_rig
from anidress_core.rig import fit_transforms
from anidress_core.stages.fit_eval import gt_template_vertices

runs, methods = sys.argv[1], sys.argv[2].split(",")
print("scene/seq | method | edge stretch rms | vertex RMSE (mm)")
for scene_seq in sys.argv[3:]:
    scene, seq = scene_seq.split("/")
    art = read_rig(f"results/{scene}/rig.npz", dtype=torch.float64)
    m = art.model
    Y = gt_template_vertices(f"data/{scene}", seq, m.rest, 40)[0].double()
    E = raster.mesh_edges(torch.as_tensor(np.load(f"results/{scene}/template.npz")["faces"]).long())[0]
    rest = (m.rest[E[:, 0]] - m.rest[E[:, 1]]).norm(dim=-1)

    def report(name, X):
        s = ((X[:, E[:, 0]] - X[:, E[:, 1]]).norm(dim=-1) / rest - 1).pow(2).mean(-1).sqrt().mean()
        rmse = ((X - Y) ** 2).sum(-1).mean(-1).sqrt().mean()
        print(f"{scene_seq} | {name} | {float(s):.4f} | {1000 * float(rmse):.1f}")

    report("ground truth", Y)
    report("rig floor", lbs(m.rest, m.weights, fit_transforms(m, Y).double()))
    for meth in methods:
        G = np.load(f"{runs}/{scene}/{seq}/pipeline/v8/{meth}/garment_poses.npz")["transforms"]
        report(meth, lbs(m.rest, m.weights, torch.as_tensor(G).double()))
