"""Scratch diagnostic: on frames of a scene, the proposals' error vs the truth and their scores; the floor's score.

Runnable only at git d6e895a: it imports anidress_core.fit.proposals and stages.fit.proposal_database,
which left the package after that commit (issue 48; its findings: studies/fit/README.md section 8).
"""
import sys
from pathlib import Path
import numpy as np, torch
from anidress_core import fit as FIT
from anidress_core.fit import proposals as P
from anidress_core.geometry import lbs
from anidress_core.io.rig import read_rig
from anidress_core.io.scene import load_body, load_sequence_motion, read_scene, scene_cameras
from anidress_core.io.garment_poses import load_garment_poses
from anidress_core.rig import fit_transforms
from anidress_core.stages.fit import CueReader, gt_template_vertices, proposal_database, select_views, texture_anchor_of
torch.set_num_threads(1)
root, scene, seq, cues_kind, base_npz = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5]
frames = [int(x) for x in sys.argv[6].split(",")]
data, res = root / "data" / scene, root / "results" / scene
info = read_scene(data)
cfg = FIT.FitConfig.from_config({})
names = select_views(info["cameras"]["train"], 0)
cams = scene_cameras(data, seq, names, info)
views = FIT.Views.from_cameras(cams)
art = read_rig(res / "rig.npz", dtype=torch.float64)
rig = FIT.RigParts.make(art.model.rest, art.model.weights, art.model.bone_centres, torch.as_tensor(art.faces))
body = load_body(data, info)
m = load_sequence_motion(data, seq, info["fps"])
posed = body.pose(m.poses, m.Rh, m.Th, m.shapes)
masks = data / seq / "gt" / "masks" if cues_kind == "gt" else res / seq / "masks"
reader = CueReader(cams, masks, data / seq / "normals", None, posed.vertices.double(), body.faces, views, "cpu",
                   seq_dir=data / seq)
anchor, _ = texture_anchor_of(data, info, res / "template.npz", rig, views, art.transforms_of(f"seq-{seq}")[0].double(),
                              cfg.image_blur, "cpu")
Y, _, _, _ = gt_template_vertices(data, seq, art.model.rest)
floor = fit_transforms(art.model, Y).double()
from anidress_core.io.body_motion import read_motion
seqs = {}
for name in list(art.sequences) + sys.argv[7].split(","):
    base_name = name.split("@")[0]
    mm = read_motion(res / "motions" / f"{base_name}.npz")
    G = (art.transforms_of(name).double() if "@" not in name
         else torch.as_tensor(np.load(f"/tmp/fitmeasure/ens/{name}.transforms.npy")))
    seqs[name] = (G, body.pose(mm.poses, mm.Rh, mm.Th, mm.shapes).transforms.double(), mm.fps)
db = P.make_database(seqs)
q = P.body_features(posed.transforms.double(), float(info["fps"]))
base, _ = load_garment_poses(base_npz)
cfg_nf = cfg.replace(weights={"flow": 0.0})
for t in frames:
    cues = reader.cues(t)
    props = P.frame_proposals(db, q, t, 8, cfg.proposal_velocity_weight, own=f"seq-{seq}", offsets=0)
    for extra in [n for n in db.names if n.startswith(f"seq-{seq}@")]:
        e = P.frame_proposals(db, q, t, 0, 0.0, own=extra, offsets=0)
        props = P.Proposals(torch.cat([props.transforms, e.transforms]), props.labels + [extra])
    G = torch.cat([props.transforms, floor[t:t + 1], torch.as_tensor(base["transforms"][t:t + 1]).double()])
    labels = props.labels + ["FLOOR", "CHAINED"]
    s = P.score_poses(rig, views, cues, G, cfg_nf, None, anchor)
    err = [float(((lbs(rig.rest, rig.weights, g) - Y[t]) ** 2).sum(-1).mean().sqrt()) for g in G]
    order = np.argsort(s.numpy())
    print(f"frame {t}: (label, score without L_flow, RMSE mm), by score")
    for i in order:
        print(f"   {labels[i]:16s} {float(s[i]):10.3f} {1e3 * err[i]:7.2f}")
    r = FIT.fit_frame(rig, views, cues, floor[t], cfg_nf, anchor=anchor)
    print(f"   LM from FLOOR: loss {r.loss:.3f} RMSE {1e3 * float(((r.verts - Y[t]) ** 2).sum(-1).mean().sqrt()):.2f}")
reader.close()
