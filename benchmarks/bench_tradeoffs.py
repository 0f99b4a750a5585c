"""Run time against error: sweeps of the knobs that trade one for the other (issue 8 §2).

Run: `snakemake --cores all bench`, `make bench`, or
     .venv/bin/python -m benchmarks.bench_tradeoffs [--scene skirt] [--only rig,fit,flow,field,resolution]
         [--fit-frames 30] [--quick]
Writes benchmarks/tradeoffs.csv (one row per run: stage, knob, value, wall_s, cpu_s, error,
error_metric, is_default, reference) and benchmarks/tradeoffs.md; the report draws the
Pareto plots and says whether the config's defaults sit on the front. Not a test.

Everything runs on the synthetic scene (default `skirt`, built by the pipeline: data/<scene>,
results/<scene>/{template,sim,...}) with the config's defaults except the one knob swept,
in this process, one after another, work files under benchmarks/runs/tradeoffs/:

* rig: bones B in {10, 15, 20, 25, 30} -> the rig's reconstruction RMSE on the simulations
  (stage rig) and the fitted garment's vertex RMSE against ground truth with that rig
  (stage fit, first ``--fit-frames`` frames of the training sequence);
* fit: training views {4, 8}; evaluations per frame t > 0 {3, 5, 10, 20} (config tolerance);
  -> vertex RMSE (mm) vs fitting time;
* flow: method {dis_ultrafast, dis_fast, dis_medium, farneback, deepflow} -> garment
  end-point error (px) vs time per image (tvl1, ~1.3 s per pair here, is in benchmarks/cues.md);
* resolution: the scene re-synthesised at half the image size (same seed, cameras, motion)
  with its own cues -> fitted vertex RMSE vs fitting time;
* field: training steps (``--field-steps``, default {150, 300, 600}) and ray-marching step
  {0.02, 0.01, 0.005} m -> novel-view PSNR (4 test cameras x 4 frames) vs training time.
"""
from __future__ import annotations

import argparse
import copy
import csv
import datetime
import os
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from anidress_core.config import load_config, scene_section
from anidress_core.io import files
from benchmarks.benchutil import cpu_model, git_rev

ROOT = Path(__file__).resolve().parents[1]

WORK = ROOT / "benchmarks" / "runs" / "tradeoffs"
#: (stage, knob) of the rows each sweep writes (for --merge)
SWEEP_KNOBS = {"rig": {("rig", "bones"), ("fit", "bones")}, "fit": {("fit", "views"), ("fit", "iterations/tolerance")},
               "flow": {("flow", "method"), ("flow", "refine")}, "resolution": {("fit", "resolution")},
               "field": {("field", "steps"), ("field", "ray step (m)")}}
FIELDS = ["stage", "knob", "value", "wall_s", "cpu_s", "error", "error_metric", "is_default", "reference", "notes"]


class Timer:
    def __enter__(self):
        self.w, self.c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *a):
        self.wall, self.cpu = time.perf_counter() - self.w, time.process_time() - self.c


def _row(rows, stage, knob, value, t, error, metric, default, notes=""):
    rows.append({"stage": stage, "knob": knob, "value": value, "wall_s": float(f"{t.wall:.4g}"),
                 "cpu_s": float(f"{t.cpu:.4g}"),
                 "error": error, "error_metric": metric, "is_default": int(bool(default)), "reference": "no",
                 "notes": notes})
    print(f"  {stage:6s} {knob}={value}: {t.wall:.1f} s wall, {metric} {error:.4g}", flush=True)


def _scene_paths(cfg, scene):
    data, res = ROOT / "data" / scene, ROOT / "results" / scene
    info = __import__("yaml").safe_load((data / "scene.yaml").read_text())
    train = [s["name"] for s in info["sequences"] if s["role"] == "train"][0]
    for p in (data, res / "template.npz", res / "rig.npz"):
        if not p.exists():
            raise SystemExit(f"{p}: missing; build the scene first (snakemake --cores all results/{scene}/rig.npz)")
    return data, res, train


