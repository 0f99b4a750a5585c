"""Where the paper's loss has its minimum at frame 0, and where the fit stops.

Frame 0 has no flow term: L = 2.0 L_M + 0.1 L_N (the paper's weights). For each scene and
cue set, frame 0 of the training sequence is fitted (the `fit` stage's settings from
config/config.yaml) from two starts:

* the rig floor: the rig's least-squares pose for the ground-truth garment (not available
  in practice; where the loss's own minimum near the truth is);
* the simulated start: the rig's simulated pose of the sequence at frame 0 (what the `fit`
  stage starts from), with the paper's loss alone and with the config's first-frame
  proximal term (``fit/first_frame_prior``).

Both starts are also fitted with the loss the `fit` stage uses on the loose scenes (variant
``collision`` of the scene's ``fit`` section: the proximal term, L_an on the garment texture's
references with its lambda_N, L_col): from the rig floor that fit shows where the pipeline's own
loss has its minimum near the truth at frame 0.

For every pose the table gives the vertex RMSE against the ground truth and the paper's
loss evaluated with the same cues (without the proximal term), so one can read whether the
fit from the simulated start stops in a local minimum (its loss above the fit from the
floor) and how far the loss's minimum near the truth is from the rig floor. Cue sets: the
pipeline's masks, the ground-truth masks, each with the shipped (degraded) normal maps, and
the ground-truth masks with ground-truth normals. Writes benchmarks/fit_frame0.md. Not a test.

    .venv/bin/python benchmarks/fit_frame0.py --scenes skirt:walk,dress:sway --views 8
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

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from anidress_core import fit as FIT  # noqa: E402
from anidress_core.config import load_config, scene_section  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.stages.fit import CueReader, fit_config, texture_anchor_of  # noqa: E402
from benchutil import cpu_model, fit_scene  # noqa: E402


def error_parts(X: torch.Tensor, Y: torch.Tensor, faces) -> tuple[float, float, float]:
    """RMS (mm) of the vertex error X - Y (V, 3) along the ground truth's vertex normals, across
    them (tangential: the material sliding along the surface, what no image cue sees at frame 0
    without a texture model), and of X's distance to the ground-truth surface (mesh Y, faces)."""
    import numpy as np
    import trimesh

    m = trimesh.Trimesh(Y.numpy(), np.asarray(faces), process=False)
    n = torch.as_tensor(np.array(m.vertex_normals), dtype=Y.dtype)
    d = X - Y
    dn = (d * n).sum(-1)
    dt = d - dn[:, None] * n
    _, dist, _ = trimesh.proximity.closest_point(m, X.numpy())
    return (1e3 * float(dn.pow(2).mean().sqrt()), 1e3 * float(dt.pow(2).sum(-1).mean().sqrt()),
            1e3 * float(np.sqrt(np.mean(dist ** 2))))


def pipeline_loss(rig, views, cues, cfg, anchor, body_verts, body_faces):
    """X (V, 3) -> the loss ``cfg`` makes fit_frame minimise (the same evaluation, ``fit._evaluate``),
    without the proximal term (it depends on the start), L_col with its body contacts taken at X."""
    cq = cues._replace(occluder=FIT._occluder_or_inf(cues, views), occluder_mesh=None)
    pb = FIT._make_problem(rig, views, cq, None, replace(cfg, w_prior_first=0.0, w_collision=0.0), None, anchor, None)

    def value(X):
        col = 0.0
        if cfg.w_collision > 0:
            ct = FIT.body_contacts(X, body_verts, body_faces, cfg.collision_radius)
            col = cfg.w_collision * float(FIT._collision_residual(ct, X, cfg.collision_eps).pow(2).sum()) / X.shape[0]
        return FIT._evaluate(pb, X).loss + col
    return value


