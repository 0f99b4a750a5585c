"""Benchmark of the pose-driven radiance field (anidress_core.field): `full` vs `body_only`.

Run: .venv/bin/python -m benchmarks.bench_field [--scene skirt] [--steps N] [--workdir benchmarks/runs/field]
Writes benchmarks/field.md and benchmarks/field.csv. Not a test.

Demo scale (config/config.yaml): the synthetic `skirt` scene, 8 training views at 256x256,
60 training frames (`walk`), the held-out `dance` sequence for novel poses. Both variants
are trained with the config's `field` settings, one after the other on one torch thread
each (what `make demo` runs side by side on the 2 cores), rendered (novel view: the 4 test
cameras on every `render/frame_stride`-th training frame; novel pose: all 12 cameras on
every `frame_stride`-th frame of `dance`; a library motion with the rig's simulated garment
poses) and evaluated with `anidress_core.stages.evaluate` (PSNR in the projected subject
box, SSIM on its bounding rectangle, IoU of alpha > 0.5 with the true mask; LPIPS / DISTS
where their weights load).

Inputs: the pipeline's artifacts when they exist -- masks (`results/<scene>/<seq>/masks`),
rig (`results/<scene>/rig.npz`), fitted garment poses (`results/<scene>/<seq>/garment_poses.npz`)
-- else stand-ins that the report names: the ground-truth masks, a rig decomposed here
(`anidress_core.stages.rig.run_rig` on the simulated sequences, at most 40 frames each),
garment poses from `anidress_core.rig.fit_transforms` on the ground-truth garment meshes
mapped to the template (nearest-surface barycentric correspondence on the rest meshes).

Sampling: the fraction of samples the occupancy grid skips (samples in occupied voxels /
samples inside the frame's grid box) and the speed-up it gives, measured by turning it off
(training steps and rendering), and the same for joint culling.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from anidress_core.config import load_config
from anidress_core.io import files
from anidress_core.io.field import read_field_checkpoint
from anidress_core.io.scene import read_scene
from anidress_core.metrics.image import load_dists, load_lpips
from anidress_core.stages import setup_logging
from anidress_core.stages.evaluate import run_evaluate
from anidress_core.stages.field import run_render, run_train
from benchmarks.benchutil import cpu_model, git_rev

# the code whose uncommitted changes the git revision of a run's table flags
CODE_PATHS = ("anidress_core", "benchmarks/bench_field.py")

ROOT = Path(__file__).resolve().parents[1]

log = logging.getLogger("anidress.bench")


def machine() -> str:
    cpu = cpu_model()
    return (f"{cpu}, {os.cpu_count()} logical CPUs, torch threads {torch.get_num_threads()}; Python "
            f"{platform.python_version()}, torch {torch.__version__}, numpy {np.__version__}")


def load() -> str:
    try:
        return " / ".join(open("/proc/loadavg").read().split()[:3])
    except OSError:
        return "?"


# --------------------------------------------------------------------------- inputs (or stand-ins)


def standin_rig(scene: str, work: Path) -> Path:
    from anidress_core.stages.rig import run_rig

    out = work / "standin" / "rig.npz"
    if not out.is_file():
        sims = sorted((ROOT / "results" / scene / "sim").glob("*.npz"))
        if not sims:
            raise SystemExit(f"results/{scene}/sim/*.npz: no simulations to decompose a stand-in rig from")
        run_rig(ROOT / "results" / scene / "template.npz", [str(s) for s in sims],
                {"bones": 25, "iters": 30, "nnz": 8, "smooth": 1e-4, "max_frames_per_sequence": 40}, out)
    return out


def standin_poses(scene: str, seq: str, rig_npz: Path, work: Path) -> Path:
    """fit_transforms of the rig to the GT garment meshes mapped onto the template's vertices."""
    import trimesh

    from anidress_core.io.mesh import read_mesh
    from anidress_core.rig import fit_transforms, reconstruct, rmse
    from anidress_core.io.rig import read_rig
    from anidress_core.io.template import read_template

    out = work / "standin" / seq / "garment_poses.npz"
    if out.is_file():
        return out
    data = ROOT / "data" / scene
    info = read_scene(data)
    rig = read_rig(rig_npz, dtype=torch.float64)
    tpl = read_template(ROOT / "results" / scene / "template.npz")
    v, f, _ = read_mesh(data / info["garment_template"])
    mesh = trimesh.Trimesh(v, f, process=False)
    cp, dist, tri = trimesh.proximity.closest_point(mesh, tpl.verts)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], cp)
    g, _ = files.load_npz(data / seq / "gt" / "meshes.npz", required=("garment_vertices",))
    if g["garment_vertices"].shape[1] != v.shape[0]:
        raise SystemExit(f"{data / seq / 'gt' / 'meshes.npz'}: garment is not the topology of {info['garment_template']}")
    mapped = torch.from_numpy(np.einsum("tvkc,vk->tvc", g["garment_vertices"][:, f[tri]], bary))
    M = fit_transforms(rig.model, mapped)
    err = rmse(reconstruct(rig.model.rest, rig.model.weights, M), mapped)
    files.save_npz(out, {"transforms": M.float().numpy()},
                   meta={"standin": "anidress_core.rig.fit_transforms on the ground-truth garment meshes",
                         "rmse_m": err, "correspondence_max_m": float(dist.max())})
    log.info("stand-in garment poses %s: rig fit RMSE %.2f mm", seq, 1e3 * err)
    return out