def _cue_dirs(res, data, seq):
    """The pipeline's cues of ``seq`` (rules masks/flows/normals)."""
    m = data / seq / "masks" if (data / seq / "masks").is_dir() else res / seq / "masks"
    n = data / seq / "normals" if (data / seq / "normals").is_dir() else None
    return m, res / seq / "flows", n


_DEFAULT_FIT: dict = {}


def _fit_rmse(cfg, data, seq, rig, tpl, masks, flows, normals, fit_over: dict, out: Path) -> tuple[float, Timer]:
    """Fit the first frames with the config's fit settings updated by ``fit_over``; mean vertex RMSE (mm).

    The default setting (pipeline rig and cues, no override but the frame count) is run once
    and reused by every sweep that includes it."""
    from anidress_core.stages.fit import run_fit
    from anidress_core.stages.fit_eval import run_fit_eval

    key = (str(data), str(rig), str(masks), tuple(sorted(fit_over.items())))
    if key in _DEFAULT_FIT:
        return _DEFAULT_FIT[key]
    params = copy.deepcopy(cfg["fit"])
    params.update(fit_over)
    with Timer() as t:
        run_fit(data, seq, rig, tpl, masks, flows, normals, params, out / "garment_poses.npz", progress=False)
    summ = run_fit_eval(data, seq, rig, {"full": out / "garment_poses.npz"}, out / "fit_metrics.csv")
    rows = [r for r in csv.DictReader(open(out / "fit_metrics.csv"))]
    rmse = float(np.mean([float(r["vertex_rmse_m"]) for r in rows])) * 1e3
    del summ
    _DEFAULT_FIT[key] = (rmse, t)
    return rmse, t


def sweep_rig(cfg, scene, rows, args):
    from anidress_core.stages.rig import run_rig

    data, res, seq = _scene_paths(cfg, scene)
    masks, flows, normals = _cue_dirs(res, data, seq)
    sims = sorted((res / "sim").glob("*.npz"))
    for B in (10, 15, 20, 25, 30):
        out = WORK / scene / f"rig_B{B}"
        out.mkdir(parents=True, exist_ok=True)
        p = dict(cfg["rig"], bones=B)
        default = B == cfg["rig"]["bones"]
        with Timer() as t:
            art = run_rig(res / "template.npz", sims, p, out / "rig.npz")
        _row(rows, "rig", "bones", B, t, 1e3 * art.model.rmse, "rig RMSE on the simulations (mm)", default)
        rig = res / "rig.npz" if default else out / "rig.npz"  # the default is the pipeline's own rig
        rm, tf = _fit_rmse(cfg, data, seq, rig, res / "template.npz", masks, flows, normals,
                           {"frames": args.fit_frames}, WORK / scene / ("fit_default" if default else f"fit_B{B}"))
        _row(rows, "fit", "bones", B, tf, rm, "fitted vertex RMSE (mm)", default)


def sweep_fit(cfg, scene, rows, args):
    data, res, seq = _scene_paths(cfg, scene)
    masks, flows, normals = _cue_dirs(res, data, seq)
    base = {"frames": args.fit_frames}
    for views in (4, 8):
        over = base if views == 8 and cfg["fit"]["views"] in (0, 8) else dict(base, views=views)
        rm, t = _fit_rmse(cfg, data, seq, res / "rig.npz", res / "template.npz", masks, flows, normals,
                          over, WORK / scene / ("fit_default" if over is base else f"fit_views{views}"))
        dv = cfg["fit"]["views"] in (0, views) and views == 8
        _row(rows, "fit", "views", views, t, rm, "fitted vertex RMSE (mm)", dv)
    tol0 = cfg["fit"]["rel_tol"]  # the evaluation cap per frame t > 0 is what trades time for error here
    for it, tol in ((3, tol0), (5, tol0), (10, tol0), (20, tol0)):
        dflt = it == cfg["fit"]["max_iters"] and tol == cfg["fit"]["rel_tol"]
        over = base if dflt else dict(base, max_iters=it, rel_tol=tol)
        rm, t = _fit_rmse(cfg, data, seq, res / "rig.npz", res / "template.npz", masks, flows, normals,
                          over, WORK / scene / ("fit_default" if dflt else f"fit_it{it}"))
        _row(rows, "fit", "iterations/tolerance", f"{it}/{tol:g}", t, rm, "fitted vertex RMSE (mm)",
             it == cfg["fit"]["max_iters"] and tol == cfg["fit"]["rel_tol"])


