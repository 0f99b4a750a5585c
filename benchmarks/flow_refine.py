"""Lucas-Kanade refinement of the garment's flow (cues/flows/refine): error at the fit's flow targets.

For each sequence the flows stage is run (into benchmarks/runs/flow_refine/) with the
pipeline's estimator and prior and ``refine: none``, then with ``refine: lk`` at several
window sizes. Each flow is measured where the fit uses it: at the projections of the
*ground-truth* garment vertices of frame t-1 that pass the fit's own target test
(:func:`anidress_core.fit.flow_targets`: visible, inside the eroded garment mask of the
pipeline), against the projections of the same vertices at frame t. Reported: mean
end-point error (px), and the error along the motion as a fraction of the motion
(sum of e . m / |m| over sum of |m|; negative = the motion is under-estimated), over all
targets and over the hem (targets on template vertices in the lowest quarter of the
garment's rest height, where the skirt swings most). Timing: the estimator and the
refinement per camera pair (the stage's own counters).

    .venv/bin/python benchmarks/flow_refine.py --seqs skirt:walk,skirt:dance,dress:sway --frames 30
"""
from __future__ import annotations

import argparse
import copy
import datetime
import os
import platform
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from anidress_core import fit as FIT  # noqa: E402
from anidress_core import raster  # noqa: E402
from anidress_core.config import load_config  # noqa: E402
from anidress_core.stages import cues as SC  # noqa: E402
from anidress_core.stages.fit import CueReader  # noqa: E402
from benchutil import cpu_model, fit_scene, git_rev  # noqa: E402


