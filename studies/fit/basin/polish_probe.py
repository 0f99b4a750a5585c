"""Probe: where does the per-frame image loss (no L_prior, no L_flow, 30 LM evaluations per frame) take
(a) the rig floor, (b) the pipeline's result? START=floor|pipeline; the method label stays `optimum`."""
import os, sys, glob, torch
from anidress_core.fit.variants import VARIANTS, Variant
from anidress_core.io.garment_poses import load_garment_poses
VARIANTS["probe_images_only_30"] = Variant("probe: no L_prior, no L_flow, 30 evaluations per frame",
    lambda c: c.replace(weights={"prior": 0.0, "flow": 0.0}, max_iters=30))
import benchmarks.bench_fit as B
B.OPTIMUM_OF = "probe_images_only_30"
start = os.environ["START"]
if start == "pipeline":
    def floor_transforms(scene, seq, rig_npz, frames):
        (p,) = glob.glob(f"/tmp/tune/runs_*/{scene}/{seq}/*/v8/pipeline/garment_poses.npz")
        a, _ = load_garment_poses(p)
        return torch.as_tensor(a["transforms"][: frames or None]).double()
    B.floor_transforms = floor_transforms
sys.argv = ["bench_fit"] + sys.argv[1:]
B.main()
