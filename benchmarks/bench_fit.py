"""Benchmark of the garment fit (anidress_core.fit) against the synthetic ground truth.

For each scene, sequence and number of training views, fits the full method and the
paper's ablations (a) vertex, (b) no_normal_flow, (c) no_flow and our variants ``photo`` (the
full loss + multi-view photo-consistency L_ph) and ``anchor`` (the full loss + the temporal
chromaticity anchor L_an) with the same cues, then
measures every frame against the ground-truth garment (stages.fit.run_fit_eval): vertex
RMSE (mean, 95th percentile, worst frame), Chamfer distance, normal consistency,
temporal jitter and acceleration error, frames per second; and the rig's floor on the
same motion (RMSE of rig.fit_transforms on the ground-truth meshes in template
topology). A second reference, ``sim``, is no fit at all: the rig driven by its own simulated
poses of the sequence (``rig.transforms_of('seq-<name>')``, the cloth simulation of the
template on the sequence's body motion, paper §4.5): what fitting to the images adds over
the simulator. Writes benchmarks/fit.md and benchmarks/fit.csv; fitted poses go to
benchmarks/runs/fit/ (not committed).

    .venv/bin/python -m benchmarks.bench_fit --scenes skirt --views 8,4 --cues pipeline
"""
from __future__ import annotations

import argparse
import csv
import datetime
import functools
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from anidress_core.config import load_config
from anidress_core.stages import setup_logging
from anidress_core.fit import FitConfig
from anidress_core.stages.fit import load_garment_poses, run_fit, run_fit_eval
from anidress_core.io.scene import read_scene
from benchmarks.benchutil import git_rev

REPO = Path(__file__).resolve().parents[1]

# the code whose uncommitted changes the git revision of a run's table flags
CODE_PATHS = ("anidress_core/fit", "anidress_core/raster.py", "anidress_core/stages/fit.py")

METHODS = ["full", "collision", "vertex", "no_normal_flow", "no_flow"]
# the loss variant (anidress_core.fit.variants) each method runs: `full` is the paper's loss, `collision`
# the pipeline's (L_an on texture references, L_col, L_prior, filtered)
VARIANT_OF = {"full": "paper", "collision": "pipeline", "vertex": "paper_vertex",
              "no_normal_flow": "paper_no_normal_flow", "no_flow": "paper_no_flow"}
LABEL = {"sim": "reference: simulation only (rig driven by the simulated poses, no fit)",
         "full": "full (rig, L_M + L_N + L_of)", "photo": "ours: full + L_ph (photo-consistency)",
         "anchor": "ours: full + L_an (chromaticity anchor)",
         "anchor_smooth": "ours: full + L_an, poses filtered over time (1 pass)",
         "anchor_texture": "ours: full + L_an with references from the garment texture, filtered (1 pass)",
         "collision": "ours: the pipeline's loss (L_an on texture references + L_col + L_prior, filtered)",
         "vertex": "(a) vertex fit, no rig", "no_normal_flow": "(b) L_M only", "no_flow": "(c) L_M + L_N"}
PAPER_ABLATIONS = ("vertex", "no_normal_flow", "no_flow")


def cue_dirs(scene: str, seq: str, source: str) -> dict:
    if source == "ground_truth":
        return {"masks": f"data/{scene}/{seq}/gt/masks", "flows": f"data/{scene}/{seq}/gt/flows",
                "normals": f"data/{scene}/{seq}/normals", "label": "gt masks + gt flows + shipped degraded normals"}
    masks = f"results/{scene}/{seq}/masks"
    flows = f"results/{scene}/{seq}/flows"
    for d in (masks, flows):
        if not (REPO / d).is_dir():
            raise SystemExit(f"{d}: pipeline cues not found; run `snakemake --cores 2 {d}` first or use --cues "
                             "ground_truth")
    return {"masks": masks, "flows": flows, "normals": f"data/{scene}/{seq}/normals",
            "label": "pipeline masks + pipeline flows (config cues) + shipped degraded normals"}