def target_errors(sc, masks: str, flows: str, T: int, hem: torch.Tensor) -> dict:
    """Flow error at the fit's targets of the ground-truth vertices, frames 1..T-1."""
    views, rig = sc.views, sc.rig
    K, E = views.K.double(), views.world_to_cam.double()
    reader = CueReader(sc.cams, masks, None, flows, sc.posed.vertices.double(), sc.body.faces, views,
                       torch.device("cpu"), num_frames=T)
    e_all, m_all, hem_all = [], [], []
    try:
        for t in range(1, T):
            prev = reader.cues(t - 1)
            flow, valid = reader.flow(t)
            occ = FIT.occluder_depth(sc.posed.vertices[t - 1].double(), sc.body.faces, views)
            Y0, Y1 = sc.Y[t - 1].double(), sc.Y[t].double()
            fr = raster.occlude(raster.rasterize(Y0, rig.faces, K, E, views.height, views.width, with_bary=False), occ)
            tg = FIT.flow_targets(Y0, views, fr, flow, valid, prev.mask, 0.005, 1)
            uv0, _ = raster.project_vertices(Y0, K, E)
            uv1, _ = raster.project_vertices(Y1, K, E)
            true = uv1[tg.cam, tg.vert]
            e_all.append(tg.target - true)
            m_all.append(true - uv0[tg.cam, tg.vert])
            hem_all.append(hem[tg.vert])
    finally:
        reader.close()
    e, m, h = torch.cat(e_all), torch.cat(m_all), torch.cat(hem_all)
    mn = m.norm(dim=-1)

    def summ(sel):
        along = (e[sel] * m[sel]).sum(-1) / mn[sel].clamp_min(1e-9)
        return {"targets": int(sel.sum()), "epe": float(e[sel].norm(dim=-1).mean()),
                "motion": float(mn[sel].mean()), "along": float(along.sum() / mn[sel].sum())}

    return {"all": summ(torch.ones_like(h)), "hem": summ(h)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seqs", default="skirt:walk,skirt:dance,dress:sway", help="scene:sequence pairs")
    ap.add_argument("--frames", type=int, default=30, help="frames measured (the flows stage runs on all)")
    ap.add_argument("--windows", default="5,7,9,15", help="LK window sizes")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/flow_refine")
    args = ap.parse_args()
    os.chdir(REPO)
    torch.set_num_threads(args.threads)
    base = copy.deepcopy(load_config("config/config.yaml")["cues"]["flows"])
    variants = [("none", dict(base, refine="none"))] + [
        (f"lk{w}", dict(base, refine="lk", refine_window=int(w))) for w in args.windows.split(",")]
    rows = []
    for pair in args.seqs.split(","):
        scene, seq = pair.split(":")
        masks = f"results/{scene}/{seq}/masks"
        if not Path(masks).is_dir():
            raise SystemExit(f"{masks}: the pipeline's masks are missing; run `snakemake --cores 2 {masks}` first")
        sc = fit_scene(scene, seq, args.views, f"results/{scene}/rig.npz", args.frames)
        rest = sc.rig.rest
        hem = rest[:, 2] <= torch.quantile(rest[:, 2], 0.25)  # up axis z (DESIGN.md)
        for name, cfg in variants:
            out = Path(f"benchmarks/runs/flow_refine/{scene}/{seq}/{name}")
            stats = SC.run_flows(f"data/{scene}", seq, masks, out, cfg, template_npz=f"results/{scene}/template.npz",
                                 threads=args.threads, progress=False)
            err = target_errors(sc, masks, str(out), args.frames, hem)
            rows.append({"scene": scene, "sequence": seq, "variant": name, **{
                f"{k}_{g}": v for g in ("all", "hem") for k, v in err[g].items()},
                "estimator_ms_per_pair": 1e3 * stats["compute_s_per_pair"],
                "refine_ms_per_pair": 1e3 * stats["refine_s_per_pair"],
                "refined_pixels_per_pair": stats["refined_pixels_per_pair"]})
            r = rows[-1]
            print(f"{scene}/{seq} {name}: EPE {r['epe_all']:.3f} px, along {100 * r['along_all']:+.1f} %, hem EPE "
                  f"{r['epe_hem']:.3f}, along {100 * r['along_hem']:+.1f} %", flush=True)
    write(rows, args, base)


def write(rows: list[dict], args, base: dict) -> None:
    import csv

    out = Path(args.out)
    with open(out.with_suffix(".csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [
        "# Lucas-Kanade refinement of the garment's flow: error at the fit's flow targets",
        "",
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `.venv/bin/python benchmarks/flow_refine.py {' '.join(sys.argv[1:])}` "
        f"(git {git_rev(('anidress_core/cues/flow.py', 'anidress_core/stages/cues.py'))})",
        f"- machine: {cpu_model() or platform.machine()}, {os.cpu_count()} logical CPUs, {args.threads} threads; "
        f"OpenCV single-threaded per camera, cameras in parallel (the flows stage)",
        f"- estimator: config.yaml `cues/flows` ({base['method']}, prior {base['prior']}); `none` = the estimator "
        "alone, `lkN` = then `cues.flow.refine_lk` with an N-pixel window at the garment's pixels of frame t-1",
        f"- measured at the fit's flow targets of the ground-truth garment of frames 0..{args.frames - 2} "
        f"({args.views} training views): EPE = mean end-point error (px); along = error along the motion / the "
        "motion (sum over targets; negative = under-estimated); hem = targets on template vertices in the lowest "
        "quarter of the garment's rest height; motion = mean |true displacement| (px).",
        "",
        "| scene/seq | variant | targets | motion px | EPE px | along % | hem targets | hem motion px | hem EPE px "
        "| hem along % | estimator ms/pair | refine ms/pair | pixels refined/pair |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']}/{r['sequence']} | {r['variant']} | {r['targets_all']} | {r['motion_all']:.2f} | "
            f"{r['epe_all']:.3f} | {100 * r['along_all']:+.1f} | {r['targets_hem']} | {r['motion_hem']:.2f} | "
            f"{r['epe_hem']:.3f} | {100 * r['along_hem']:+.1f} | {r['estimator_ms_per_pair']:.1f} | "
            f"{r['refine_ms_per_pair']:.1f} | {r['refined_pixels_per_pair']:.0f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
