"""Probe: does L_stretch widen the images' basin? Every frame of the pipeline's fit (``stretch_300`` in
``--runs``) refitted by the per-frame image loss with L_stretch (no L_prior, no L_flow, <= 30 LM evaluations),
as section 12's polish_probe did without L_stretch; with ``KEEP_PRIOR=1`` L_prior stays on (only L_flow off).
The row is labelled ``optimum`` (bench_fit's started-from row); its "As run" line names the loss.

    [KEEP_PRIOR=1] PYTHONPATH=. .venv/bin/python studies/fit/stretch/polish.py --suite <overlay> \\
        --methods optimum --views 8 --frames 12 --no-sim --threads 1 --runs /tmp/tune/runs_a --out /tmp/polish
"""
import glob
import os
import sys

import torch

import benchmarks.bench_fit as B
from anidress_core.fit.variants import VARIANTS, Variant
from anidress_core.io.garment_poses import load_garment_poses

VARIANTS["probe_images_stretch_30"] = Variant(
    "probe: the pipeline (L_stretch 300) without L_prior and L_flow, 30 evaluations per frame",
    lambda c: c.replace(weights={"prior": 0.0, "flow": 0.0}, max_iters=30, window=0))
VARIANTS["probe_no_flow_30"] = Variant(
    "probe: the pipeline (L_stretch 300) without L_flow, 30 evaluations per frame",
    lambda c: c.replace(weights={"flow": 0.0}, max_iters=30, window=0))
KEEP_PRIOR = os.environ.get("KEEP_PRIOR") == "1"
B.OPTIMUM_OF = "probe_no_flow_30" if KEEP_PRIOR else "probe_images_stretch_30"
RUNS = sys.argv[sys.argv.index("--runs") + 1]


def pipeline_transforms(scene, seq, rig_npz, frames):
    (p,) = glob.glob(f"{RUNS}/{scene}/{seq}/*/v8/stretch_300/garment_poses.npz")
    a, _ = load_garment_poses(p)
    return torch.as_tensor(a["transforms"][: frames or None]).double()


B.floor_transforms = pipeline_transforms
B.PROG = ("KEEP_PRIOR=1 " if KEEP_PRIOR else "") + "PYTHONPATH=. .venv/bin/python studies/fit/stretch/polish.py"
sys.argv = ["bench_fit"] + sys.argv[1:]
B.main()
