"""Where the garment fit's error comes from: chained flow targets against re-anchored ones.

With ground-truth masks and flows (synthetic scene) and frame 0 started on the rig floor
(the rig's best pose for the ground truth), the fit of frames t > 0 is run four ways:

* ``chain``: the paper's L_of -- flow targets from the previous frame's *fitted* mesh
  (what `fit` does);
* ``oracle``: flow targets from the previous frame's *rig floor* mesh (not available in
  practice; isolates what the chaining costs);
* ``chain + L_ph``: as ``chain`` with the multi-view photo-consistency term on (variant
  ``photo``);
* ``chain + L_an``: as ``chain`` with the temporal chromaticity anchor on (variant
  ``anchor``; references from the frame each vertex is first seen in);
* ``chain + L_an (texture)``: the same with L_an's references from the garment texture at the
  template's UVs, frame 0 included (variant ``anchor_texture``, without its temporal filter);
* ``anchor_texture_true_flows``: as ``anchor_texture`` with the scene's true flows (gt/flows) in
  place of the estimated ones, the masks unchanged (isolates what the flow estimate's error costs);
* ``anchor_texture_no_flow``: as ``anchor_texture`` without L_of (no transport between frames);
* ``anchor_texture_oracle``: as ``anchor_texture`` with the flow targets from the rig floor of t-1
  (what the chaining costs once L_an is on).

``--basin 5,11,21`` adds, for the ``anchor_texture`` run, a look at those frames: the loss without
L_of (what is left to place the frame once its targets are spent) at the chained fit, at a
fit of the same frame started on the rig floor and run to convergence, and on the straight line
between the two meshes -- does the loss have its minimum near the truth, is the chained fit in
it, and is there a barrier between them?

Writes benchmarks/fit_drift.md (per-frame vertex RMSE against the ground truth, every
other frame) and prints it. Not a test.

    .venv/bin/python benchmarks/fit_drift.py --scene skirt --seq walk --frames 22 --views 8
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from anidress_core import fit as FIT  # noqa: E402
from anidress_core import raster  # noqa: E402
from anidress_core.config import load_config, scene_section  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.stages.fit import CueReader, fit_config, texture_anchor_of  # noqa: E402
from benchutil import cpu_model, fit_scene  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--seq", default="walk")
    ap.add_argument("--frames", type=int, default=22)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--rig", default="results/{scene}/rig.npz", help="rig file ({scene}: the scene's name)")
    ap.add_argument("--runs", default="chain,oracle,photo,anchor,anchor_texture",
                    help="which of chain, oracle, photo, anchor, anchor_texture, anchor_texture_true_flows, "
                         "anchor_texture_no_flow to run")
    ap.add_argument("--cues", default="ground_truth", choices=["ground_truth", "pipeline"],
                    help="masks and flows: the scene's true ones (gt/) or the pipeline's (results/<scene>/<seq>/)")
    ap.add_argument("--basin", default="", help="frames (comma-separated) of the loss-basin check of the "
                    "anchor_texture run (see the module docstring)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/fit_drift.md")
    a = ap.parse_args()
    basin_frames = [int(x) for x in a.basin.split(",")] if a.basin else []
    if basin_frames and ("anchor_texture" not in a.runs.split(",")
                         or not all(0 < t < a.frames for t in basin_frames)):
        raise SystemExit(f"--basin {a.basin}: needs the run anchor_texture and frames in 1..{a.frames - 1}")
    os.chdir(REPO)
    torch.set_num_threads(a.threads)
    d = Path("data") / a.scene
    T = a.frames
    sc = fit_scene(a.scene, a.seq, a.views, a.rig.format(scene=a.scene), T)
    info, names, cams, views, rig = sc.info, sc.names, sc.cams, sc.views, sc.rig
    body, posed, Y, floor_G = sc.body, sc.posed, sc.Y, sc.floor_G
    floor_X = lbs(rig.rest, rig.weights, floor_G)
    params = scene_section(load_config("config/config.yaml"), "fit", a.scene)
    base = fit_config(params)

    def rmse(X, t):
        return 1e3 * float(((X - Y[t]) ** 2).sum(-1).mean().sqrt())

    def fragments(X, t):
        occ = FIT.occluder_depth(posed.vertices[t].double(), body.faces, views)
        return raster.occlude(raster.rasterize(X, rig.faces, views.K, views.world_to_cam, views.height, views.width,
                                               with_bary=False), occ)

    runs, chained = {}, {}
    paper = replace(base, w_photo=0.0, w_anchor=0.0)
    # texture-referenced L_an runs: the pipeline's lambda_N for them (fit/weights/normal_texture_anchor,
    # stages.fit.fit_config), without the variant's temporal filter
    texture = replace(FIT.config_for(paper, "anchor"), w_normal=fit_config(params, "anchor_texture").w_normal)
    wanted = set(a.runs.split(","))
    for key, name, cfg, oracle in (("chain", "chain (the paper's L_of; the default)", paper, False),
                                   ("oracle", "oracle targets (from the rig floor of t-1)", paper, True),
                                   ("photo", "chain + L_ph (variant photo)", FIT.config_for(paper, "photo"), False),
                                   ("anchor", "chain + L_an (variant anchor)", FIT.config_for(paper, "anchor"), False),
                                   ("anchor_texture", "chain + L_an on texture references (variant anchor_texture, "
                                    "unfiltered)", texture, False),
                                   ("anchor_texture_true_flows", "as anchor_texture, the true flows (gt/flows) in "
                                    "place of the estimated ones", texture, False),
                                   ("anchor_texture_no_flow", "as anchor_texture without L_of",
                                    replace(texture, w_flow=0.0), False),
                                   ("anchor_texture_oracle", "as anchor_texture, targets from the rig floor of t-1",
                                    texture, True)):
        if key not in wanted:
            continue
        cue_dir = d / a.seq / "gt" if a.cues == "ground_truth" else Path("results") / a.scene / a.seq
        for sub in ("masks", "flows"):
            if not (cue_dir / sub).is_dir():
                raise SystemExit(f"{cue_dir / sub}: not found (the pipeline's cues: run the masks / flows rules)")
        flow_dir = d / a.seq / "gt" / "flows" if key == "anchor_texture_true_flows" else cue_dir / "flows"
        reader = CueReader(cams, cue_dir / "masks", d / a.seq / "normals", flow_dir,
                            posed.vertices.double(), body.faces, views, torch.device("cpu"), num_frames=T,
                            seq_dir=d / a.seq if (cfg.w_photo > 0 or cfg.w_anchor > 0) else None)
        t0 = time.perf_counter()
        cues = reader.cues(0)
        anchor = None  # L_an's references (variant anchor), as fit_sequence keeps them
        if key.startswith("anchor_texture"):  # fixed references for every vertex from frame 0 on
            anchor, _ = texture_anchor_of(d, info, f"results/{a.scene}/template.npz", rig, views, floor_G[0],
                                          cfg.photo_blur, torch.device("cpu"))
        prev = FIT.fit_frame(rig, views, cues, floor_G[0], cfg, None, first=True, anchor=anchor)

        def update(anchor, prev, cues):
            if cfg.w_anchor == 0 or key.startswith("anchor_texture"):
                return anchor
            return FIT.update_anchor(anchor, prev.verts, views, prev.fragments, cues.image, cues.mask, cfg)

        anchor = update(anchor, prev, cues)
        out, mask_prev, G = [rmse(prev.verts, 0)], cues.mask, prev.transforms
        verts = [prev.verts]
        for t in range(1, T):
            cues = reader.cues(t)
            flow, valid = reader.flow(t)
            src_x, src_f = (floor_X[t - 1], fragments(floor_X[t - 1], t - 1)) if oracle else (prev.verts, prev.fragments)
            targets = FIT.flow_targets(src_x, views, src_f, flow, valid, mask_prev, cfg.vis_depth_tol,
                                       cfg.flow_margin_px)
            prev = FIT.fit_frame(rig, views, cues, G, cfg, targets, anchor=anchor)
            anchor = update(anchor, prev, cues)
            out.append(rmse(prev.verts, t))
            verts.append(prev.verts)
            mask_prev, G = cues.mask, prev.transforms
        runs[name] = (out, time.perf_counter() - t0)
        if key == "anchor_texture" and basin_frames:
            chained = basin(basin_frames, reader, rig, views, cfg, anchor, verts, floor_G, rmse)
        reader.close()
        print(f"{name}: mean {np.mean(out):.1f} mm", flush=True)
    floor = [rmse(floor_X[t], t) for t in range(T)]
    cols = list(range(0, T, 2))
    lines = [
        "# Garment fit drift: chained flow targets against re-anchored ones",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `.venv/bin/python benchmarks/fit_drift.py {' '.join(sys.argv[1:])}`",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} ({a.threads} threads), "
        f"Python {platform.python_version()}",
        f"- {a.scene}/{a.seq} ({info['image_size'][0]}x{info['image_size'][1]}), rig "
        f"`{a.rig.format(scene=a.scene)}`, first {T} frames, "
        f"{len(names)} views {names}; "
        f"{'ground-truth' if a.cues == 'ground_truth' else 'the pipeline' + chr(39) + 's'} masks and flows, shipped "
        "(degraded) normals; frame 0 starts on the rig floor (the rig's least-squares pose for the ground truth); "
        "fit settings of config/config.yaml (the scene's `fit` section).",
        "",
        "Vertex RMSE against the ground truth (mm), every other frame:",
        "",
        "| run | mean | " + " | ".join(f"t={t}" for t in cols) + " |",
        "| --- | ---: | " + " | ".join("---:" for _ in cols) + " |",
        f"| rig floor (reference) | {np.mean(floor):.1f} | " + " | ".join(f"{floor[t]:.1f}" for t in cols) + " |",
    ]
    for name, (out, _) in runs.items():
        lines.append(f"| {name} | {np.mean(out):.1f} | " + " | ".join(f"{out[t]:.1f}" for t in cols) + " |")
    lines += ["", "Wall time per run: " + ", ".join(f"{k}: {v:.0f} s" for k, (_, v) in runs.items()) + "."]
    if chained:
        lines += ["", "Loss basins of the `anchor_texture` run (`--basin`): the fit's loss with the configured weights "
                  "but without L_of (L_M, L_N, L_an; L_col not counted) at the chained fit, at a fit of the frame from "
                  "the rig floor run to convergence (relative tolerance 1e-6, up to 200 evaluations), and on the "
                  "straight line between the two meshes; vertex RMSE in mm:", "",
                  "| frame | rig floor RMSE | chained fit: RMSE | loss | from the floor, converged: RMSE | loss | "
                  "evaluations | loss, chained - converged | loss on the line chained -> converged at 1/4, 1/2, 3/4 |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
        for t, r in chained.items():
            lines.append(f"| {t} | {r['floor']:.1f} | {r['chain_rmse']:.1f} | {r['chain_loss']:.3f} | "
                         f"{r['conv_rmse']:.1f} | {r['conv_loss']:.3f} | {r['evals']} | "
                         f"{r['chain_loss'] - r['conv_loss']:+.3f} | " + ", ".join(f"{x:.3f}" for x in r["line"]) + " |")
    Path(a.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def basin(frames, reader, rig, views, cfg, anchor, verts, floor_G, rmse) -> dict:
    """Per frame t of ``frames``: the loss without L_of at the chained fit ``verts[t]``, at a
    converged fit of the frame started on the rig floor (same cues, same references) and on the
    straight line between the two meshes."""
    cf = replace(cfg, w_flow=0.0, max_iters=200, rel_tol=1e-6)
    out = {}
    for t in frames:
        cues = reader.cues(t)

        def loss(X):
            return float(FIT.loss_terms(rig, views, cues, X, None, cf, anchor=anchor)[0])

        res = FIT.fit_frame(rig, views, cues, floor_G[t], cf, None, anchor=anchor)
        floor = rmse(lbs(rig.rest, rig.weights, floor_G[t]), t)
        out[t] = {"floor": floor, "chain_rmse": rmse(verts[t], t), "chain_loss": loss(verts[t]),
                  "conv_rmse": rmse(res.verts, t), "conv_loss": loss(res.verts), "evals": res.iterations,
                  # on the straight line between the two meshes (skinning is linear in the transforms)
                  "line": [loss((1 - s) * verts[t] + s * res.verts) for s in (0.25, 0.5, 0.75)]}
        print(f"basin t={t}: {out[t]}", flush=True)
    return out


if __name__ == "__main__":
    main()
