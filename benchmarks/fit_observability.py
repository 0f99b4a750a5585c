"""Where the garment fit's 3D error sits: per vertex, by how many training views see it, and
how far off the fitted vertices are *in the images*.

The fit (the `fit` stage's own ``run_fit``, the scene's ``fit`` section = the pipeline's loss) is
run on the first frames of a loose-garment sequence; then, per frame, against the synthetic ground
truth ``Y`` and against the rig floor (the rig's least-squares pose for ``Y``):

* vertex RMSE over all vertices, and over the vertices seen by 0, 1 and >= 2 of the training
  views (seen: the ground-truth vertex is visible in the view, the body an occluder,
  :func:`anidress_core.raster.visible_vertices`) -- is the error where no image can see it?
* the vertex error along the ground truth's vertex normals (depth of the surface) and across
  them (material sliding);
* the 2D reprojection error in pixels, RMS over the (view, vertex) pairs where the ground-truth
  vertex is seen -- what every image cue (masks, normals, flows, colours) can measure at best;
  and the image footprint of a pixel at the garment (mm per pixel), to read the two together.

Writes ``<out>.md`` and ``<out>.csv`` (one row per run: means over the frames). Not a test.

    .venv/bin/python benchmarks/fit_observability.py --runs skirt:walk,dress:sway --views 8,4 --frames 30
"""
from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import sys
import tempfile
import time
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
from anidress_core.stages.fit import fit_config, run_fit  # noqa: E402
from benchutil import cpu_model, fit_scene, git_rev  # noqa: E402
from fit_frame0 import error_parts  # noqa: E402

#: visibility depth tolerance (m) of the ground truth's visible vertices, the fit's default
VIS_TOL = 0.01


