"""Probe: the render settings against CPU time and image quality, on the trained fields of a finished demo run.

    .venv/bin/python studies/field/render_settings.py OUT_DIR [VARIANT ...]

Run from a workdir holding a demo run (`make demo`). Each variant overrides config/config.yaml's field section;
the three demo fields (skirt full and body_only, tight full) are rendered as rules render_novel_view and
render_novel_pose do (every 12th frame, one torch thread) and scored as rule evaluate_field does. Prints, per
variant and field, the median CPU s per image (novel view, novel pose) as a ratio to ``base`` and the change of
the box / subject / garment PSNR (dB), subject SSIM and IoU. ``base`` must be among the variants run.
"""
import copy
import json
import statistics
import sys

import torch

from anidress_core.config import load_config
from anidress_core.io.scene import read_scene
from anidress_core.stages.evaluate import run_evaluate
from anidress_core.stages.field import run_render

VARIANTS = {  # section -> keys overridden; base = config/config.yaml
    "base": {},
    "early_1e-3": {"render": {"early_stop": 0.001}},
    "skip_0.05": {"render": {"skip_density": 0.05}},
    "early_1e-3_skip_0.05": {"render": {"early_stop": 0.001, "skip_density": 0.05}},
    "skip_5": {"render": {"skip_density": 5.0}},
    "margin_2cm": {"sampler": {"dilate_m": 0.02}},
    "chunk_32k": {"render": {"chunk": 32768}},
    "chunk_64k": {"render": {"chunk": 65536}},
}
FIELDS = (("skirt", "full"), ("skirt", "body_only"), ("tight", "full"))

torch.set_num_threads(1)
out_dir, names = sys.argv[1], sys.argv[2:] or list(VARIANTS)
cfg = load_config("config/config.yaml")
res = {}
for vn in names:
    p = copy.deepcopy(cfg["field"])
    for sec, kv in VARIANTS[vn].items():
        p[sec].update(kv)
    for scn, var in FIELDS:
        info = read_scene(f"data/{scn}")
        garment = scn == "skirt"
        d, cpu, renders = f"{out_dir}/{vn}/{scn}_{var}", [], []
        for kind, seq, cams in (("novel_view", "walk", info["cameras"]["test"]),
                                ("novel_pose", "dance", info["cameras"]["train"] + info["cameras"]["test"])):
            s = run_render(f"results/{scn}/walk/{var}/field.pt", f"data/{scn}", f"{d}/{kind}", p, seq=seq, cameras=cams,
                           garment_poses_npz=f"results/{scn}/{seq}/garment_poses.npz" if garment and var == "full"
                           else None, template_npz=f"results/{scn}/template.npz" if garment else None,
                           rig_npz=f"results/{scn}/rig.npz" if garment else None, frame_stride=12, device="cpu",
                           progress=False)
            cpu.append(statistics.median(q["cpu_seconds"] for q in s["per_image"]))
            renders.append((kind, seq, f"{d}/{kind}"))
        run_evaluate(f"data/{scn}", renders, f"{d}/metrics.csv", f"{d}/metrics.json", cfg["metrics"], progress=False)
        res[(vn, scn, var)] = (cpu, json.load(open(f"{d}/metrics.json"))["metrics"])
for (vn, scn, var), (cpu, m) in res.items():
    bc, bm = res[("base", scn, var)]
    row = [f"{vn:22s} {scn}/{var:9s} CPU s per image x{cpu[0] / bc[0]:.3f} (nv) x{cpu[1] / bc[1]:.3f} (np)"]
    for i, kind in enumerate(("nv", "np")):
        a, b = m[i], bm[i]
        dg = float(a["psnr_garment_db"]) - float(b["psnr_garment_db"])  # NaN without garment labels (tight)
        row.append(f"{kind}: box {a['psnr_db'] - b['psnr_db']:+.3f} subject {a['psnr_subject_db'] - b['psnr_subject_db']:+.3f} "
                   f"garment {dg:+.3f} SSIM {a['ssim_subject'] - b['ssim_subject']:+.4f} IoU {a['iou'] - b['iou']:+.4f}")
    print(" | ".join(row))