def sweep_flow(cfg, scene, rows, args):
    from anidress_core.stages.cues import evaluate_cues, run_flows

    data, res, seq = _scene_paths(cfg, scene)
    masks, _, _ = _cue_dirs(res, data, seq)
    default = cfg["cues"]["flows"]["method"]

    def run(name: str, flows_cfg: dict) -> tuple[Timer, float]:
        """The flows of ``flows_cfg`` into WORK/<scene>/<name>: time per image, garment EPE (px)."""
        out = WORK / scene / name
        if out.exists():
            shutil.rmtree(out)
        with Timer() as t:
            run_flows(data, seq, masks, out, flows_cfg, res / "template.npz", threads=1, progress=False)
        ev = evaluate_cues(data, seq, flows_dir=out)
        frames = max(1, int(ev.get("frames", 1)) - 1) * max(1, int(ev.get("cameras", 1)))
        t.wall, t.cpu = t.wall / frames, t.cpu / frames
        return t, float(ev["epe_garment_px"])

    for method in ("dis_ultrafast", "dis_fast", "dis_medium", "farneback", "deepflow"):
        t, epe = run(f"flow_{method}", dict(cfg["cues"]["flows"], method=method))
        _row(rows, "flow", "method", method, t, epe, "garment flow EPE (px); time per image", method == default)
    # the configured method with and without the Lucas-Kanade refinement of the garment's pixels
    refine = cfg["cues"]["flows"].get("refine", "none")
    for value in ("none", "lk"):
        if value == refine:  # that run is the default method's row above
            row = next(r for r in rows if r["stage"] == "flow" and r["knob"] == "method" and r["value"] == default)
            rows.append(dict(row, knob="refine", value=value))
            continue
        t, epe = run(f"flow_{default}_refine_{value}", dict(cfg["cues"]["flows"], refine=value))
        _row(rows, "flow", "refine", value, t, epe, "garment flow EPE (px); time per image", False)