def write_sim_poses(rig_npz: str, seq: str, frames: int, out: Path) -> None:
    """The ``sim`` reference as a garment_poses.npz: the rig driven by its simulated poses of ``seq``."""
    from anidress_core.geometry import lbs
    from anidress_core.io import files
    from anidress_core.io.rig import read_rig

    art = read_rig(rig_npz, dtype=torch.float64)
    name = f"seq-{seq}"
    if name not in art.sequences:
        raise SystemExit(f"{rig_npz}: no simulated sequence {name!r} (has {sorted(art.sequences)})")
    G = art.transforms_of(name).double()
    G = G[:frames] if frames else G
    T = G.shape[0]
    X = lbs(art.model.rest, art.model.weights, G)
    nan = np.full(T, np.nan)
    files.save_npz(out, {"transforms": G.float().numpy(), "verts": X.float().numpy(),
                         "faces": np.asarray(art.faces, np.int64), "loss": nan, "iterations": np.zeros(T, np.int64),
                         "wall_s": nan},
                   meta={"method": "sim", "description": LABEL["sim"], "rig": rig_npz, "sequence": seq, "frames": T,
                         "fps": float("nan"), "wall_fit_s": float("nan"), "cpu_fit_s": float("nan"),
                         "torch_threads": torch.get_num_threads(), "source": f"rig.transforms_of({name!r})"})


@functools.lru_cache(maxsize=None)
def chamfer_bias(scene: str, seq: str, samples: int) -> float:
    """The Chamfer of the ground-truth garment of frame 0 against itself (two independent
    sample sets of ``samples`` points): what the Chamfer column reads for a perfect fit."""
    from anidress_core.metrics import mesh as MM

    d = np.load(f"data/{scene}/{seq}/gt/meshes.npz")
    V = torch.as_tensor(d["garment_vertices"][0]).double()
    F = torch.as_tensor(d["garment_faces"]).long()
    a, b = (MM.surface_samples(V, F, samples, torch.Generator().manual_seed(s)) for s in (1, 2))
    return MM.chamfer_normal(a, b).chamfer