def frame_stats(X: torch.Tensor, F: torch.Tensor, Y: torch.Tensor, faces: torch.Tensor, views: FIT.Views,
                occluder: torch.Tensor) -> dict:
    """One frame: fitted X, rig floor F, ground truth Y (V, 3); occluder (C, H, W) body depth."""
    frags = raster.occlude(raster.rasterize(Y, faces, views.K, views.world_to_cam, views.height, views.width,
                                            with_bary=False), occluder)
    seen = raster.visible_vertices(Y, views.K, views.world_to_cam, frags, VIS_TOL)  # (C, V)
    n = seen.sum(0)
    uv_y, z_y = raster.project_vertices(Y, views.K, views.world_to_cam)
    out = {}
    for key, M in (("fit", X), ("floor", F)):
        e2 = ((M - Y) ** 2).sum(-1)
        out[f"{key}_rmse"] = 1e3 * float(e2.mean().sqrt())
        for name, m in (("0", n == 0), ("1", n == 1), ("2+", n >= 2)):
            out[f"{key}_rmse_{name}"] = 1e3 * float(e2[m].mean().sqrt()) if bool(m.any()) else float("nan")
        uv, _ = raster.project_vertices(M, views.K, views.world_to_cam)
        out[f"{key}_px"] = float(((uv - uv_y) ** 2).sum(-1)[seen].mean().sqrt())
        out[f"{key}_normal"], out[f"{key}_tangential"], _ = error_parts(M, Y, faces)
    for name, m in (("0", n == 0), ("1", n == 1), ("2+", n >= 2)):
        out[f"share_{name}"] = float(m.double().mean())
    focal = 0.5 * (views.K[:, 0, 0] + views.K[:, 1, 1])  # (C,)
    out["mm_per_px"] = 1e3 * float((z_y / focal[:, None])[seen].mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="skirt:walk,dress:sway", help="scene:sequence pairs")
    ap.add_argument("--views", default="8,4")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/fit_observability")
    a = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(a.threads)
    config = load_config("config/config.yaml")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for pair in a.runs.split(","):
            scene, seq = pair.split(":")
            for nv in (int(v) for v in a.views.split(",")):
                params = dict(scene_section(config, "fit", scene), frames=a.frames, views=nv, threads=a.threads)
                res = Path(f"results/{scene}/{seq}")
                for sub in ("masks", "flows"):
                    if not (res / sub).is_dir():
                        raise SystemExit(f"{res / sub}: not found (run the pipeline's masks / flows rules for "
                                         f"{scene}/{seq})")
                out_npz = Path(tmp) / f"{scene}_{seq}_{nv}.npz"
                t0 = time.perf_counter()
                run_fit(f"data/{scene}", seq, f"results/{scene}/rig.npz", f"results/{scene}/template.npz",
                        res / "masks", res / "flows", f"data/{scene}/{seq}/normals", params, out_npz, progress=False)
                wall = time.perf_counter() - t0
                X = torch.as_tensor(np.load(out_npz)["verts"]).double()
                sc = fit_scene(scene, seq, nv, f"results/{scene}/rig.npz", a.frames)
                T = min(a.frames, X.shape[0], sc.Y.shape[0])
                floor = lbs(sc.rig.rest, sc.rig.weights, sc.floor_G)
                stats = []
                for t in range(T):
                    occ = FIT.occluder_depth(sc.posed.vertices[t].double(), sc.body.faces, sc.views)
                    stats.append(frame_stats(X[t], floor[t], sc.Y[t], sc.rig.faces, sc.views, occ))
                mean = {k: float(np.nanmean([s[k] for s in stats])) for k in stats[0]}
                cfg = fit_config(params)
                rows.append({"scene": scene, "sequence": seq, "views": nv, "frames": T,
                             "lambda_N": cfg.w_normal, "w_anchor": cfg.w_anchor,
                             **{k: round(v, 4) for k, v in mean.items()}})
                print(f"{scene}/{seq} {nv} views: fit {mean['fit_rmse']:.2f} mm, floor {mean['floor_rmse']:.2f}, "
                      f"2D {mean['fit_px']:.3f} / {mean['floor_px']:.3f} px ({wall:.0f} s)", flush=True)
    with open(f"{a.out}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [
        "# Garment fit: where its 3D error sits, and how far off it is in the images",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `.venv/bin/python benchmarks/fit_observability.py {' '.join(sys.argv[1:])}` (git {git_rev()})",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} ({a.threads} threads), "
        f"Python {platform.python_version()}",
        "- fit: the `fit` stage's `run_fit` with the scene's `fit` section of config/config.yaml (the pipeline's "
        "loss: L_M, L_N, L_of + L_an on texture references, L_col), the pipeline's masks and flows, shipped normals; "
        f"first {a.frames} frames, frame 0 from the simulated start, as the stage runs it (its temporal filter "
        "included).",
        "- reference: the rig floor (the rig's least-squares pose for the ground truth, per frame).",
        f"- seen: a ground-truth vertex visible in a training view (body occluding, depth tolerance {VIS_TOL} m); "
        "the columns `0 / 1 / >=2 views` split the vertices by how many training views see them (share of the "
        "garment's vertices, mean over frames).",
        "- 2D error: RMS distance in pixels between the projections of the fitted (or floor) vertex and of the "
        "ground-truth vertex, over the (view, vertex) pairs where the ground-truth vertex is seen; `mm / px`: the "
        "mean image footprint of a pixel at those vertices.",
        "- all figures: means over the frames of the per-frame values (mm unless marked).",
        "",
        "| scene/seq | views | vertex RMSE fit / floor (x) | seen by >= 2 views: share, fit / floor (x) | "
        "seen by 1: share, fit / floor | seen by 0: share, fit / floor | along normals fit / floor | "
        "tangential fit / floor | 2D error px fit / floor (x) | mm / px |",
        "| --- | ---: | --- | --- | --- | --- | --- | --- | --- | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']}/{r['sequence']} | {r['views']} | {r['fit_rmse']:.2f} / {r['floor_rmse']:.2f} "
            f"({r['fit_rmse'] / r['floor_rmse']:.2f}) | {100 * r['share_2+']:.1f} %: {r['fit_rmse_2+']:.2f} / "
            f"{r['floor_rmse_2+']:.2f} ({r['fit_rmse_2+'] / r['floor_rmse_2+']:.2f}) | {100 * r['share_1']:.1f} %: "
            f"{r['fit_rmse_1']:.1f} / {r['floor_rmse_1']:.1f} | {100 * r['share_0']:.1f} %: {r['fit_rmse_0']:.1f} / "
            f"{r['floor_rmse_0']:.1f} | {r['fit_normal']:.2f} / {r['floor_normal']:.2f} | {r['fit_tangential']:.2f} / "
            f"{r['floor_tangential']:.2f} | {r['fit_px']:.3f} / {r['floor_px']:.3f} ({r['fit_px'] / r['floor_px']:.2f})"
            f" | {r['mm_per_px']:.1f} |")
    lines += ["", "## Reading (generated from the rows)", ""]
    for r in rows:
        lines.append(
            f"- {r['scene']}/{r['sequence']}, {r['views']} views: {r['fit_rmse'] / r['floor_rmse']:.2f} x the floor "
            f"over all vertices, {r['fit_rmse_2+'] / r['floor_rmse_2+']:.2f} x over the {100 * r['share_2+']:.0f} % "
            f"seen by two or more views; in the images the fitted vertices are {r['fit_px']:.2f} px from the truth "
            f"where it is seen, the floor {r['floor_px']:.2f} px ({r['fit_px'] / r['floor_px']:.2f} x), one pixel "
            f"covering {r['mm_per_px']:.1f} mm there.")
    Path(f"{a.out}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