def sweep_resolution(cfg, scene, rows, args):
    """Half-resolution copy of the scene (same everything else), its own cues, then the fit."""
    from anidress_core.config import scene_config
    from anidress_core.stages.cues import run_flows, run_masks
    from anidress_core.stages.synth import run_synth

    data, res, seq = _scene_paths(cfg, scene)
    masks, flows, normals = _cue_dirs(res, data, seq)
    rm, t = _fit_rmse(cfg, data, seq, res / "rig.npz", res / "template.npz", masks, flows, normals,
                      {"frames": args.fit_frames}, WORK / scene / "fit_default")
    H, W = cfg["scenes"][scene]["image_size"]
    _row(rows, "fit", "resolution", f"{H}x{W}", t, rm, "fitted vertex RMSE (mm)", True)
    sc = copy.deepcopy(scene_config(cfg, scene))
    sc["image_size"] = [H // 2, W // 2]
    # the whole sequence: a procedural motion depends on its length, and the fit starts from
    # the rig's poses of the full-resolution scene's simulated sequence
    sc["sequences"] = [s for s in sc["sequences"] if s["name"] == seq]
    half = WORK / f"{scene}_half" / "data"
    if (half / "scene.yaml").is_file():
        made = __import__("yaml").safe_load((half / "scene.yaml").read_text())
        if [s["frames"] for s in made["sequences"]] != [s["frames"] for s in sc["sequences"]]:
            shutil.rmtree(half.parent)
    if not (half / "scene.yaml").is_file():
        run_synth(sc, f"{scene}_half", half, threads=2, progress=False)
    hres = WORK / f"{scene}_half" / "results"
    if not (hres / "masks").is_dir():
        run_masks(half, seq, hres / "masks", cfg["cues"]["masks"], res / "template.npz", threads=2, progress=False)
        run_flows(half, seq, hres / "masks", hres / "flows", cfg["cues"]["flows"], res / "template.npz", threads=2,
                  progress=False)
    hn = half / seq / "normals" if (half / seq / "normals").is_dir() else None
    rm, t = _fit_rmse(cfg, half, seq, res / "rig.npz", res / "template.npz", hres / "masks", hres / "flows", hn,
                      {"frames": args.fit_frames}, WORK / scene / "fit_res_half")
    _row(rows, "fit", "resolution", f"{H // 2}x{W // 2}", t, rm, "fitted vertex RMSE (mm)", False)


def sweep_field(cfg, scene, rows, args):
    from anidress_core.stages.evaluate import run_evaluate
    from anidress_core.stages.field import run_render, run_train

    data, res, seq = _scene_paths(cfg, scene)
    masks, _, _ = _cue_dirs(res, data, seq)
    poses = res / seq / "garment_poses.npz"
    if not poses.is_file():
        raise SystemExit(f"{poses}: missing; run the fit first (snakemake --cores all {poses.relative_to(ROOT)})")
    info = __import__("yaml").safe_load((data / "scene.yaml").read_text())
    test = info["cameras"]["test"]
    base = cfg["field"]
    steps_default = base["train"]["steps"]
    step_default = base["sampler"]["step_m"]
    steps = (100, 300) if args.quick else tuple(int(x) for x in args.field_steps.split(","))
    runs = [("steps", s, {"train": {"steps": s}}) for s in steps]
    runs += [("ray step (m)", m, {"sampler": {"step_m": m}}) for m in (0.02, 0.005)]
    for knob, value, over in runs:
        p = copy.deepcopy(base)
        for k, v in over.items():
            p[k].update(v)
        out = WORK / scene / f"field_{knob.split()[0]}_{value}"
        out.mkdir(parents=True, exist_ok=True)
        with Timer() as t:
            run_train(data, seq, "full", masks, out / "field.pt", p, template_npz=res / "template.npz",
                      rig_npz=res / "rig.npz", garment_poses_npz=poses, progress=False)
        rdir = out / "renders" / "novel_view"
        if rdir.exists():
            shutil.rmtree(rdir)
        run_render(out / "field.pt", data, rdir, p, seq=seq, cameras=test, template_npz=res / "template.npz",
                   rig_npz=res / "rig.npz", garment_poses_npz=poses, frame_stride=15, progress=False)
        summ = run_evaluate(data, [("novel_view", seq, rdir)], out / "metrics.csv", out / "summary.json",
                            cfg["metrics"], progress=False)
        psnr = summ["metrics"][0]["psnr_db"]
        default = (knob == "steps" and value == steps_default) or (knob != "steps" and value == step_default)
        # PSNR: lower is worse, the front wants "lower is better": plot its negative
        _row(rows, "field", knob, value, t, -psnr, "minus novel-view PSNR (dB)", default)
    # the default itself (600 steps, 0.01 m) is the steps row with value = default


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--only", default="rig,fit,flow,resolution,field")
    ap.add_argument("--fit-frames", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="fewer field steps (a smoke run)")
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows of the sweeps not in --only from the existing benchmarks/tradeoffs.csv")
    ap.add_argument("--field-steps", default="150,300,600", help="training steps swept (comma list)")
    args = ap.parse_args()
    cfg = load_config(args.config)
    # the scene's own fit settings (scenes/<scene>/fit, e.g. the skirt's texture references for L_an),
    # as the workflow's rule fit reads them
    cfg = dict(cfg, fit=scene_section(cfg, "fit", args.scene))
    torch.set_num_threads(2)
    WORK.mkdir(parents=True, exist_ok=True)
    rows, started = [], datetime.datetime.now()
    loads = [os.getloadavg()[0]]
    sweeps = {"rig": sweep_rig, "fit": sweep_fit, "flow": sweep_flow, "resolution": sweep_resolution,
              "field": sweep_field}
    for name in args.only.split(","):
        print(f"== {name}", flush=True)
        sweeps[name](cfg, args.scene, rows, args)
        loads.append(os.getloadavg()[0])
    out = ROOT / "benchmarks" / "tradeoffs.csv"
    if args.merge and out.is_file():  # keep the other sweeps' rows of the last run
        with open(out) as fh:
            old = list(csv.DictReader(fh))
        rerun = {k for name in args.only.split(",") for k in SWEEP_KNOBS[name]}
        kept = [dict(r, wall_s=float(r["wall_s"]), cpu_s=float(r["cpu_s"]), error=float(r["error"]),
                     is_default=int(r["is_default"])) for r in old if (r["stage"], r["knob"]) not in rerun]
        rows = kept + rows
    with files.atomic_path(out) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=FIELDS)
            w.writeheader()
            w.writerows(rows)
    md = ROOT / "benchmarks" / "tradeoffs.md"
    prev_md = md.read_text().splitlines() if md.is_file() else []
    lines = ["# Run time against error (`benchmarks.bench_tradeoffs`)", "",
             f"- date: {started.isoformat(timespec='seconds')}",
             f"- command: `.venv/bin/python -m benchmarks.bench_tradeoffs --scene {args.scene} --only {args.only} "
             f"--fit-frames {args.fit_frames}{' --quick' if args.quick else ''}` (git {git_rev()})",
             f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs, torch "
             f"{torch.__version__}; load average (1 min) at the start and after each sweep: "
             + ", ".join(f"{x:.2f}" for x in loads),
             *(["- merged (--merge): the rows of the other sweeps come from the earlier run: "
                + "; ".join(l[2:] for l in prev_md if l.startswith(("- date:", "- command:", "- machine:")))]
               if args.merge and prev_md else []),
             "- each row: the config's defaults except the knob; `error` is lower-is-better (the field's row holds "
             "minus PSNR); the report (results/report.html) draws one Pareto plot per stage and error and says "
             "whether the default is on the front.", "",
             "| stage | knob | value | wall s | CPU s | error | metric | default |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['stage']} | {r['knob']} | {r['value']} | {r['wall_s']:.4g} | {r['cpu_s']:.4g} | "
                     f"{r['error']:.4g} | {r['error_metric']} | {'yes' if r['is_default'] else ''} |")
    from anidress_core.plots import pareto_front, scatter_chart

    lines += ["", "## Defaults and the Pareto front", "",
              "One chart per stage and error (CPU seconds, log scale, against the error; lower-left is "
              "better); the dashed line is the Pareto front, the config's defaults are outlined.", ""]
    written, per_stage = set(), {}
    for key in dict.fromkeys((r["stage"], r["error_metric"]) for r in rows):
        rs = [r for r in rows if (r["stage"], r["error_metric"]) == key]
        front = set(pareto_front([(r["cpu_s"], r["error"]) for r in rs]))
        for i, r in enumerate(rs):
            if r["is_default"]:
                beat = [f"{o['knob']}={o['value']} ({o['cpu_s']:.3g} CPU s, {o['error']:.4g})" for o in rs
                        if o["cpu_s"] <= r["cpu_s"] and o["error"] <= r["error"]
                        and (o["cpu_s"] < r["cpu_s"] or o["error"] < r["error"])]
                lines.append(f"- {key[0]} / {key[1]}: default {r['knob']}={r['value']} ({r['cpu_s']:.3g} CPU s, "
                             f"{r['error']:.4g}) is " + ("on the front" if i in front else
                                                        "NOT on the front: dominated by " + ", ".join(beat))
                             + f" of these {len(rs)} runs.")
        svg = scatter_chart([{"x": r["cpu_s"], "y": r["error"], "label": f"{r['knob']}={r['value']}",
                              "group": r["knob"], "highlight": bool(r["is_default"])} for r in rs],
                            f"{key[0]}: {key[1]}", "CPU s", key[1])
        k = per_stage[key[0]] = per_stage.get(key[0], -1) + 1  # a stable name: stage (and metric number)
        name = f"tradeoffs_{key[0]}{'' if k == 0 else f'_{k}'}.svg"
        (ROOT / "benchmarks" / name).write_text(svg)
        written.add(name)
        lines += ["", f"![{key[0]}: {key[1]} against CPU time]({name})", ""]
    for old in (ROOT / "benchmarks").glob("tradeoffs_*.svg"):  # charts of an earlier run's layout
        if old.name not in written:
            old.unlink()
    md.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