def bone_search(rig, G, loss, steps_m=(0.03, 0.06)):
    """One round of a coordinate search over the bones: each bone in turn is moved by every step of
    ``steps_m`` (m) along the 26 directions of a 3x3x3 grid; the move that lowers ``loss`` (of the
    skinned mesh) most is kept. Returns the new transforms G."""
    import itertools

    dirs = torch.tensor([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)], dtype=G.dtype)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    best_l = loss(lbs(rig.rest, rig.weights, G))
    for b in range(G.shape[0]):
        cand = None
        for m in steps_m:
            for d in dirs:
                G2 = G.clone()
                G2[b, :3, 3] += m * d
                val = loss(lbs(rig.rest, rig.weights, G2))
                if val < best_l:
                    best_l, cand = val, G2
        if cand is not None:
            G = cand
    return G


CUE_SETS = {  # name: (label, masks folder, normals folder)
    "pipeline": ("pipeline masks, shipped normals", "results/{scene}/{seq}/masks", "data/{scene}/{seq}/normals"),
    "gt_masks": ("GT masks, shipped normals", "data/{scene}/{seq}/gt/masks", "data/{scene}/{seq}/normals"),
    "gt": ("GT masks, GT normals", "data/{scene}/{seq}/gt/masks", "data/{scene}/{seq}/gt/normals"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="skirt:walk,dress:sway", help="scene:sequence pairs")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--rig", default="results/{scene}/rig.npz", help="rig file ({scene}: the scene's name)")
    ap.add_argument("--cue-sets", default=",".join(CUE_SETS), help="comma-separated keys of CUE_SETS")
    ap.add_argument("--search", type=int, default=0, help="rounds of the per-bone translation search "
                    "(bone_search, then the pipeline loss's LM fit) after the pipeline-loss fit from the simulated "
                    "start, on the pipeline cue set (0: none)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/fit_frame0.md")
    a = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(a.threads)
    config = load_config("config/config.yaml")
    params = config["fit"]
    default = fit_config(params)  # the fit section's settings (first-frame proximal term included)
    default = replace(default, w_photo=0.0, w_anchor=0.0, w_collision=0.0,
                      w_normal=float(params.get("weights", {}).get("normal", default.w_normal)))  # the paper's loss
    paper = replace(default, w_prior_first=0.0)
    photo = replace(default, w_photo=FIT.PHOTO_WEIGHT)
    # the pipeline's loss on the loose scenes: variant `collision` of the scene's fit section (L_an on
    # texture references, its lambda_N from weights/normal_texture_anchor, L_col, the proximal term)
    pipeline_cfg = {pair.split(":")[0]: fit_config(scene_section(config, "fit", pair.split(":")[0]), "collision")
                    for pair in a.scenes.split(",")}
    lines = [
        "# Garment fit, frame 0: where the paper's loss has its minimum, where the fit stops",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `.venv/bin/python benchmarks/fit_frame0.py {' '.join(sys.argv[1:])}`",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} ({a.threads} threads), "
        f"Python {platform.python_version()}",
        f"- rig: `{a.rig}`; frame 0 of each training sequence, {a.views} views; loss = the paper's frame-0 loss "
        f"{paper.w_mask} L_M + {paper.w_normal} L_N (no flow at frame 0), evaluated on the same cues for every pose "
        f"and without the proximal term; fits use config/config.yaml's `fit` settings; `+ prior` = the config's "
        f"first-frame proximal term (weight {default.w_prior_first}) towards the simulated start.",
        "- rows: `rig floor` and `simulated start` are poses, not fits; `fit from X` = the Levenberg-Marquardt fit "
        "of frame 0 started there.",
        "- error parts: the vertex error split along the ground truth's vertex normals (`normal`) and across them "
        "(`tangential`: material sliding along the surface, which a correct surface can still have), and the RMS "
        "distance of the vertices to the ground-truth surface (`to surface`).",
        f"- `+ L_ph`: the same fit with our multi-view photo-consistency term (weight {FIT.PHOTO_WEIGHT:g}, "
        "variant `photo`), which places the textured surface in depth.",
        "- `pipeline loss`: the loss the `fit` stage uses on the loose scenes (variant `collision` of the scene's "
        "`fit` section): the proximal term + L_an whose references are the garment texture's chromaticity at the "
        "template's UVs (`fit.texture_anchor`; weights " + "; ".join(
            f"{s}: L_an {c.w_anchor:g}, lambda_N {c.w_normal:g}, L_col {c.w_collision:g}"
            for s, c in pipeline_cfg.items()) + "), from the simulated start (what the stage does) and from the "
        "rig floor (where that loss's own minimum near the truth is). Column `pipeline loss`: that loss (without "
        "the proximal term, which depends on the start; L_col with the body contacts of the pose itself) at every "
        "pose, evaluated as fit_frame evaluates it.",
        *([f"- `per-bone search` (`--search {a.search}`, pipeline cues only): from the pipeline-loss fit from the "
           "simulated start, each bone in turn moved by 3 and 6 cm along the 26 directions of a 3x3x3 grid, the move "
           "that lowers the pipeline loss most kept, then the stage's LM fit; repeated per round (`bone_search`): "
           "a search past the LM's local minimum."] if a.search else []),
        "",
        "| scene/seq, image size | cues | pose | vertex RMSE mm | x rig floor | normal mm | tangential mm | "
        "to surface mm | loss | w_M L_M | w_N L_N | LM evaluations | pipeline loss |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    findings = []
    cue_sets = [c.strip() for c in a.cue_sets.split(",")]
    for c in cue_sets:
        if c not in CUE_SETS:
            raise SystemExit(f"--cue-sets: unknown cue set {c!r} (known: {list(CUE_SETS)})")
    for pair in a.scenes.split(","):
        scene, seq = pair.split(":")
        rig_path = a.rig.format(scene=scene)
        sc = fit_scene(scene, seq, a.views, rig_path, frames=1)
        info, cams, views, art, rig, body = sc.info, sc.cams, sc.views, sc.art, sc.rig, sc.body
        label = f"{scene}/{seq} {info['image_size'][0]}x{info['image_size'][1]}"
        posed_verts = sc.posed.vertices[:1]
        Y, floor_G = sc.Y[0], sc.floor_G[0]
        sim_name = f"seq-{seq}"
        if sim_name not in art.sequences:
            raise SystemExit(f"{rig_path}: no simulated sequence {sim_name!r}")
        sim_G = art.transforms_of(sim_name)[0].double()
        rmse = lambda X: 1e3 * float(((X - Y) ** 2).sum(-1).mean().sqrt())  # noqa: E731
        floor_rmse = rmse(lbs(rig.rest, rig.weights, floor_G))
        for cue_set in cue_sets:
            cue_name, mdir, ndir = CUE_SETS[cue_set]
            mdir, ndir = Path(mdir.format(scene=scene, seq=seq)), Path(ndir.format(scene=scene, seq=seq))
            if not mdir.is_dir():
                raise SystemExit(f"{mdir}: masks not found (run the pipeline's `masks` rule for {scene}/{seq})")
            reader = CueReader(cams, mdir, ndir, None, posed_verts.double(), body.faces, views,
                                torch.device("cpu"), num_frames=1, seq_dir=Path(f"data/{scene}/{seq}"))
            cues = reader.cues(0)
            reader.close()

            def loss(X):
                total, terms = FIT.loss_terms(rig, views, cues, X, None, paper)
                return float(total), paper.w_mask * float(terms["mask"]), paper.w_normal * float(terms["normal"])

            poses = {"rig floor": (lbs(rig.rest, rig.weights, floor_G), None),
                     "simulated start": (lbs(rig.rest, rig.weights, sim_G), None)}
            t0 = time.perf_counter()
            tex_ref, _ = texture_anchor_of(Path(f"data/{scene}"), info, f"results/{scene}/template.npz", rig, views,
                                           sim_G, default.photo_blur, torch.device("cpu"))
            for name, start, cfg, anchor in (
                    ("fit from rig floor", floor_G, paper, None), ("fit from simulated start", sim_G, paper, None),
                    ("fit from simulated start + prior", sim_G, default, None),
                    ("fit from simulated start + prior + L_ph", sim_G, photo, None),
                    ("fit from simulated start, pipeline loss", sim_G, pipeline_cfg[scene], tex_ref),
                    ("fit from rig floor, pipeline loss", floor_G, pipeline_cfg[scene], tex_ref)):
                r = FIT.fit_frame(rig, views, cues, start, cfg, None, first=True, anchor=anchor)
                poses[name] = (r.verts.detach(), r.iterations)
                if name == "fit from simulated start, pipeline loss":
                    G_pipe = r.transforms
            ploss = pipeline_loss(rig, views, cues, pipeline_cfg[scene], tex_ref, posed_verts[0].double(), body.faces)
            if a.search > 0 and cue_set == "pipeline":
                G, its = G_pipe, 0
                for _ in range(a.search):
                    G = bone_search(rig, G, ploss)
                    r = FIT.fit_frame(rig, views, cues, G, pipeline_cfg[scene], None, first=True, anchor=tex_ref)
                    G, its = r.transforms, its + r.iterations
                poses[f"fit from simulated start, pipeline loss + {a.search} rounds of per-bone search"] = (
                    r.verts.detach(), its)
            print(f"{label} {cue_name}: {time.perf_counter() - t0:.0f} s", flush=True)
            res = {}
            for name, (X, its) in poses.items():
                e, (ls, lm, ln), pl = rmse(X), loss(X), ploss(X)
                res[name] = (e, ls) + error_parts(X, Y, rig.faces) + (pl,)
                lines.append(f"| {label} | {cue_name} | {name} | {e:.1f} | {e / floor_rmse:.2f} | "
                             f"{res[name][2]:.1f} | {res[name][3]:.1f} | {res[name][4]:.1f} | {ls:.4f} | "
                             f"{lm:.4f} | {ln:.4f} | {'' if its is None else its} | {pl:.3f} |")
            ff, fs = res["fit from rig floor"], res["fit from simulated start"]
            if abs(fs[1] - ff[1]) <= 0.01 * ff[1]:
                verdict = "as low as the fit from the floor (within 1 %): the loss does not tell them apart"
            elif fs[1] > ff[1]:
                verdict = "above the fit from the floor: a local minimum"
            else:
                verdict = "below the fit from the floor: the loss prefers it"
            findings.append(
                f"- {label}, {cue_name}: fitted from the rig floor, frame 0 ends at {ff[0]:.1f} mm = "
                f"{ff[0] / floor_rmse:.2f} x the rig floor{' (above 1.5 x)' if ff[0] > 1.5 * floor_rmse else ''}; "
                f"from the simulated start at {fs[0]:.1f} mm, with loss {fs[1]:.5f} against {ff[1]:.5f}, {verdict}.")
            ss, fp, fph, ftx, fl, fpf = (res[k] for k in ("simulated start", "fit from simulated start + prior",
                                                          "fit from simulated start + prior + L_ph",
                                                          "fit from simulated start, pipeline loss", "rig floor",
                                                          "fit from rig floor, pipeline loss"))
            findings.append(
                f"  Tangential error (material sliding): simulated start {ss[3]:.1f} mm, after the paper's loss + "
                f"prior {fp[3]:.1f}, with L_ph {fph[3]:.1f}, with the pipeline's loss {ftx[3]:.1f} (rig floor "
                f"{fl[3]:.1f}); distance to the true surface: {ss[4]:.1f} -> {fp[4]:.1f} -> {fph[4]:.1f} / "
                f"{ftx[4]:.1f} mm (rig floor {fl[4]:.1f}); vertex RMSE with the pipeline's loss {ftx[0]:.1f} mm = "
                f"{ftx[0] / floor_rmse:.2f} x the floor from the simulated start, {fpf[0]:.1f} mm = "
                f"{fpf[0] / floor_rmse:.2f} x from the rig floor"
                f"{' (above 1.5 x: that loss has its minimum there)' if fpf[0] > 1.5 * floor_rmse else ''}.")
            srch = [k for k in res if "per-bone search" in k]
            findings.append(
                f"  The pipeline's loss (no proximal term): {fl[5]:.3f} at the rig floor, {fpf[5]:.3f} fitted from "
                f"there, {ftx[5]:.3f} fitted from the simulated start"
                + "".join(f"; after {k.split('+ ')[-1]}: {res[k][5]:.3f} at {res[k][0]:.1f} mm = "
                          f"{res[k][0] / floor_rmse:.2f} x the floor" for k in srch) + ".")
    lines += ["", "## Reading", ""] + findings
    Path(a.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
