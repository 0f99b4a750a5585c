"""Probe: the rig's simulation of the observed motion at other bending stiffnesses (the truth's among them)
against the ground truth in template topology (raw simulated vertices, no rig). Two plain tuning scenes.

    PYTHONPATH=. .venv/bin/python studies/fit/basin/stiffness_probe.py > studies/fit/basin/stiffness.txt
"""
import tempfile

import numpy as np
import torch
import yaml

from anidress_core.stages.fit_eval import gt_template_vertices
from anidress_core.stages.simulate import run_simulate

cloth = yaml.safe_load(open("config/config.yaml"))["simulate"]["cloth"]
suite = yaml.safe_load(open("config/fit_suite.yaml"))["scenes"]
print("scene, bending stiffness (J), vertex RMSE of the raw simulation vs the ground truth: mean / frame 0 / last frame (mm)")
with tempfile.TemporaryDirectory() as tmp:
    for scene in ["suite_06", "suite_00"]:
        seq = suite[scene]["sequences"][0]["name"]
        rest = torch.as_tensor(np.load(f"results/{scene}/template.npz")["verts"]).double()
        Y = gt_template_vertices(f"data/{scene}", seq, rest)[0].numpy()
        truth = suite[scene]["garment"]["cloth"]["bend_stiffness"]
        for bend in [cloth["bend_stiffness"], 1e-3, truth, 1e-2]:
            res = run_simulate(f"results/{scene}/template.npz", f"results/{scene}/motions/seq-{seq}.npz",
                               f"data/{scene}", dict(cloth, bend_stiffness=bend), f"{tmp}/sim.npz", progress=False)
            e = np.sqrt(((res.frames[: Y.shape[0]] - Y) ** 2).sum(-1).mean(-1))
            label = " (the truth's)" if bend == truth else (" (the rig's)" if bend == cloth["bend_stiffness"] else "")
            print(f"{scene}, {bend:g}{label}: {1e3 * e.mean():.2f} / {1e3 * e[0]:.2f} / {1e3 * e[-1]:.2f}", flush=True)
