"""lambda_N with L_an on: the pipeline's fit (rule `fit`, the scene's settings of config.yaml) with
the normal term's weight swept, for L_an's two kinds of references, against the synthetic
ground truth.

At its weight (1e5) L_an is ~99 % of the fit's loss (per-frame terms of the pipeline's fit:
2 L_M ~ 0.1, 0.1 L_N ~ 0.01, 1e5 L_an ~ 40), so with the paper's lambda_N = 0.1 the normal maps
barely count. Each run is `stages.fit.run_fit` on the pipeline's cues with lambda_N set to the
value wherever it applies (`weights/normal` and `weights/normal_texture_anchor` both), and
L_an's references from the garment texture (`texture`) or from the first frame each vertex is
seen (`images`); `paper` rows are the paper's loss (no L_an, L_col, L_ph, no filter; fit.md's
`full`) with `weights/normal` at the value. Reported: the vertex RMSE against the ground truth
in the template's topology (mean over the frames), its ratio to the rig floor (the rig's
least-squares pose for the ground truth) and the acceleration error (mean |second difference|
of fit - ground truth, the jitter a fit adds). Not a test.

    .venv/bin/python benchmarks/fit_normal_weight.py --runs skirt/walk,skirt/dance,dress/sway \\
        --refs texture,images --values 0.1,30,100,300 --views 8,4 --frames 30
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

from anidress_core.config import load_config, scene_section  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.stages.fit import load_garment_poses, run_fit  # noqa: E402
from benchutil import cpu_model, fit_scene, git_rev  # noqa: E402

KEY = ("scene", "seq", "views", "loss", "lambda_n")


def params_of(base: dict, loss: str, value: float, frames: int, views: int) -> dict:
    """The fit section of one run: ``loss`` 'texture' / 'images' (the pipeline's fit, L_an's
    references) or 'paper' (the paper's loss), lambda_N = ``value``."""
    p = dict(base, frames=frames, views=views)
    if loss == "paper":
        return dict(p, smooth_passes=0, weights=dict(base["weights"], normal=value, normal_texture_anchor=0.0,
                                                      photo=0.0, anchor=0.0, collision=0.0))
    return dict(p, anchor_reference=loss, weights=dict(base["weights"], normal=value, normal_texture_anchor=value))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="skirt/walk,skirt/dance,dress/sway", help="scene/seq, comma-separated")
    ap.add_argument("--refs", default="texture,images", help="L_an's references: texture and/or images")
    ap.add_argument("--values", default="0.1,30,100,300", help="lambda_N values")
    ap.add_argument("--paper-values", default="", help="also the paper's loss with weights/normal at these values")
    ap.add_argument("--views", default="8,4")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/fit_normal_weight")
    ap.add_argument("--merge", action="store_true", help="keep the rows of <out>.csv that this run does not redo")
    a = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(a.threads)
    cfg = load_config("config/config.yaml")
    plan = [(ref, float(v)) for ref in a.refs.split(",") if ref for v in a.values.split(",")]
    plan += [("paper", float(v)) for v in a.paper_values.split(",") if v]
    rows = []
    for run in a.runs.split(","):
        scene, seq = run.split("/")
        rig_npz, res = f"results/{scene}/rig.npz", Path("results") / scene / seq
        for need in (rig_npz, res / "masks", res / "flows"):
            if not Path(need).exists():
                raise SystemExit(f"{need}: not found (build the scene's rig and cues first: snakemake {rig_npz} "
                                 f"{res}/masks {res}/flows --config 'run_scenes=[{scene}]')")
        sc = fit_scene(scene, seq, 8, rig_npz, a.frames)  # the ground truth in the rig's topology, the rig floor
        art, Y = sc.art, sc.Y
        floor = lbs(art.model.rest, art.model.weights, sc.floor_G)
        floor_rmse = float(((floor - Y) ** 2).sum(-1).mean(-1).sqrt().mean())
        base = scene_section(cfg, "fit", scene)
        for nv in (int(x) for x in a.views.split(",")):
            for loss, value in plan:
                with tempfile.TemporaryDirectory() as tmp:
                    out = Path(tmp) / "garment_poses.npz"
                    t0 = time.perf_counter()
                    run_fit(f"data/{scene}", seq, rig_npz, f"results/{scene}/template.npz", res / "masks",
                            res / "flows", f"data/{scene}/{seq}/normals", params_of(base, loss, value, a.frames, nv),
                            out, progress=False)
                    wall = time.perf_counter() - t0
                    G = torch.as_tensor(load_garment_poses(out)[0]["transforms"]).double()
                e = lbs(art.model.rest, art.model.weights, G) - Y
                rmse = float((e ** 2).sum(-1).mean(-1).sqrt().mean())
                acc = float((e[2:] - 2 * e[1:-1] + e[:-2]).norm(dim=-1).mean())
                row = {"scene": scene, "seq": seq, "views": nv, "loss": loss, "lambda_n": value,
                       "vertex_rmse_mm": 1e3 * rmse, "rig_floor_mm": 1e3 * floor_rmse, "ratio": rmse / floor_rmse,
                       "accel_error_mm": 1e3 * acc, "fps": a.frames / wall}
                rows.append(row)
                print(row, flush=True)
    if a.merge and Path(f"{a.out}.csv").is_file():
        with open(f"{a.out}.csv") as fh:
            old = [{k: (int(v) if k == "views" else v if k in ("scene", "seq", "loss") else float(v))
                    for k, v in r.items()} for r in csv.DictReader(fh)]
        done = {tuple(r[k] for k in KEY) for r in rows}
        rows = [r for r in old if tuple(r[k] for k in KEY) not in done] + rows
    write(rows, a)