def stats(x: np.ndarray, worst="max") -> tuple[float, float, float]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (float("nan"),) * 3
    return float(x.mean()), float(np.percentile(x, 95 if worst == "max" else 5)), float(x.max() if worst == "max"
                                                                                        else x.min())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="skirt")
    ap.add_argument("--seq", default="train", help="sequence names, or 'train' (the train-role sequence)")
    ap.add_argument("--views", default="8,4")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--no-sim", action="store_true", help="leave out the simulation-only reference row")
    ap.add_argument("--cues", default="pipeline", choices=["pipeline", "ground_truth"])
    ap.add_argument("--frames", type=int, default=0, help="fit only the first N frames (0: all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--out", default="benchmarks/fit")
    ap.add_argument("--reuse", action="store_true", help="reuse fitted poses already in benchmarks/runs/fit")
    args = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(args.threads)
    log = setup_logging(None)
    cfg = load_config("config/config.yaml")
    params = {k: v for k, v in cfg["fit"].items() if k not in ("ablations", "eval")}
    params["threads"] = args.threads
    # lambda_N of the paper's loss (`full` and its ablations) and of the pipeline's (`collision`)
    lam_n, lam_n_an = FitConfig.from_config(params, "paper").weights.normal, FitConfig.from_config(params).weights.normal
    load0 = os.getloadavg()
    rows, notes = [], []
    command = "  ".join([".venv/bin/python -m benchmarks.bench_fit"] + sys.argv[1:])
    for scene in args.scenes.split(","):
        info = read_scene(f"data/{scene}")
        seqs = [s["name"] for s in info["sequences"] if s.get("role") == "train"] if args.seq == "train" else \
            args.seq.split(",")
        rig = f"results/{scene}/rig.npz"
        for seq in seqs:
            dirs = cue_dirs(scene, seq, args.cues)
            for nv in (int(v) for v in args.views.split(",")):
                fits, timing = {}, {}
                if not args.no_sim:  # no fitting: cheap, always recomputed
                    out = Path(f"benchmarks/runs/fit/{scene}/{seq}/{args.cues}/v{nv}/sim/garment_poses.npz")
                    write_sim_poses(rig, seq, args.frames, out)
                    fits["sim"], timing["sim"] = out, load_garment_poses(out)[1]["meta"]
                for method in args.methods.split(","):
                    out = Path(f"benchmarks/runs/fit/{scene}/{seq}/{args.cues}/v{nv}/{method}/garment_poses.npz")
                    p = dict(params, views=nv)
                    if args.frames:
                        p["frames"] = args.frames
                    if not (args.reuse and out.is_file()):
                        t0 = time.perf_counter()
                        run_fit(f"data/{scene}", seq, rig, f"results/{scene}/template.npz", dirs["masks"],
                                dirs["flows"], dirs["normals"], p, out, ablation=VARIANT_OF.get(method, method),
                                progress=False, cue_source=dirs["label"])
                        log.info("bench_fit: %s %s v%d %s: %.1f s", scene, seq, nv, method, time.perf_counter() - t0)
                    fits[method] = out
                    timing[method] = load_garment_poses(out)[1]["meta"]
                csv_path = Path(f"benchmarks/runs/fit/{scene}/{seq}/{args.cues}/v{nv}/fit_metrics.csv")
                summ = run_fit_eval(f"data/{scene}", seq, rig, fits, csv_path, samples=args.samples)
                with open(csv_path) as fh:
                    per = list(csv.DictReader(fh))
                for method in fits:
                    r = [x for x in per if x["method"] == method]
                    col = lambda k: np.array([float(x[k]) for x in r])  # noqa: E731
                    meta = timing[method]
                    vr, fl = col("vertex_rmse_m"), col("rig_floor_rmse_m")
                    row = {
                        "scene": scene, "sequence": seq, "views": nv, "method": method, "cues": args.cues,
                        "frames": len(r), "reference": "rig floor (rig.fit_transforms on GT meshes)",
                        "rig_floor_rmse_m": float(fl.mean()),
                        "fps": meta["fps"], "wall_fit_s": meta["wall_fit_s"], "torch_threads": meta["torch_threads"],
                        "cpu_s_per_frame": meta.get("cpu_fit_s", float("nan")) / max(len(r), 1),
                        "iterations_mean": float(col("iterations").mean()),
                    }
                    for k, worst in (("vertex_rmse_m", "max"), ("chamfer_m", "max"), ("normal_consistency", "min")):
                        m, p95, w = stats(col(k), worst)
                        row[f"{k}_mean"], row[f"{k}_p95" if worst == "max" else f"{k}_p5"], row[f"{k}_worst"] = m, p95, w
                    row["worst_frame"] = int(np.nanargmax(vr))
                    row["jitter_m"] = float(np.nanmean(col("jitter_m")))
                    row["gt_jitter_m"] = float(np.nanmean(col("gt_jitter_m")))
                    row["accel_error_m"] = float(np.nanmean(col("accel_error_m")))
                    row["rmse_over_floor"] = row["vertex_rmse_m_mean"] / row["rig_floor_rmse_m"]
                    row["rig_floor_chamfer_m"] = float(col("rig_floor_chamfer_m").mean())
                    row["chamfer_over_floor"] = row["chamfer_m_mean"] / row["rig_floor_chamfer_m"]
                    rows.append(row)
                notes.append(f"{scene}/{seq}, {nv} views: template -> ground-truth correspondence distance mean "
                             f"{1e3 * summ['correspondence_mean_m']:.2f} mm, max {1e3 * summ['correspondence_max_m']:.2f}"
                             f" mm; Chamfer sampling bias (the ground truth of frame 0 against itself, two independent "
                             f"sample sets): {1e3 * chamfer_bias(scene, seq, args.samples):.2f} mm; cues: {dirs['label']}"
                             f"; cameras: {timing['full']['cameras']}")
    load1 = os.getloadavg()
    notes.insert(0, f"lambda_N = {lam_n:g} in every row except those with L_an on texture references "
                 f"(`collision`, the pipeline's loss): {lam_n_an:g} there (config `fit/weights/normal`; "
                 "studies/fit/fit_normal_weight.md)")
    write(rows, notes, args, command, load0, load1)


