"""Body-pose error of refined poses against an export-capture truth.

Usage: python studies/body_refine/score.py SCENE SEQ OUT FRAMES
(SCENE: a scene written by `anidress export-capture`, its truth in SCENE.truth; OUT: an `anidress refine-body` output)."""
import sys, json, numpy as np, torch
from anidress_core.io.motion import read_easymocap_smpl_dir
from anidress_core.io.scene import load_body
from anidress_core.stages.export_capture import pose_errors
scene, seq, out, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
body = load_body(scene)
def rd(d):
    x = read_easymocap_smpl_dir(d)
    return {k: np.asarray(x[k], np.float64)[:n] for k in ("poses", "Rh", "Th")}
truth = rd(f"{scene}.truth/{seq}/smpl"); noisy = rd(f"{scene}/{seq}/smpl"); ref = rd(f"{out}/smpl")
print("before", {k: round(v, 3) for k, v in pose_errors(body, truth, noisy).items()})
print("after ", {k: round(v, 3) for k, v in pose_errors(body, truth, ref).items()})
