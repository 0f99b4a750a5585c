"""Probe: the fit with and without L_prior towards the simulation on bench_capture's exported
captures (noisy body poses, so the simulation of the observed motion is made from them; no garment
texture: L_anchor on image references), refitting walk exactly as the variant's own run did (its
garment_poses.npz header: cue folders and fit section) and scoring it as bench_capture does.

    .venv/bin/python studies/fit/sim_prior/capture.py /tmp/capdemo/pose_noise /tmp/capdemo/capture
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))

from anidress_core.io.garment_poses import load_garment_poses  # noqa: E402
from anidress_core.stages.fit import run_fit
from anidress_core.stages.fit_eval import run_fit_eval  # noqa: E402

VARIANTS = ("pipeline_no_sim_prior", "pipeline")

for work in map(Path, sys.argv[1:]):
    meta = load_garment_poses(work / "results" / "skirtcap" / "walk" / "garment_poses.npz")[1]["meta"]
    scene, res = meta["scene"], work / "results" / meta["scene"]
    params = dict(meta["params"], weights={k: v for k, v in meta["params"]["weights"].items() if k != "prior"})
    und = res / "walk" / "undistorted"
    fits = {}
    for v in VARIANTS:
        fits[v] = work / "score" / "simprior" / f"{v}.npz"
        run_fit(work / "data" / scene, "walk", res / "rig.npz", res / "template.npz", work / meta["masks_dir"],
                work / meta["flows_dir"], work / meta["normals_dir"], params, fits[v], ablation=v, progress=False,
                undistorted_dir=und if und.is_dir() else None, motions_dir=res / "motions")
    summ = run_fit_eval(work / "score" / scene, "walk", res / "rig.npz", fits, work / "score" / "simprior" / "fit_metrics.csv")
    for v, s in summ["methods"].items():
        print(f"{work.name} {v}: vertex RMSE {1e3 * s['vertex_rmse_m']:.2f} mm, rig floor {1e3 * s['rig_floor_rmse_m']:.2f} mm, "
              f"{s['vertex_rmse_m'] / s['rig_floor_rmse_m']:.2f}x")