def verdicts(rows: list[dict]) -> list[str]:
    out = []
    groups = {}
    for r in rows:
        groups.setdefault((r["scene"], r["sequence"], r["views"], r["cues"]), {})[r["method"]] = r
    for (scene, seq, nv, cues), g in groups.items():
        if "full" not in g:
            continue
        f = g["full"]

        def beat(a, name, r):
            ok_r = a["vertex_rmse_m_mean"] < r["vertex_rmse_m_mean"]
            ok_j = a["accel_error_m"] < r["accel_error_m"]
            return (f"{name}: RMSE {'better' if ok_r else 'NOT better'} ({1e3 * a['vertex_rmse_m_mean']:.2f} vs "
                    f"{1e3 * r['vertex_rmse_m_mean']:.2f} mm), jitter {'better' if ok_j else 'NOT better'} "
                    f"({1e3 * a['accel_error_m']:.2f} vs {1e3 * r['accel_error_m']:.2f} mm)")

        beats = [beat(f, m, g[m]) for m in PAPER_ABLATIONS if m in g]
        if "anchor" in g:  # our variant against the full method (information, not a criterion)
            p = g["anchor"]
            beats.append(f"variant anchor (not a criterion): RMSE {1e3 * p['vertex_rmse_m_mean']:.2f} vs full "
                         f"{1e3 * f['vertex_rmse_m_mean']:.2f} mm ({p['rmse_over_floor']:.2f} x the floor), Chamfer "
                         f"{1e3 * p['chamfer_m_mean']:.2f} vs {1e3 * f['chamfer_m_mean']:.2f} mm, acceleration error "
                         f"{1e3 * p['accel_error_m']:.2f} vs {1e3 * f['accel_error_m']:.2f} mm, {p['fps']:.2f} vs "
                         f"{f['fps']:.2f} frames/s")
        if "anchor_smooth" in g and "anchor" in g:  # the temporal filter on top of L_an (information)
            p, q = g["anchor_smooth"], g["anchor"]
            beats.append(f"variant anchor_smooth (not a criterion): RMSE {1e3 * p['vertex_rmse_m_mean']:.2f} vs anchor "
                         f"{1e3 * q['vertex_rmse_m_mean']:.2f} mm, acceleration error {1e3 * p['accel_error_m']:.2f} vs "
                         f"{1e3 * q['accel_error_m']:.2f} mm (full {1e3 * f['accel_error_m']:.2f})")
        # each variant against the one it adds to (information): texture references vs first-seen ones,
        # L_col on top of texture references
        for name, ref in (("anchor_texture", "anchor_smooth"), ("collision", "anchor_texture")):
            if name in g and ref in g:
                p, q = g[name], g[ref]
                beats.append(f"variant {name} (not a criterion): RMSE {1e3 * p['vertex_rmse_m_mean']:.2f} mm = "
                             f"{p['rmse_over_floor']:.2f} x the floor ({ref} {1e3 * q['vertex_rmse_m_mean']:.2f} "
                             f"mm = {q['rmse_over_floor']:.2f} x), Chamfer {1e3 * p['chamfer_m_mean']:.2f} vs "
                             f"{1e3 * q['chamfer_m_mean']:.2f} mm, acceleration error {1e3 * p['accel_error_m']:.2f} vs "
                             f"{1e3 * q['accel_error_m']:.2f} mm, {p['fps']:.2f} vs {q['fps']:.2f} frames/s")
        if "sim" in g:  # the simulator alone (information, not a criterion)
            beats.append(beat(f, "simulation only (reference, not a criterion)", g["sim"]))
        if "photo" in g:  # our variant against the full method (information, not a criterion)
            p = g["photo"]
            beats.append(f"variant photo (not a criterion): RMSE {1e3 * p['vertex_rmse_m_mean']:.2f} vs full "
                         f"{1e3 * f['vertex_rmse_m_mean']:.2f} mm, Chamfer {1e3 * p['chamfer_m_mean']:.2f} vs "
                         f"{1e3 * f['chamfer_m_mean']:.2f} mm, acceleration error {1e3 * p['accel_error_m']:.2f} vs "
                         f"{1e3 * f['accel_error_m']:.2f} mm")
        ratio = f["rmse_over_floor"]
        line = (f"- **{scene}/{seq}, {nv} views ({cues} cues)**: full RMSE {1e3 * f['vertex_rmse_m_mean']:.2f} mm = "
                f"{ratio:.2f} x the rig floor {1e3 * f['rig_floor_rmse_m']:.2f} mm -> "
                f"{'MET' if ratio < 1.5 else 'NOT MET'} (< 1.5 x); {f['fps']:.2f} frames/s"
                f"{' -> MET' if f['fps'] >= 1 else ' -> NOT MET'} (>= 1 at 8 views)" if nv == 8 else
                f"- **{scene}/{seq}, {nv} views ({cues} cues)**: full RMSE {1e3 * f['vertex_rmse_m_mean']:.2f} mm = "
                f"{ratio:.2f} x the rig floor {1e3 * f['rig_floor_rmse_m']:.2f} mm -> "
                f"{'MET' if ratio < 1.5 else 'NOT MET'} (< 1.5 x); {f['fps']:.2f} frames/s")
        out.append(line)
        out += [f"  - vs {b}" for b in beats]
    return out