def write(rows: list[dict], a) -> None:
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    with open(f"{a.out}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    by = {tuple(r[k] for k in KEY): r for r in rows}
    floor = {(r["scene"], r["seq"], r["views"]): r["rig_floor_mm"] for r in rows}
    values = sorted({r["lambda_n"] for r in rows})
    lines = [
        "# lambda_N with L_an on: the pipeline's fit against the ground truth",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `.venv/bin/python benchmarks/fit_normal_weight.py {' '.join(sys.argv[1:])}` "
        f"(git {git_rev(('anidress_core',))})",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch {torch.__version__} ({a.threads} threads), "
        f"Python {platform.python_version()}",
        f"- first {a.frames} frames, the pipeline's masks and flows and the shipped (degraded) normals. `texture` / "
        "`images`: the pipeline's fit (config/config.yaml with the scene's fit section: L_an, L_col, the temporal "
        "filter) with L_an's references from the garment texture / from the first frame each vertex is seen, "
        "lambda_N at the column's value; `paper`: the paper's loss (fit.md's `full`) with lambda_N at the value. "
        "The paper's lambda_N is 0.1.",
        "",
        "Vertex RMSE against the ground truth, mean over the frames, mm (ratio to the rig floor; "
        "acceleration error mm); -- = not run:",
        "",
        "| scene/seq | views | rig floor mm | loss | " + " | ".join(f"lambda_N {v:g}" for v in values) + " |",
        "| --- | ---: | ---: | --- | " + " | ".join("---:" for _ in values) + " |",
    ]
    for s, q, nv, loss in dict.fromkeys((r["scene"], r["seq"], r["views"], r["loss"]) for r in rows):
        cells = []
        for v in values:
            r = by.get((s, q, nv, loss, v))
            cells.append("--" if r is None else f"{r['vertex_rmse_mm']:.2f} ({r['ratio']:.2f}x; {r['accel_error_mm']:.2f})")
        lines.append(f"| {s}/{q} | {nv} | {floor[(s, q, nv)]:.2f} | {loss} | " + " | ".join(cells) + " |")
    fps = [r["fps"] for r in rows]
    lines += ["", f"Fit speed over all runs: median {np.median(fps):.2f} frames/s (min {min(fps):.2f}, max "
              f"{max(fps):.2f}; cue loading included, 2 cores shared)."]
    Path(f"{a.out}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