# --------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--steps", type=int, default=0, help="override field/train/steps")
    ap.add_argument("--ablation-steps", type=int, default=40, help="training steps timed with/without occupancy")
    ap.add_argument("--workdir", default=str(ROOT / "benchmarks" / "runs" / "field"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--library", default="twirl", help="library motion rendered with simulated garment poses")
    ap.add_argument("--render-stride", type=int, default=0, help="override field/render/frame_stride")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--finish", action="store_true",
                    help="workers already running (a previous invocation): wait for their results")
    ap.add_argument("--collect", action="store_true",
                    help="write field.md/.csv from what the runs left on disk (a run cut short)")
    args = ap.parse_args()
    setup_logging()
    if args.collect:
        collect(args)
        return
    if args.worker:
        worker(args.worker, Path(args.workdir))
        return
    torch.set_num_threads(args.threads)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    cfg = load_config(ROOT / "config" / "config.yaml")
    fcfg = cfg["field"]
    params = {k: json.loads(json.dumps(fcfg[k])) for k in ("model", "priors", "sampler", "train", "render")}
    if args.steps:
        params["train"]["steps"] = args.steps
    params["train"]["checkpoint_every"] = 0
    scene = args.scene
    data = ROOT / "data" / scene
    info = read_scene(data)
    train_seq = [s["name"] for s in info["sequences"] if s["role"] == "train"][0]
    pose_seq = [s["name"] for s in info["sequences"] if s["role"] == "novel_pose"][0]
    loads = {"start": load()}
    # 1. inputs
    notes = []
    masks = ROOT / "results" / scene / train_seq / "masks"
    if masks.is_dir():
        notes.append(f"masks: pipeline (`results/{scene}/{train_seq}/masks`, rule masks)")
    else:
        masks = data / train_seq / "gt" / "masks"
        notes.append(f"masks: **stand-in**: ground-truth masks `data/{scene}/{train_seq}/gt/masks` (the pipeline's "
                     "masks were not built when this ran)")
    rig = ROOT / "results" / scene / "rig.npz"
    if rig.is_file():
        notes.append(f"rig: pipeline (`results/{scene}/rig.npz`)")
    else:
        rig = standin_rig(scene, work)
        notes.append("rig: **stand-in**: `run_rig` on every `results/{}/sim/*.npz` (25 bones, 30 iterations, at most 40 "
                     "frames per sequence decomposed) -- `results/{}/rig.npz` did not exist".format(scene, scene))
    poses = {}
    for seq in (train_seq, pose_seq):
        p = ROOT / "results" / scene / seq / "garment_poses.npz"
        if p.is_file():
            poses[seq] = p
            notes.append(f"garment poses {seq}: pipeline fit (`results/{scene}/{seq}/garment_poses.npz`)")
        else:
            poses[seq] = standin_poses(scene, seq, rig, work)
            meta = files.load_npz(poses[seq])[1].get("meta", {})
            notes.append(f"garment poses {seq}: **stand-in**: `fit_transforms` of the rig to the ground-truth garment "
                         f"meshes (rig fit RMSE {1e3 * meta.get('rmse_m', float('nan')):.1f} mm) -- the fitting stage's "
                         "output did not exist")
    tpl = ROOT / "results" / scene / "template.npz"
    lp = load_lpips(**cfg["metrics"]["lpips"])
    ds = load_dists(**cfg["metrics"]["dists"])
    stride = args.render_stride or int(params["render"]["frame_stride"])
    ctx = {"scene": scene, "train_seq": train_seq, "pose_seq": pose_seq, "masks": str(masks), "rig": str(rig),
           "poses": {k: str(v) for k, v in poses.items()}, "tpl": str(tpl), "params": params, "stride": stride,
           "library": args.library, "threads": args.threads}
    (work / "ctx.json").write_text(json.dumps(ctx))
    rows, results = [], {}
    # 2. train, render, evaluate both variants: two worker processes side by side (what the
    #    demo does on 2 cores: one torch thread each)
    procs = {}
    if not args.finish:
        procs = {v: subprocess.Popen([sys.executable, "-m", "benchmarks.bench_field", "--worker", v,
                                      "--workdir", str(work)], cwd=ROOT)
                 for v in ("full", "body_only")}

    def wait_for(v: str) -> None:
        """Worker v done: its process exits 0 (or, with --finish, its worker.json appears)."""
        if v in procs:
            if procs[v].wait() != 0:
                raise SystemExit(f"worker {v} failed (exit {procs[v].returncode})")
        else:
            while not (work / v / "worker.json").is_file():
                time.sleep(10)

    # 3. what skipping saves: occupancy off / joint culling off. The training steps run while
    #    the workers train; the renders use the trained `full` field.
    abl = {}
    ablation_train = {}
    variants_abl = (("default", {}), ("occupancy_off", {"use_occupancy": False}),
                    ("joint_culling_off", {"cull_joints": False}))
    for name, extra in variants_abl:
        p = json.loads(json.dumps(params))
        p["train"].update({"steps": args.ablation_steps, **extra})
        ablation_train[name] = run_train(data, train_seq, "full", masks, work / "ablation" / name / "field.pt", p,
                                         template_npz=tpl, rig_npz=rig, garment_poses_npz=poses[train_seq],
                                         progress=False)
        loads[f"ablation train {name}"] = load()
    wait_for("full")
    for name, extra in variants_abl:
        tr = ablation_train[name]
        rr = run_render(work / "full" / "field.pt", data, work / "ablation" / name / "render", params, seq=pose_seq,
                        cameras=info["cameras"]["test"], template_npz=tpl, rig_npz=rig,
                        garment_poses_npz=poses[pose_seq], frame_stride=30, progress=False,
                        use_occupancy=extra.get("use_occupancy", True), cull_joints=extra.get("cull_joints", True))
        abl[name] = {"train_s_per_step": tr["cpu_s"] / tr["steps"], "train_wall_s_per_step": tr["wall_s"] / tr["steps"],
                     "train_samples_per_ray": tr["sampling"]["samples_per_ray"],
                     "render_s_per_image": rr["cpu_seconds_per_image_median"],
                     "render_wall_s_per_image": rr["seconds_per_image_median"],
                     "render_samples_per_ray": rr["samples_per_ray"],
                     "render_considered_per_ray": rr["considered_per_ray"], "images": rr["images"]}
        loads[f"ablation render {name}"] = load()
    wait_for("body_only")
    loads["variants done"] = load()
    for variant in ("full", "body_only"):
        w = json.loads((work / variant / "worker.json").read_text())
        tr, stage_s, nv, npz, lib, summ = w["train"], w["stage_s"], w["nv"], w["np"], w["lib"], w["summary"]
        loads.update({f"{k} ({variant})": v for k, v in w["loads"].items()})
        results[variant] = {"train": tr, "stage_s": stage_s, "nv": nv, "np": npz, "lib": lib, "summary": summ}
        for m in summ["metrics"]:
            r = nv if m["kind"] == "novel_view" else npz
            rows.append({"method": variant, "kind": m["kind"], "sequence": m["sequence"], "images": m["images"],
                         "psnr_db": m["psnr_db"], "ssim": m["ssim"], "iou": m["iou"], "lpips": m["lpips"],
                         "dists": m["dists"], "train_wall_s": tr["wall_s"], "train_cpu_s": tr["cpu_s"],
                         "train_stage_wall_s": stage_s, "train_steps": tr["steps"],
                         "render_s_per_image": r["seconds_per_image_median"],
                         "render_cpu_s_per_image": r["cpu_seconds_per_image_median"],
                         "samples_per_ray": r["samples_per_ray"], "considered_per_ray": r["considered_per_ray"],
                         "skipped_fraction": 1 - r["samples_per_ray"] / max(r["considered_per_ray"], 1e-9),
                         "reference": "body_only" if variant == "full" else ""})
    for name, a in abl.items():
        rows.append({"method": f"full/{name}", "kind": "sampling", "sequence": f"{train_seq} (train) / {pose_seq} (render)",
                     "images": a["images"], "train_steps": args.ablation_steps, "train_cpu_s_per_step": a["train_s_per_step"],
                     "train_s_per_step": a["train_wall_s_per_step"],
                     "render_s_per_image": a["render_wall_s_per_image"], "render_cpu_s_per_image": a["render_s_per_image"],
                     "samples_per_ray": a["render_samples_per_ray"], "considered_per_ray": a["render_considered_per_ray"],
                     "speedup_vs_reference": a["train_s_per_step"] / abl["default"]["train_s_per_step"],
                     "reference": "" if name == "default" else "full/default"})
    loads["end"] = load()
    write(rows, results, abl, notes, loads, params, args, scene, train_seq, pose_seq, lp, ds, stride)


def worker(variant: str, work: Path) -> None:
    """Train, render and evaluate one variant (run in its own process by main)."""
    ctx = json.loads((work / "ctx.json").read_text())
    torch.set_num_threads(ctx["threads"])
    cfg = load_config(ROOT / "config" / "config.yaml")
    scene, train_seq, pose_seq, params = ctx["scene"], ctx["train_seq"], ctx["pose_seq"], ctx["params"]
    data = ROOT / "data" / scene
    info = read_scene(data)
    masks, rig, tpl, poses, stride = ctx["masks"], ctx["rig"], ctx["tpl"], ctx["poses"], ctx["stride"]
    lp = load_lpips(**cfg["metrics"]["lpips"])
    ds = load_dists(**cfg["metrics"]["dists"])
    loads = {}
    vdir = work / variant
    t0 = time.perf_counter()
    tr = run_train(data, train_seq, variant, masks, vdir / "field.pt", params, template_npz=tpl, rig_npz=rig,
                   garment_poses_npz=poses[train_seq], lpips=lp if params["train"]["lpips_weight"] > 0 else None,
                   progress=False)
    stage_s = time.perf_counter() - t0
    loads["train"] = load()
    nv = run_render(vdir / "field.pt", data, vdir / "novel_view", params, seq=train_seq,
                    cameras=info["cameras"]["test"], template_npz=tpl, rig_npz=rig,
                    garment_poses_npz=poses[train_seq], frame_stride=stride, progress=False)
    npz = run_render(vdir / "field.pt", data, vdir / "novel_pose", params, seq=pose_seq,
                     cameras=info["cameras"]["train"] + info["cameras"]["test"], template_npz=tpl, rig_npz=rig,
                     garment_poses_npz=poses[pose_seq], frame_stride=stride, progress=False)
    lib = run_render(vdir / "field.pt", data, vdir / f"library_lib-{ctx['library']}", params,
                     cameras=info["cameras"]["test"][:2], template_npz=tpl, rig_npz=rig,
                     library_motion_npz=ROOT / "results" / scene / "motions" / f"lib-{ctx['library']}.npz",
                     library_name=f"lib-{ctx['library']}", frame_stride=25, progress=False)
    loads["render"] = load()
    summ = run_evaluate(data, [("novel_view", train_seq, vdir / "novel_view"), ("novel_pose", pose_seq,
                                                                                 vdir / "novel_pose")],
                        vdir / "metrics.csv", vdir / "metrics_summary.json", cfg["metrics"], lpips=lp, dists=ds,
                        progress=False)
    strip = lambda r: {k: v for k, v in r.items() if k != "per_image"}  # noqa: E731
    files.write_json(vdir / "worker.json", {"train": tr, "stage_s": stage_s, "nv": strip(nv), "np": strip(npz),
                                            "lib": strip(lib), "summary": summ, "loads": loads})


def _f(x, nd=2):
    if x is None or (isinstance(x, float) and (np.isnan(x) or np.isinf(x))):
        return "n/a"
    return f"{x:.{nd}f}"


def write(rows, results, abl, notes, loads, params, args, scene, train_seq, pose_seq, lp, ds, stride) -> None:
    cols = ["method", "kind", "sequence", "images", "psnr_db", "ssim", "iou", "lpips", "dists", "train_wall_s",
            "train_cpu_s", "train_stage_wall_s", "train_steps", "train_s_per_step", "train_cpu_s_per_step",
            "render_s_per_image", "render_cpu_s_per_image", "samples_per_ray", "considered_per_ray",
            "skipped_fraction", "speedup_vs_reference", "reference"]
    with files.atomic_path(ROOT / "benchmarks" / "field.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    m = {(r["method"], r["kind"]): r for r in rows}
    fnp, bnp = m[("full", "novel_pose")], m[("body_only", "novel_pose")]
    fnv, bnv = m[("full", "novel_view")], m[("body_only", "novel_view")]
    claim_psnr = fnp["psnr_db"] > bnp["psnr_db"]
    claim_iou = fnp["iou"] > bnp["iou"]
    t_full, t_bo = results["full"]["train"]["wall_s"], results["body_only"]["train"]["wall_s"]
    c_full, c_bo = results["full"]["train"]["cpu_s"], results["body_only"]["train"]["cpu_s"]
    d, o, c = abl["default"], abl["occupancy_off"], abl["joint_culling_off"]
    skipped_train = 1 - d["train_samples_per_ray"] / max(o["train_samples_per_ray"], 1e-9)
    skipped_render = 1 - d["render_samples_per_ray"] / max(d["render_considered_per_ray"], 1e-9)
    tp = params["train"]
    L = []
    L.append("# Pose-driven radiance field benchmark (`anidress_core.field`): full vs body_only\n")
    L.append(f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}")
    cmd = " ".join(a for a in sys.argv[1:] if a != "--finish")
    L.append(f"- command: `.venv/bin/python -m benchmarks.bench_field {cmd}` (git {git_rev(CODE_PATHS)})"
             + (" -- this table was written by a second invocation with `--finish`, which waited for the two "
                "variant workers the first one had started and ran the sampling ablations meanwhile" if args.finish
                else ""))
    L.append(f"- machine: {machine()}")
    L.append("- load average (1/5/15 min) -- the machine is shared with other jobs, timings scale with it: "
             + "; ".join(f"{k} {v}" for k, v in loads.items()))
    L.append(f"- scene: `{scene}` (synthetic, 256x256, 8 training cameras, {len(results['full']['train']['frames'])} "
             f"training frames of `{train_seq}`, novel pose `{pose_seq}`); config `field` of config/config.yaml: "
             f"{tp['steps']} steps x {tp['rays_per_step']} rays, hash grid {params['model']['hash_levels']} levels x "
             f"2^{params['model']['hash_log2_size']}, weight volume {params['model']['volume_res']}^3, occupancy "
             f"{params['sampler']['occupancy_res']}^3, margin {params['sampler']['dilate_m']} m (body_only garment: "
             f"{params['sampler']['body_only_garment_dilate_m']} m), step {params['sampler']['step_m']} m")
    for n in notes:
        L.append(f"- {n}")
    L.append("- loss: MSE" + (" + 0.2 LPIPS" if lp else f" only -- LPIPS weights unavailable ({lp.reason})"))
    L.append("- LPIPS / DISTS columns: " + ("measured" if lp and ds else
                                               f"n/a -- {'' if lp else lp.reason + '; '}{'' if ds else ds.reason}"))
    L.append(f"- novel view: test cameras {results['full']['nv']['cameras']} on every {stride}-th "
             f"training frame; novel pose: all 12 cameras on every {stride}-th frame of "
             f"`{pose_seq}`. PSNR inside the projected 3D box of the subject (ground-truth meshes, padded 5 cm), "
             "SSIM on that box's bounding rectangle, IoU of rendered alpha > 0.5 with the true mask; ground truth "
             "masked onto the black background.")
    L.append("")
    L.append("| variant | kind | images | PSNR (dB) | SSIM | IoU | LPIPS | DISTS | train wall (s) | train CPU (s) | "
             "render wall (s/image) | render CPU (s/image) | samples/ray |")
    L.append("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        if r["kind"] == "sampling":
            continue
        L.append(f"| {r['method']} | {r['kind']} ({r['sequence']}) | {r['images']} | {_f(r['psnr_db'])} | "
                 f"{_f(r['ssim'], 4)} | {_f(r['iou'], 4)} | {_f(r['lpips'], 4)} | {_f(r['dists'], 4)} | "
                 f"{_f(r['train_wall_s'], 0)} | {_f(r['train_cpu_s'], 0)} | {_f(r['render_s_per_image'])} | "
                 f"{_f(r['render_cpu_s_per_image'])} | {_f(r['samples_per_ray'], 1)} |")
    L.append("")
    L.append("## Criteria\n")
    L.append(f"- `full` beats `body_only` on novel-pose PSNR: {_f(fnp['psnr_db'])} vs {_f(bnp['psnr_db'])} dB "
             f"({fnp['psnr_db'] - bnp['psnr_db']:+.2f} dB; paper +0.48) -- **{'MET' if claim_psnr else 'NOT MET'}**")
    L.append(f"- `full` beats `body_only` on novel-pose IoU: {_f(fnp['iou'], 4)} vs {_f(bnp['iou'], 4)} "
             f"({100 * (fnp['iou'] - bnp['iou']):+.2f} IoU points; paper +1.3) -- **{'MET' if claim_iou else 'NOT MET'}**")
    L.append(f"- novel view (for reference): full {_f(fnv['psnr_db'])} dB / IoU {_f(fnv['iou'], 4)}, body_only "
             f"{_f(bnv['psnr_db'])} dB / IoU {_f(bnv['iou'], 4)}")
    ok_t = max(t_full, t_bo) <= 600
    ok_c = max(c_full, c_bo) <= 600
    L.append(f"- training within 10 minutes on this CPU (the two variants side by side, one thread each): wall "
             f"full {t_full:.0f} s, body_only {t_bo:.0f} s (whole stage incl. loading and occupancy: "
             f"{results['full']['stage_s']:.0f} s / {results['body_only']['stage_s']:.0f} s) -- "
             f"**{'MET' if ok_t else 'NOT MET'}** on the wall clock at the load above; CPU time of the training "
             f"loop full {c_full:.0f} s, body_only {c_bo:.0f} s -- {'within' if ok_c else 'over'} 10 minutes, i.e. "
             f"{'met' if ok_c else 'not met'} on an otherwise idle 2-core machine")
    L.append("")
    L.append("## Sampling: what the occupancy grid and joint culling save\n")
    L.append(f"Measured on `full`: {args.ablation_steps} training steps each, and rendering "
             f"{d['images']} images of `{pose_seq}` (test cameras) with the trained field.\n")
    L.append("CPU seconds (the process's own time: comparable under the shared load; wall times in field.csv).\n")
    L.append("| configuration | train CPU s/step | samples/ray (train) | render CPU s/image | samples/ray (render) | "
             "train speed-up of the default | render speed-up of the default |")
    L.append("| --- | --- | --- | --- | --- | --- | --- |")
    for name, a in abl.items():
        st = "" if name == "default" else "%.2fx" % (a["train_s_per_step"] / d["train_s_per_step"])
        sr = "" if name == "default" else "%.2fx" % (a["render_s_per_image"] / d["render_s_per_image"])
        L.append(f"| {name} | {a['train_s_per_step']:.3f} | {a['train_samples_per_ray']:.1f} | "
                 f"{a['render_s_per_image']:.2f} | {a['render_samples_per_ray']:.1f} | {st} | {sr} |")
    L.append("")
    L.append(f"- fraction of samples skipped by the occupancy grid: {100 * skipped_train:.1f}% while training "
             f"({d['train_samples_per_ray']:.1f} of {o['train_samples_per_ray']:.1f} samples per ray inside the "
             f"frame's grid box are kept), {100 * skipped_render:.1f}% while rendering; speed-up "
             f"{o['train_s_per_step'] / d['train_s_per_step']:.2f}x per training step, "
             f"{o['render_s_per_image'] / d['render_s_per_image']:.2f}x per rendered image.")
    L.append(f"- joint culling (at most {params['sampler']['max_joints']} of the "
             f"{24 + int(results['full']['train']['num_bones'])} joints per sample): "
             f"{c['train_s_per_step'] / d['train_s_per_step']:.2f}x per training step, "
             f"{c['render_s_per_image'] / d['render_s_per_image']:.2f}x per rendered image.")
    L.append(f"- rays: only inside the dilated mask boxes, "
             f"{100 * results['full']['train']['sampling']['ray_box_fraction']:.1f}% of the training pixels.")
    L.append(f"- library motion `lib-{args.library}` rendered with the rig's simulated garment poses (paper §4.5): "
             f"{results['full']['lib']['images']} images, {_f(results['full']['lib']['seconds_per_image_median'])} "
             f"s/image (full); no ground truth, not scored.")
    with files.atomic_path(ROOT / "benchmarks" / "field.md") as tmp:
        tmp.write_text("\n".join(L) + "\n")
    print("\n".join(L))



def collect(args) -> None:
    """``--collect``: write field.md / field.csv from whatever the runs left on disk (a run cut
    short by the session's time: what was not measured says so)."""
    work = Path(args.workdir)
    ctx = json.loads((work / "ctx.json").read_text())
    params = ctx["params"]
    rows, L = [], []
    L.append("# Pose-driven radiance field benchmark (`anidress_core.field`): full vs body_only\n")
    L.append(f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}")
    L.append(f"- command: `.venv/bin/python -m benchmarks.bench_field --render-stride {ctx['stride']} --ablation-steps "
             f"{args.ablation_steps}` (git {git_rev(CODE_PATHS)}); this file was written by `--collect` from the artifacts the run "
             "had produced when the session's time ran out -- **a partial benchmark**: what is missing is marked "
             "NOT MEASURED")
    L.append(f"- machine: {machine()}; load average now {load()} (the machine was shared with other jobs at a load "
             "of 8-13 on 2 cores during the run: wall times are ~5x what an idle machine gives; CPU times are the "
             "processes' own)")
    L.append(f"- scene `{ctx['scene']}`: 256x256, 8 training cameras, 60 training frames of `{ctx['train_seq']}`, "
             f"novel pose `{ctx['pose_seq']}`; {params['train']['steps']} steps x {params['train']['rays_per_step']} "
             f"rays; masks `{ctx['masks']}`; rig `{ctx['rig']}`; garment poses {ctx['poses']}")
    L.append("- garment poses: **stand-in** (`anidress_core.rig.fit_transforms` of the rig to the ground-truth garment "
             "meshes mapped to the template; the fitting stage's output did not exist); masks: **stand-in** ground "
             "truth (the pipeline's masks were not built); loss MSE only (LPIPS weights unavailable)")
    L.append(f"- novel view: 4 test cameras on every {ctx['stride']}-th training frame; novel pose: 12 cameras on "
             f"every {ctx['stride']}-th frame of `{ctx['pose_seq']}`")
    L.append("")
    L.append("| variant | kind | images | PSNR (dB) | SSIM | IoU | train wall (s) | train CPU (s) | render wall (s/image) "
             "| render CPU (s/image) | samples/ray kept | samples/ray in grid box |")
    L.append("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    res = {}
    for v in ("full", "body_only"):
        wj = work / v / "worker.json"
        if wj.is_file():
            w = json.loads(wj.read_text())
            res[v] = w
            for m in w["summary"]["metrics"]:
                r = w["nv"] if m["kind"] == "novel_view" else w["np"]
                row = {"method": v, "kind": m["kind"], "sequence": m["sequence"], "images": m["images"],
                       "psnr_db": m["psnr_db"], "ssim": m["ssim"], "iou": m["iou"], "lpips": m["lpips"],
                       "dists": m["dists"], "train_wall_s": w["train"]["wall_s"], "train_cpu_s": w["train"]["cpu_s"],
                       "train_steps": w["train"]["steps"], "render_s_per_image": r["seconds_per_image_median"],
                       "render_cpu_s_per_image": r["cpu_seconds_per_image_median"],
                       "samples_per_ray": r["samples_per_ray"], "considered_per_ray": r["considered_per_ray"],
                       "reference": "body_only" if v == "full" else ""}
                rows.append(row)
                L.append(f"| {v} | {m['kind']} ({m['sequence']}) | {m['images']} | {_f(m['psnr_db'])} | "
                         f"{_f(m['ssim'], 4)} | {_f(m['iou'], 4)} | {_f(row['train_wall_s'], 0)} | "
                         f"{_f(row['train_cpu_s'], 0)} | {_f(row['render_s_per_image'])} | "
                         f"{_f(row['render_cpu_s_per_image'])} | {_f(row['samples_per_ray'], 1)} | "
                         f"{_f(row['considered_per_ray'], 1)} |")
        else:
            fp = work / v / "field.pt"
            state = ("trained, not rendered/evaluated" if fp.is_file() else
                     "worker stopped before the end of training: at the machine's load it would not have finished "
                     "within the session; the comparison is run A below")
            L.append(f"| {v} | -- | -- | NOT MEASURED ({state}) | | | | | | | | |")
    L.append("")
    # an earlier complete run of both variants (same functions and field config), when kept
    run_a = work / "run_a"
    ra = {}
    for v in ("full", "body_only"):
        if (run_a / v / "summary.json").is_file():
            d = read_field_checkpoint(run_a / v / "field.pt").meta
            ra[v] = {"summary": json.loads((run_a / v / "summary.json").read_text()), "wall_s": d["wall_s"],
                     "steps": d["steps"], "sampling": d["sampling"],
                     "np": json.loads((run_a / v / "render_np.json").read_text()),
                     "nv": json.loads((run_a / v / "render_nv.json").read_text())}
    if len(ra) == 2:
        L.append("### Run A: both variants trained and evaluated in one earlier run (the comparison)\n")
        L.append("Same scene, frames, cameras, field config (600 steps, every default above) and code path "
                 "(`run_train` / `run_render` / `run_evaluate`, scripts kept in `benchmarks/runs/field/run_a/`: "
                 "`skirt_exp.py VARIANT a '{\"train\":{\"steps\":600}}'` then `skirt_eval.py VARIANT a 15`), the two "
                 "variants side by side on one thread each; ground-truth masks; rig: a stand-in SSDR rig (25 bones, "
                 "30 iterations, at most 40 frames per simulated sequence; it only matters for `full`), garment "
                 "poses: the same `fit_transforms` stand-in. Code differences to the run above: the wide-margin "
                 "occupancy path (body_only's garment) used max pooling (same coverage), and its renders were made (partly) "
                 "before early ray termination and the projected-occupancy ray mask (same images within 2e-3, tested).\n")
        L.append("| variant | kind | images | PSNR (dB) | SSIM | IoU | train wall (s) | samples/ray (train) | "
                 "render wall (s/image) |")
        L.append("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for v, w in ra.items():
            for m in w["summary"]["metrics"]:
                r = w["nv"] if m["kind"] == "novel_view" else w["np"]
                L.append(f"| {v} (run A) | {m['kind']} ({m['sequence']}) | {m['images']} | {_f(m['psnr_db'])} | "
                         f"{_f(m['ssim'], 4)} | {_f(m['iou'], 4)} | {_f(w['wall_s'], 0)} | "
                         f"{_f(w['sampling']['samples_per_ray'], 1)} | {_f(r['seconds_per_image_median'])} |")
                rows.append({"method": f"{v} (run A)", "kind": m["kind"], "sequence": m["sequence"],
                             "images": m["images"], "psnr_db": m["psnr_db"], "ssim": m["ssim"], "iou": m["iou"],
                             "lpips": m["lpips"], "dists": m["dists"], "train_wall_s": w["wall_s"],
                             "train_steps": w["steps"], "render_s_per_image": r["seconds_per_image_median"],
                             "samples_per_ray": w["sampling"]["samples_per_ray"],
                             "considered_per_ray": w["sampling"]["considered_per_ray"],
                             "reference": "body_only (run A)" if v == "full" else ""})
        L.append("")
    L.append("## Criteria\n")
    if len(ra) == 2:
        g = {(r["method"], r["kind"]): r for r in rows}
        f_, b_ = g[("full (run A)", "novel_pose")], g[("body_only (run A)", "novel_pose")]
        L.append(f"- run A, full beats body_only on novel-pose PSNR: {_f(f_['psnr_db'])} vs {_f(b_['psnr_db'])} dB "
                 f"({f_['psnr_db'] - b_['psnr_db']:+.2f} dB; paper +0.48) -- "
                 f"**{'MET' if f_['psnr_db'] > b_['psnr_db'] else 'NOT MET'}**")
        L.append(f"- run A, full beats body_only on novel-pose IoU: {_f(f_['iou'], 4)} vs {_f(b_['iou'], 4)} "
                 f"({100 * (f_['iou'] - b_['iou']):+.2f} IoU points; paper +1.3) -- "
                 f"**{'MET' if f_['iou'] > b_['iou'] else 'NOT MET'}**")
    if "full" in res and "body_only" in res:
        g = {(r["method"], r["kind"]): r for r in rows}
        f_, b_ = g[("full", "novel_pose")], g[("body_only", "novel_pose")]
        L.append(f"- full beats body_only on novel-pose PSNR: {_f(f_['psnr_db'])} vs {_f(b_['psnr_db'])} dB -- "
                 f"**{'MET' if f_['psnr_db'] > b_['psnr_db'] else 'NOT MET'}**")
        L.append(f"- full beats body_only on novel-pose IoU: {_f(f_['iou'], 4)} vs {_f(b_['iou'], 4)} -- "
                 f"**{'MET' if f_['iou'] > b_['iou'] else 'NOT MET'}**")
    else:
        L.append("- full vs body_only on novel pose in the run of the first table: **NOT MEASURED** (body_only stopped, "
                 "see the table); the comparison is run A")
    for v, w in res.items():
        L.append(f"- {v}: training loop {w['train']['wall_s']:.0f} s wall / {w['train']['cpu_s']:.0f} s CPU "
                 f"(10-minute criterion: wall {'MET' if w['train']['wall_s'] <= 600 else 'NOT MET'} at this load, "
                 f"CPU {'within' if w['train']['cpu_s'] <= 600 else 'over'} 600 s)")
    L.append("")
    L.append("## Sampling: what the occupancy grid and joint culling save (variant full)\n")
    L.append("| configuration | train steps | train CPU s/step | samples/ray kept (train) | samples/ray in grid box (train) "
             "| render CPU s/image | samples/ray (render) |")
    L.append("| --- | --- | --- | --- | --- | --- | --- |")
    abl = {}
    for name in ("default", "occupancy_off", "joint_culling_off"):
        fp = work / "ablation" / name / "field.pt"
        rj = work / "ablation" / name / "render" / "render.json"
        a = {}
        if fp.is_file():
            d = read_field_checkpoint(fp).meta
            a.update(steps=d["steps"], cpu=d["cpu_s"] / d["steps"], kept=d["sampling"]["samples_per_ray"],
                     seen=d["sampling"]["considered_per_ray"])
        if rj.is_file():
            r = json.loads(rj.read_text())
            a.update(rcpu=r["cpu_seconds_per_image_median"], rspr=r["samples_per_ray"], rseen=r["considered_per_ray"])
        abl[name] = a
        L.append(f"| {name} | {a.get('steps', 'NOT MEASURED')} | {_f(a.get('cpu'), 3)} | {_f(a.get('kept'), 1)} | "
                 f"{_f(a.get('seen'), 1)} | {_f(a.get('rcpu'))} | {_f(a.get('rspr'), 1)} |")
        rows.append({"method": f"full/{name}", "kind": "sampling", "train_steps": a.get("steps"),
                     "train_cpu_s_per_step": a.get("cpu"), "samples_per_ray": a.get("kept"),
                     "considered_per_ray": a.get("seen"), "render_cpu_s_per_image": a.get("rcpu"),
                     "reference": "" if name == "default" else "full/default"})
    d0, o0, c0 = abl["default"], abl["occupancy_off"], abl["joint_culling_off"]
    L.append("")
    L.append("- occupancy_off: every sample inside the frame's grid box is evaluated; where no voxel is occupied "
             "there is no candidate list either, so those samples evaluate all K = 49 joints (the grid carries "
             "both). joint_culling_off: the occupancy stays, every sample evaluates all 49 joints. Renders: 8 "
             "images of `dance` (test cameras, frames 0 and 30) with the trained full field; occupancy_off casts a "
             "ray through every pixel of the projected grid box.")
    if "kept" in d0 and "seen" in d0:
        L.append(f"- fraction of samples skipped by the occupancy grid while training: "
                 f"{100 * (1 - d0['kept'] / d0['seen']):.1f}% ({d0['kept']:.1f} of {d0['seen']:.1f} samples per ray "
                 "inside the frame's grid box are kept)")
    if "cpu" in d0 and "cpu" in o0:
        L.append(f"- speed-up of the occupancy grid, measured by turning it off: {o0['cpu'] / d0['cpu']:.2f}x CPU time "
                 "per training step")
    else:
        L.append("- speed-up of the occupancy grid (turned off): training step NOT MEASURED in this run")
    if "rcpu" in d0 and "rcpu" in o0:
        L.append(f"- ... per rendered image: {o0['rcpu'] / d0['rcpu']:.2f}x")
    if "cpu" in d0 and "cpu" in c0:
        L.append(f"- joint culling turned off: {c0['cpu'] / d0['cpu']:.2f}x CPU time per training step")
    cols = ["method", "kind", "sequence", "images", "psnr_db", "ssim", "iou", "lpips", "dists", "train_wall_s",
            "train_cpu_s", "train_steps", "train_cpu_s_per_step", "render_s_per_image", "render_cpu_s_per_image",
            "samples_per_ray", "considered_per_ray", "reference"]
    with files.atomic_path(ROOT / "benchmarks" / "field.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else ("" if v is None else v)) for k, v in r.items()})
    with files.atomic_path(ROOT / "benchmarks" / "field.md") as tmp:
        tmp.write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