def write(rows, notes, args, command, load0, load1) -> None:
    out = Path(args.out)
    cols = list(rows[0].keys()) if rows else []
    with open(out.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    mm = lambda x: f"{1e3 * x:.2f}"  # noqa: E731
    num = lambda x: f"{x:.2f}" if np.isfinite(x) else "--"  # noqa: E731
    lines = [
        "# Garment fitting benchmark (`anidress_core.fit`) against the synthetic ground truth",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{command}` (git {git_rev(CODE_PATHS)})",
        f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, torch "
        f"{torch.__version__} ({args.threads} threads), Python {platform.python_version()}; shared machine, load "
        f"average (1/5/15 min) at start {load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end "
        f"{load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f}",
        "- reference (measured in the same run): the rig floor = RMSE of `rig.fit_transforms` on the ground-truth "
        "garment meshes carried onto the template's vertices (the best the rig can express); every method is "
        "measured against the same ground truth, on the same frames and cues.",
        "- metrics per frame: vertex RMSE vs ground truth in template topology; Chamfer = symmetric mean nearest-"
        f"neighbour distance between {args.samples} area-uniform surface samples of each mesh; normal consistency "
        "= mean |cos| between nearest samples' face normals (1 best); jitter = mean |x[t+1] - 2x[t] + x[t-1]| "
        "(fit and ground truth); acceleration error = the same of (fit - ground truth), the jitter a fit adds; "
        "rig floor Chamfer = the Chamfer of the rig floor's meshes (the surface error the rig cannot avoid; unlike the "
        "vertex RMSE, the Chamfer does not count material sliding along the surface, which images cannot see at "
        "frame 0: studies/fit/fit_frame0.md). "
        "Columns give mean / 95th percentile / worst frame (normal consistency: mean / 5th percentile / worst).",
        "- fps = frames / wall time of the fitting loop (cue loading and body occluder rasterisation included, "
        "rig and camera loading excluded); CPU s/frame = process CPU time of that loop per frame (all threads; "
        "less sensitive to other jobs on the machine than the wall time).",
        "- methods: `full` = the paper's loss (the pipeline's config adds L_an and L_col: the `anchor*` and `collision` rows); (a), (b), (c) = the paper's ablations; `photo` "
        "= our variant, the full loss + multi-view photo-consistency L_ph (weight 1000), not part of the criteria; "
        "`anchor` = our variant, the full loss + the temporal chromaticity anchor L_an (weight 1e5), not part of the "
        "criteria; `anchor_smooth` = `anchor`, then one pass of the temporal filter (1, 2, 1) / 4 over the bone "
        "transforms (`fit.smooth_transforms`), not part of the criteria; `anchor_texture` = `anchor_smooth` with "
        "L_an's references taken from the garment's texture at the template's UVs (`fit.texture_anchor`) instead of "
        "from the first frame each vertex is seen, not part of the criteria; `collision` = `anchor_texture` + our "
        "body-collision term L_col (weight 1e6; the pipeline's configuration on both loose scenes), not part of the criteria; "
        "`sim` = no fit, the rig driven by its simulated poses of the sequence (the cloth simulator alone; no fps).",
        "",
        "| scene/seq | views | method | frames | vertex RMSE mm mean / p95 / worst (frame) | rig floor mm | RMSE / floor "
        "| Chamfer mm mean / p95 / worst | rig floor Chamfer mm | Chamfer / floor | normal consistency mean / p5 / "
        "worst | jitter mm (GT) | acceleration error mm | fps | CPU s/frame | iterations/frame |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']}/{r['sequence']} | {r['views']} | {LABEL.get(r['method'], r['method'])} | {r['frames']} | "
            f"{mm(r['vertex_rmse_m_mean'])} / {mm(r['vertex_rmse_m_p95'])} / {mm(r['vertex_rmse_m_worst'])} "
            f"({r['worst_frame']}) | {mm(r['rig_floor_rmse_m'])} | {r['rmse_over_floor']:.2f} | "
            f"{mm(r['chamfer_m_mean'])} / {mm(r['chamfer_m_p95'])} / {mm(r['chamfer_m_worst'])} | "
            f"{mm(r['rig_floor_chamfer_m'])} | {r['chamfer_over_floor']:.2f} | "
            f"{r['normal_consistency_mean']:.4f} / {r['normal_consistency_p5']:.4f} / {r['normal_consistency_worst']:.4f}"
            f" | {mm(r['jitter_m'])} ({mm(r['gt_jitter_m'])}) | {mm(r['accel_error_m'])} | {num(r['fps'])} | "
            f"{num(r['cpu_s_per_frame'])} | {r['iterations_mean']:.1f} |")
    lines += ["", "## Criteria", ""] + verdicts(rows) + ["", "## Notes", ""] + [f"- {n}" for n in notes]
    (out.with_suffix(".md")).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
