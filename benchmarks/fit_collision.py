"""The garment fit with and without L_col, the body-collision term (not in the paper).

For each scene/sequence (pipeline cues: estimated masks and flows, shipped normals; 8 views;
the scene's own fit settings from config/config.yaml), the fit runs twice -- the config as is
and with ``weights/collision`` set -- and each result is measured against the ground truth
(vertex RMSE against the rig floor, Chamfer, acceleration error: ``fit_eval``) and against the
posed body (garment vertices more than 2 mm inside it per frame, the deepest one; winding
number, :func:`anidress_core.sim.penetration_depth`). Writes benchmarks/fit_collision.md / .csv.
Not a test.

    .venv/bin/python benchmarks/fit_collision.py --frames 30 --weight 1e6
"""
from __future__ import annotations

import argparse
import copy
import datetime
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from anidress_core.config import load_config, scene_section  # noqa: E402
from anidress_core.sim import penetration_depth  # noqa: E402
from anidress_core.stages.fit import run_fit, run_fit_eval  # noqa: E402
from bench_fit import cue_dirs  # noqa: E402
from benchutil import cpu_model, fit_scene, git_rev  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="skirt:walk:texture,skirt:walk:images,dress:sway:images",
                    help="scene:sequence:anchor_reference triples")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--weight", type=float, default=1e6, help="weights/collision of the L_col runs")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/fit_collision")
    a = ap.parse_args()
    os.chdir(REPO)
    config = load_config("config/config.yaml")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for triple in a.runs.split(","):
            scene, seq, ref = triple.split(":")
            base = copy.deepcopy(scene_section(config, "fit", scene))
            base.update(frames=a.frames, views=a.views, threads=a.threads, anchor_reference=ref)
            sc = fit_scene(scene, seq, a.views, f"results/{scene}/rig.npz", a.frames)
            body = sc.posed.vertices.numpy()[: a.frames]
            depth_gt = penetration_depth(sc.Y.numpy(), body, np.asarray(sc.body.faces))
            for label, w in (("without L_col", 0.0), (f"L_col {a.weight:g}", a.weight)):
                p = copy.deepcopy(base)
                p["weights"]["collision"] = w
                out = Path(tmp) / f"{scene}-{seq}-{ref}-{w:g}.npz"
                d = cue_dirs(scene, seq, "pipeline")
                meta = run_fit(f"data/{scene}", seq, f"results/{scene}/rig.npz", f"results/{scene}/template.npz",
                               d["masks"], d["flows"], d["normals"], p, out, progress=False, cue_source=d["label"])
                csv = out.with_suffix(".csv")
                run_fit_eval(f"data/{scene}", seq, f"results/{scene}/rig.npz", {"fit": out}, csv)
                m = pd.read_csv(csv)
                m = m[m.method == "fit"]
                depth = penetration_depth(np.load(out)["verts"], body, np.asarray(sc.body.faces))
                rows.append({
                    "scene": scene, "sequence": seq, "anchor_reference": ref, "run": label,
                    "vertex_rmse_mm": 1e3 * m.vertex_rmse_m.mean(), "rig_floor_mm": 1e3 * m.rig_floor_rmse_m.mean(),
                    "x_floor": m.vertex_rmse_m.mean() / m.rig_floor_rmse_m.mean(),
                    "chamfer_mm": 1e3 * m.chamfer_m.mean(), "accel_error_mm": 1e3 * m.accel_error_m.mean(),
                    "inside_per_frame": float((depth > 0.002).sum(1).mean()),
                    "inside_gt_per_frame": float((depth_gt > 0.002).sum(1).mean()),
                    "deepest_mm": 1e3 * float(depth.max()), "fps": meta["fps"]})
                print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    df.to_csv(a.out + ".csv", index=False, float_format="%.4g")
    lines = [
        "# Garment fit with and without L_col (body collision)",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}, git {git_rev()}",
        f"- command: `.venv/bin/python benchmarks/fit_collision.py {' '.join(sys.argv[1:])}`",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} ({a.threads} threads), "
        f"Python {platform.python_version()}",
        f"- first {a.frames} frames, {a.views} views, pipeline cues (estimated masks and flows, shipped normals), "
        "each scene's fit settings of config/config.yaml (frame 0 from the simulation), L_an's references as "
        "in the column; *inside*: garment vertices more than 2 mm inside the posed body per frame (the ground "
        "truth's count beside it), *deepest*: the deepest one over the sequence.",
        "",
        "| scene | seq | L_an refs | run | vertex RMSE mm | x floor | Chamfer mm | accel. err. mm | inside / frame "
        "(truth) | deepest mm | frames/s |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['sequence']} | {r['anchor_reference']} | {r['run']} | "
                     f"{r['vertex_rmse_mm']:.2f} | {r['x_floor']:.2f} | {r['chamfer_mm']:.2f} | "
                     f"{r['accel_error_mm']:.2f} | {r['inside_per_frame']:.1f} ({r['inside_gt_per_frame']:.1f}) | "
                     f"{r['deepest_mm']:.1f} | {r['fps']:.2f} |")
    Path(a.out + ".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
