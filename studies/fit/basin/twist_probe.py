"""Probe: how much of the error is one twist of the whole garment about the vertical axis (per frame, every 4th,
the best rotation in [-30, 30] deg by 0.5 deg about the true garment's centroid). RUNS: bench_fit --runs folders (glob).

    PYTHONPATH=. .venv/bin/python studies/fit/basin/twist_probe.py "/tmp/tune/runs_*" > studies/fit/basin/twist.txt
"""
import glob, sys

import numpy as np, torch, yaml
from anidress_core.stages.fit_eval import gt_template_vertices
from anidress_core.io.garment_poses import load_garment_poses
suite = yaml.safe_load(open("config/fit_suite.yaml"))["scenes"]
for scene in ["suite_00", "suite_03", "suite_06", "suite_09", "suite_01", "suite_02"]:
    seq = suite[scene]["sequences"][0]["name"]
    rest = torch.as_tensor(np.load(f"results/{scene}/template.npz")["verts"]).double()
    Y = gt_template_vertices(f"data/{scene}", seq, rest)[0].numpy()
    for m in ["sim", "pipeline"]:
        (p,) = glob.glob(f"{sys.argv[1]}/{scene}/{seq}/*/v8/{m}/garment_poses.npz")
        X = load_garment_poses(p)[0]["verts"]
        T = min(len(X), len(Y))
        up = np.array([0, 1.0, 0]) if np.ptp(Y[0][:, 1]) > np.ptp(Y[0][:, 2]) else np.array([0, 0, 1.0])
        base, best, bang, bz = [], [], [], []
        for t in range(0, T, 4):
            x, y = X[t], Y[t]
            c = y.mean(0)
            e0 = np.sqrt(((x - y) ** 2).sum(-1).mean())
            be, ba = e0, 0
            for a in np.radians(np.arange(-30, 30.1, 0.5)):
                ca, sa = np.cos(a), np.sin(a)
                if up[1]:
                    R = np.array([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]])
                else:
                    R = np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]])
                xr = (x - c) @ R.T + c
                e = np.sqrt(((xr - y) ** 2).sum(-1).mean())
                if e < be: be, ba = e, np.degrees(a)
            base.append(e0); best.append(be); bang.append(ba)
        print(scene, m, "RMSE %.1f mm -> %.1f mm after the best twist about the vertical (median |angle| %.1f deg)" % (1e3*np.mean(base), 1e3*np.mean(best), np.median(np.abs(bang))))
