"""Runnable only at git d6e895a: it sets the fit settings proposal_* and backward, which left the package
after that commit (issue 48; its findings: studies/fit/README.md section 8).

Probe (issue 23 items 3-5): stage fit with and without proposals and the backward pass.

Usage: python studies/fit/proposals/measure.py ROOT SCENE SEQ {gt|pipeline} FRAMES base,prop10,prop10_back OUT
(ROOT holds data/<scene> and results/<scene> of a finished workflow run; writes OUT/<variant>.npz, OUT/metrics.csv)."""
import json, sys, time, os
from pathlib import Path
import numpy as np, torch
from anidress_core.stages.fit import run_fit, run_fit_eval
torch.set_num_threads(1)
root = Path(sys.argv[1]); scene = sys.argv[2]; seq = sys.argv[3]; cues = sys.argv[4]; frames = int(sys.argv[5])
variants = sys.argv[6].split(",")
data, res = root / "data" / scene, root / "results" / scene
if cues == "gt":
    masks, flows = data / seq / "gt" / "masks", data / seq / "gt" / "flows"
else:
    masks, flows = res / seq / "masks", res / seq / "flows"
normals = data / seq / "normals"
V = {
    "base": {},
    "prop10": {"proposal_every": 10},
    "prop5": {"proposal_every": 5},
    "back": {"backward": True},
    "prop10_back": {"proposal_every": 10, "backward": True},
    "prop0": {"proposal_every": 1000},  # frame 0 only
    "prop10_r1": {"proposal_every": 10, "proposal_refine": 1},
    "prop5_r1": {"proposal_every": 5, "proposal_refine": 1},
}
out = Path(sys.argv[7]); out.mkdir(parents=True, exist_ok=True)
fits = {}
for v in variants:
    params = dict(V[v], frames=frames)
    p = out / f"{v}.npz"
    t0 = time.time(); c0 = time.process_time()
    meta = run_fit(data, seq, res / "rig.npz", res / "template.npz", masks, flows, normals, params, p, progress=False,
                   motions_dir=res / "motions")
    print(v, "wall %.1f s cpu %.1f s fps %.3f load %s" % (time.time() - t0, time.process_time() - c0, meta["fps"],
          [round(x, 2) for x in os.getloadavg()]), flush=True)
    kept = {t: n["proposal"]["kept"] for t, n in meta["frame_notes"].items() if "proposal" in n}
    nb = sum("backward" in n for n in meta["frame_notes"].values())
    print("   proposals kept:", kept, "backward frames:", nb, flush=True)
    fits[v] = p
summ = run_fit_eval(data, seq, res / "rig.npz", fits, out / "metrics.csv")
import csv
rows = list(csv.DictReader(open(out / "metrics.csv")))
for v in variants:
    r = [x for x in rows if x["method"] == v]
    e = np.array([float(x["vertex_rmse_m"]) for x in r]); f = np.array([float(x["rig_floor_rmse_m"]) for x in r])
    n = min(10, len(e) // 2)
    print(f"{v:12s} RMSE {1e3*e.mean():6.2f} mm floor {1e3*f.mean():5.2f} ratio {e.mean()/f.mean():.2f}x "
          f"first{n} {1e3*e[:n].mean():6.2f} last{n} {1e3*e[-n:].mean():6.2f} drift {e[-n:].mean()/e[:n].mean():.2f} "
          f"loss {np.mean([float(x['loss']) for x in r]):.5g}")
