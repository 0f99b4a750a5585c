"""Benchmark of the pose-driven radiance field: this code against the field of git 6aee398 (the reference of
issue 45), measured in one run on one machine. Not a test.

    .venv/bin/python -m benchmarks.bench_field demo          # the demo scenes, both codes
    .venv/bin/python -m benchmarks.bench_field profile       # a training step and an image, part by part
    .venv/bin/python -m benchmarks.bench_field convergence   # the tuning scenes: quality against the training budget
    .venv/bin/python -m benchmarks.bench_field suite         # the held-out scenes: figures and time to quality
    .venv/bin/python -m benchmarks.bench_field attribution   # what blurs the garment (tuning scenes)
    .venv/bin/python -m benchmarks.bench_field options       # the paper's warp and the pose refinement, held out
    .venv/bin/python -m benchmarks.bench_field bound         # exact garment inputs (rig floor, dense truth), held out
    .venv/bin/python -m benchmarks.bench_field write         # benchmarks/field.{md,csv} from the runs on disk
                                                             # (a section without one: kept as field.md has it)

Every field is trained, rendered and scored through the ``anidress`` command line (:mod:`benchmarks.field_runs`):
the reference from a git worktree of 6aee398 with that commit's config, this code with config/config.yaml;
both scored by this checkout's ``evaluate`` (PSNR in the subject's projected box, the paper's convention, and
pooled inside the ground-truth subject mask and its garment and body labels). Jobs run two at a time, one
torch thread each (as profiles/default runs the demo's). Inputs are the pipeline's own: masks, rig and
fitted garment poses under results/ (build them first: ``make demo`` for the demo scenes, the suite's
targets for the suite). Finished jobs are kept under benchmarks/runs/field/ and reused.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

import yaml

from benchmarks.benchutil import cpu_model, git_rev
from benchmarks.fit_suite import FIELD_SUITE, FIELD_TUNING
from benchmarks.field_runs import (REFERENCE, Job, code_dir, fit_anchor, load, noisy_bodies, rig_floor_poses,
                                   run_jobs, scene_sequences)

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "benchmarks" / "runs" / "field"
CODE_PATHS = ("anidress_core", "benchmarks/bench_field.py", "benchmarks/field_runs.py", "benchmarks/field_profile.py",
              "benchmarks/field_oracle.py", "config/config.yaml")
#: budgets of the held-out time-to-quality runs, as fractions of this code's field/train/steps
BUDGETS = (0.25, 0.5, 1.0)
#: budgets of the convergence curve on the tuning scenes
CURVE = (0.25, 0.5, 1.0, 2.0)
#: the heading of each section of field.md (write() puts it above the section's table)
TITLES = {"demo": "The demo scenes", "profile": "Where the time goes", "suite": "The held-out scenes of the field suite",
          "convergence": "Convergence on the tuning scenes (the budget was chosen here)",
          "attribution": "What blurs the garment: attribution on the tuning scenes",
          "options": "The paper's warp and the pose refinement on the held-out scenes",
          "bound": "The bound: exact garment inputs on the held-out scenes"}
#: the reference's figures that define "today's quality" (both kinds: novel view and novel pose)
QUALITY = ("psnr_subject_db", "psnr_garment_db")


def machine() -> dict:
    return {"cpu": cpu_model(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "date": datetime.datetime.now().isoformat(timespec="seconds"), "git": git_rev(CODE_PATHS)}


def config() -> dict:
    return yaml.safe_load((ROOT / "config" / "config.yaml").read_text())


def suite_scenes() -> tuple[list[str], list[str]]:
    """(tuning scenes, held-out scenes) of config/field_suite.yaml (benchmarks/fit_suite.py: FIELD_TUNING)."""
    names = yaml.safe_load(FIELD_SUITE.read_text())["run_scenes"]
    return [n for n in names if n in FIELD_TUNING], [n for n in names if n not in FIELD_TUNING]


def save(kind: str, rows: list[dict], meta: dict) -> None:
    d = WORK / kind
    d.mkdir(parents=True, exist_ok=True)
    (d / "rows.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))


def read(kind: str) -> dict | None:
    p = WORK / kind / "rows.json"
    return json.loads(p.read_text()) if p.is_file() else None


# --------------------------------------------------------------------------- runs


def run_demo(args) -> None:
    """skirt (full, body_only) and tight (full) with both codes, their default settings."""
    meta = {**machine(), "load_start": load(), "command": "demo", "fit_anchor": fit_anchor(["skirt"])}
    jobs = []
    for code in (REFERENCE, "."):
        label = REFERENCE if code != "." else "this code"
        for scene, variant in (("skirt", "full"), ("skirt", "body_only"), ("tight", "full")):
            jobs.append(Job(label, scene, variant, WORK / "demo" / f"{code.strip('.') or 'new'}_{scene}_{variant}",
                            code=code))
    rows = run_jobs(jobs, args.workers)
    meta["load_end"] = load()
    save("demo", rows, meta)


def run_profile(args) -> None:
    """benchmarks/field_profile.py in both codes, on 1 and 2 threads (one process at a time)."""
    meta = {**machine(), "load_start": load(), "command": "profile"}
    rows = []
    for code in (REFERENCE, "."):
        for threads in (1, 2):
            out = WORK / "profile" / f"{code.strip('.') or 'new'}_{threads}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            env = dict(os.environ)
            cd = code_dir(code)
            if cd is not None:
                env["PYTHONPATH"] = str(cd)
            # run as a script, not with -m: the working directory would come before PYTHONPATH
            subprocess.run([sys.executable, str(ROOT / "benchmarks" / "field_profile.py"), "--threads", str(threads),
                            "--out", str(out)], cwd=ROOT, env=env, check=True)
            r = json.loads(out.read_text())
            r["method"] = REFERENCE if code != "." else "this code"
            rows.append(r)
    meta["load_end"] = load()
    save("profile", rows, meta)


def _budget_overlay(steps: int) -> dict:
    return {"field": {"train": {"steps": steps}}}


def _budget_jobs(kind: str, scenes: list[str], budgets: tuple[float, ...]) -> list[Job]:
    """Both variants of every scene: the reference at its default, this code at ``budgets`` x its steps."""
    steps = int(config()["field"]["train"]["steps"])
    jobs = []
    for scene in scenes:
        for variant in ("full", "body_only"):
            jobs.append(Job(REFERENCE, scene, variant, WORK / kind / scene / f"ref_{variant}", code=REFERENCE))
            for b in budgets:
                n = max(1, round(b * steps))
                jobs.append(Job("this code", scene, variant, WORK / kind / scene / f"new_{variant}_{n}",
                                overlay=_budget_overlay(n)))
    return jobs


def run_suite(args) -> None:
    """The held-out scenes: the reference at its default, this code at BUDGETS of its steps."""
    tuning, held = suite_scenes()
    steps = int(config()["field"]["train"]["steps"])
    meta = {**machine(), "load_start": load(), "command": "suite", "tuning": tuning, "held_out": held,
            "fit_anchor": fit_anchor(tuning + held),
            "steps": steps}
    rows = run_jobs(_budget_jobs("suite", held, BUDGETS), args.workers)
    meta["load_end"] = load()
    save("suite", rows, meta)


def run_convergence(args) -> None:
    """The tuning scenes: the reference at its default, this code at CURVE x its steps."""
    tuning, held = suite_scenes()
    steps = int(config()["field"]["train"]["steps"])
    meta = {**machine(), "load_start": load(), "command": "convergence", "tuning": tuning, "held_out": held,
            "fit_anchor": fit_anchor(tuning + held),
            "steps": steps}
    rows = run_jobs(_budget_jobs("convergence", tuning, CURVE), args.workers)
    meta["load_end"] = load()
    save("convergence", rows, meta)


def attribution_jobs(scene: str) -> list[Job]:
    """The rows of the attribution table on one tuning scene (this code, its default budget)."""
    d = WORK / "attribution" / scene
    train, pose = scene_sequences(scene)
    res = ROOT / "results" / scene
    floor = {s: str(rig_floor_poses(scene, s, res / "rig.npz", d / f"rig_floor_{s}.npz")) for s in (train, pose)}
    jobs = [Job("pipeline fits", scene, "full", d / "fits"),
            Job("body_only", scene, "body_only", d / "body_only"),
            Job("rig floor", scene, "full", d / "floor", poses=floor),
            Job("dense ground-truth deformation", scene, "full", d / "dense_gt", oracle="dense_gt"),
            Job("warp: HumanNeRF blend (the paper's)", scene, "full", d / "blend",
                overlay={"field": {"model": {"warp_iterations": 0}}}),
            Job("warp: HumanNeRF blend, rig floor", scene, "full", d / "blend_floor", poses=floor,
                overlay={"field": {"model": {"warp_iterations": 0}}}),
            Job("capacity: hash 2^19 x 8 levels to 512, MLP 128", scene, "full", d / "capacity",
                overlay={"field": {"model": {"hash_log2_size": 19, "hash_max_resolution": 512, "width": 128}}}),
            Job("training: 4x the steps", scene, "full", d / "steps4x",
                overlay={"field": {"train": {"steps": 4 * int(config()["field"]["train"]["steps"])}}})]
    jobs.append(Job("garment poses refined through the images (field/train/refine_garment)", scene, "full",
                    d / "refine", overlay={"field": {"train": {"refine_garment": True}}}))
    jobs.append(Job("density: Mip-NeRF 360 distortion loss, weight 0.01", scene, "full", d / "distortion",
                    overlay={"field": {"train": {"distortion_weight": 0.01}}}))
    noisy = {s: str(noisy_bodies(scene, s, 2.0, d / f"bodies_2cm_{s}")) for s in (train, pose)}
    jobs.append(Job("body poses with 2 cm noise (the field only; fits from exact poses)", scene, "full",
                    d / "body_noise", body=noisy))
    for bones in (40, 60):
        rig = d / f"rig_{bones}.npz"
        if not rig.is_file():
            sims = sorted(str(p) for p in (res / "sim").glob("*.npz"))
            subprocess.run([str(Path(sys.executable).parent / "anidress"), "rig", str(res / "template.npz"), *sims,
                            "--bones", str(bones), "-o", str(rig)], cwd=ROOT, check=True, capture_output=True)
        fl = {s: str(rig_floor_poses(scene, s, rig, d / f"rig{bones}_floor_{s}.npz")) for s in (train, pose)}
        jobs.append(Job(f"rig of {bones} bones, its rig floor", scene, "full", d / f"floor_{bones}", rig=str(rig),
                        poses=fl))
    return jobs


#: the texture rows: the first tuning scene (a plain skirt) synthesised again with these fabrics
TEXTURES = ("plain", "plaid", "floral")


def texture_jobs(scene: str) -> list[Job]:
    """The same garment, motion and cloth in other fabrics (``anidress synth`` of a copy of the scene's section
    with another texture, sharing its template and rig): rig-floor poses and ground-truth masks for all, so that
    only the texture differs (plain < plaid < floral in frequency)."""
    d = WORK / "attribution" / f"{scene}_texture"
    d.mkdir(parents=True, exist_ok=True)
    base = yaml.safe_load(FIELD_SUITE.read_text())["scenes"][scene]
    train, pose = scene_sequences(scene)
    jobs = []
    for tex in TEXTURES:
        name = scene if tex == base["garment"]["texture"] else f"{scene}_{tex}"
        if not (ROOT / "data" / name / "scene.yaml").is_file():
            sec = json.loads(json.dumps(base))
            sec["garment"]["texture"] = tex
            cfg = config()
            cfg["scenes"] = {name: sec}
            cfg["run_scenes"] = [name]
            (d / f"{name}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
            subprocess.run([str(Path(sys.executable).parent / "anidress"), "synth", "--config", str(d / f"{name}.yaml"),
                            "--scene", name, "--threads", "1", "--quiet"], cwd=ROOT, check=True)
        res = ROOT / "results" / name
        if name != scene:
            res.mkdir(parents=True, exist_ok=True)
            for f in ("template.npz", "rig.npz"):
                if not (res / f).exists():
                    (res / f).symlink_to(ROOT / "results" / scene / f)
        floor = {s: str(rig_floor_poses(name, s, res / "rig.npz", d / f"floor_{tex}_{s}.npz")) for s in (train, pose)}
        jobs.append(Job(f"texture: {tex} (rig floor, ground-truth masks)", name, "full", d / tex, poses=floor,
                        masks=str(ROOT / "data" / name / train / "gt" / "masks")))
    return jobs


def run_attribution(args) -> None:
    tuning, _ = suite_scenes()
    meta = {**machine(), "load_start": load(), "command": "attribution", "scenes": tuning,
            "fit_anchor": fit_anchor(tuning)}
    jobs = [j for s in tuning for j in attribution_jobs(s)] + texture_jobs(tuning[0])
    rows = run_jobs(jobs, args.workers)
    meta["load_end"] = load()
    save("attribution", rows, meta)


#: the settings compared with the defaults on the held-out scenes (`full`): (label, directory, config overlay)
OPTIONS = (("this code, its defaults", "default", {}),
           ("warp: HumanNeRF blend (the paper's; field/model/warp_iterations 0)", "blend",
            {"field": {"model": {"warp_iterations": 0}}}),
           ("garment poses refined through the images (field/train/refine_garment)", "refine",
            {"field": {"train": {"refine_garment": True}}}))


def run_options(args) -> None:
    """The held-out scenes, variant `full`: this code's defaults beside the paper's warp and the pose refinement."""
    tuning, held = suite_scenes()
    meta = {**machine(), "load_start": load(), "command": "options", "tuning": tuning, "held_out": held,
            "fit_anchor": fit_anchor(held)}
    jobs = [Job(label, scene, "full", WORK / "options" / scene / name, overlay=overlay)
            for scene in held for label, name, overlay in OPTIONS]
    rows = run_jobs(jobs, args.workers)
    meta["load_end"] = load()
    save("options", rows, meta)


def bound_jobs(scene: str) -> list[Job]:
    """The exact-input bounds on a held-out scene: the rig floor's garment poses, the dense ground-truth
    deformation (this code, its default budget, ``full``)."""
    d = WORK / "bound" / scene
    train, pose = scene_sequences(scene)
    res = ROOT / "results" / scene
    floor = {s: str(rig_floor_poses(scene, s, res / "rig.npz", d / f"rig_floor_{s}.npz")) for s in (train, pose)}
    return [Job("rig floor", scene, "full", d / "floor", poses=floor),
            Job("dense ground-truth deformation", scene, "full", d / "dense_gt", oracle="dense_gt")]


def run_bound(args) -> None:
    """The held-out scenes with exact garment inputs: how far any garment-pose or deformation fix could go."""
    tuning, held = suite_scenes()
    meta = {**machine(), "load_start": load(), "command": "bound", "tuning": tuning, "held_out": held,
            "fit_anchor": fit_anchor(held)}
    rows = run_jobs([j for s in held for j in bound_jobs(s)], args.workers)
    meta["load_end"] = load()
    save("bound", rows, meta)


# --------------------------------------------------------------------------- tables


def _fits_line(m: dict) -> str:
    """Which L_anchor references the pipeline's fits of a run had (:func:`benchmarks.field_runs.fit_anchor`); a run
    from before that was recorded: the default at its commit (schema ``fit/anchor_reference``)."""
    if "fit_anchor" in m:
        return f"- the pipeline's fits: L_anchor references from {m['fit_anchor']} (fit/anchor_reference)"
    rev = (str(m.get("git", "")).split() or [""])[0]
    try:
        if not rev:
            raise KeyError("git")
        schema = yaml.safe_load(subprocess.run(["git", "show", f"{rev}:workflow/schemas/config.schema.yaml"], cwd=ROOT,
                                               capture_output=True, text=True, check=True).stdout)
        default = schema["properties"]["fit"]["properties"]["anchor_reference"]["default"]
    except (subprocess.CalledProcessError, KeyError, TypeError, yaml.YAMLError):
        return "- the pipeline's fits: L_anchor references not recorded"
    return (f"- the pipeline's fits: L_anchor references not recorded by this run; the default at git {rev} was "
            f"{default}")


def _f(x, nd: int = 2) -> str:
    if x is None or (isinstance(x, float) and (x != x or abs(x) == float("inf"))):
        return "n/a"
    return f"{x:.{nd}f}"


def _fig_cols(r: dict) -> list[str]:
    out = []
    for k in ("nv", "np"):
        out += [_f(r.get(f"{k}_psnr_db")), _f(r.get(f"{k}_psnr_subject_db")), _f(r.get(f"{k}_psnr_garment_db")),
                _f(r.get(f"{k}_psnr_body_db")), _f(r.get(f"{k}_ssim_subject"), 4), _f(r.get(f"{k}_iou"), 4)]
    return out


FIG_HEAD = ("novel view: box / subject / garment / body PSNR (dB), subject SSIM, IoU",
            "novel pose: box / subject / garment / body PSNR (dB), subject SSIM, IoU")


def _figs(r: dict, k: str) -> str:
    return " / ".join(_f(r.get(f"{k}_{f}")) for f in ("psnr_db", "psnr_subject_db", "psnr_garment_db",
                                                        "psnr_body_db")) + \
        f", {_f(r.get(f'{k}_ssim_subject'), 4)}, {_f(r.get(f'{k}_iou'), 4)}"


def demo_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    L = [f"- command: `.venv/bin/python -m benchmarks.bench_field demo` (git {m['git']}, {m['date']}); {m['cpu']}, "
         f"{m['cpus']} logical CPUs; load {m['load_start']} at the start, {m['load_end']} at the end",
         _fits_line(m),
         "- each field trained, rendered and scored as rules train_field / render_* / evaluate_field do (the pipeline's "
         "masks, rig and fits of `make demo`), one torch thread, two jobs side by side; each code with its own "
         "default settings. Novel view: the 4 test cameras on every 12th training frame; novel pose: all 12 "
         "cameras on every 12th frame of `dance`. Masks of the regions: the ground truth's labels (gt/masks)", "",
         f"| scene, variant | code | steps x rays | train wall s (CPU s) | render CPU s/image (nv, np) | {FIG_HEAD[0]} | "
         f"{FIG_HEAD[1]} |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: (r["scene"], r["variant"], r["code"] == ".")):
        L.append(f"| {r['scene']}, {r['variant']} | {r['method']} | {r['steps']} x {r['rays_per_step']} | "
                 f"{_f(r['train_wall_s'], 0)} ({_f(r['train_cpu_s'], 0)}) | {_f(r['nv_render_cpu_s_per_image'])}, "
                 f"{_f(r['np_render_cpu_s_per_image'])} | {_figs(r, 'nv')} | {_figs(r, 'np')} |")
    # against the reference, figure by figure
    L += ["", "Change against the reference (this code minus 6aee398; PSNR in dB):", "",
          "| scene, variant | kind | box | subject | garment | body | subject SSIM | IoU | train wall time | "
          "render time per image |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for scene, variant in sorted({(r["scene"], r["variant"]) for r in rows}):
        ref = [r for r in rows if (r["scene"], r["variant"]) == (scene, variant) and r["code"] != "."]
        new = [r for r in rows if (r["scene"], r["variant"]) == (scene, variant) and r["code"] == "."]
        if not ref or not new:
            continue
        a, b = ref[0], new[0]
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            d_ = [b[f"{k}_{f}"] - a[f"{k}_{f}"] for f in ("psnr_db", "psnr_subject_db", "psnr_garment_db",
                                                          "psnr_body_db", "ssim_subject", "iou")]
            L.append(f"| {scene}, {variant} | {name} | {d_[0]:+.2f} | {d_[1]:+.2f} | {d_[2]:+.2f} | {d_[3]:+.2f} | "
                     f"{d_[4]:+.4f} | {d_[5]:+.4f} | {b['train_wall_s'] / a['train_wall_s']:.2f}x | "
                     f"{b[f'{k}_render_cpu_s_per_image'] / a[f'{k}_render_cpu_s_per_image']:.2f}x |")
    return L


def profile_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    L = [f"- command: `.venv/bin/python -m benchmarks.bench_field profile` (git {m['git']}, {m['date']}); {m['cpu']}; "
         f"load {m['load_start']} at the start, {m['load_end']} at the end",
         "- benchmarks/field_profile.py on the demo skirt's `full` field (the pipeline's inputs), each code with its "
         "defaults: CPU ms per training step of `train_field`, and each part alone on one batch (forward and "
         "backward; the weight volume's decode per step); what the step spends beyond the parts is Python and launch "
         "overhead. Rendering: CPU s per image of the training cameras' mask boxes, early termination on", ""]
    parts = list(rows[0]["parts_cpu_s"])
    head = [f"{r['method']}, {r['threads']} thread{'s' if r['threads'] > 1 else ''}" for r in rows]
    L += ["| CPU ms per step | " + " | ".join(head) + " |", "| --- |" + " --- |" * len(rows)]
    for p in parts:
        L.append(f"| {p} | " + " | ".join(_f(1e3 * r["parts_cpu_s"][p], 1) for r in rows) + " |")
    L.append("| **whole step** | " + " | ".join(f"**{_f(1e3 * r['train_cpu_s_per_step'], 1)}**" for r in rows) + " |")
    L.append("| samples per step (rays per step) | " + " | ".join(f"{r['samples_per_step']} ({r['rays_per_step']})"
                                                                    for r in rows) + " |")
    L.append("| rays per CPU second | " + " | ".join(f"{r['rays_per_step'] / r['train_cpu_s_per_step'] / 1e3:.1f} K"
                                                     for r in rows) + " |")
    for name in rows[0].get("ablations_cpu_s_per_step", {}):
        L.append(f"| step with {name} (x the whole step) | " + " | ".join(
            f"{_f(1e3 * r['ablations_cpu_s_per_step'][name], 0)} ({r['ablations_cpu_s_per_step'][name] / r['train_cpu_s_per_step']:.1f}x)"
            for r in rows) + " |")
    L.append("| render CPU s per image (samples per ray) | " + " | ".join(
        f"{_f(r['render_cpu_s_per_image'], 3)} ({_f(r['render_samples_per_ray'], 1)})" for r in rows) + " |")
    return L


def time_to_quality(rows: list[dict]) -> list[dict]:
    """Per (scene, variant): the reference's wall time and figures, the smallest budget of this code reaching
    every QUALITY figure of the reference on both kinds, and its wall time."""
    out = []
    for scene, variant in sorted({(r["scene"], r["variant"]) for r in rows}):
        ref = [r for r in rows if (r["scene"], r["variant"]) == (scene, variant) and r["code"] != "."]
        new = sorted([r for r in rows if (r["scene"], r["variant"]) == (scene, variant) and r["code"] == "."],
                     key=lambda r: r["steps"])
        if not ref or not new:
            continue
        a = ref[0]
        reach = next((r for r in new if all(r[f"{k}_{q}"] >= a[f"{k}_{q}"] for k in ("nv", "np") for q in QUALITY)),
                     None)
        out.append({"scene": scene, "variant": variant, "ref": a, "reach": reach, "default": new[-1],
                    "ratio": None if reach is None else reach["train_wall_s"] / a["train_wall_s"],
                    "cpu_ratio": None if reach is None else reach["train_cpu_s"] / a["train_cpu_s"]})
    return out


def _med_worst(vals: list[float], worst=min) -> str:
    return f"median {statistics.median(vals):+.2f}, worst {worst(vals):+.2f}" if vals else "n/a"


def _change_summary(ref: list[dict], new: list[dict], scenes: list[str], k: str) -> str:
    """'garment median .., worst ..; subject ..; box ..; IoU ..': ``new`` minus ``ref`` (rows of one kind of
    run each, one per scene) over ``scenes``, for kind ``k`` (nv, np)."""
    pairs = _paired(ref, new, scenes)
    return "; ".join(f"{nd} {_med_worst([b[f'{k}_{f}'] - a[f'{k}_{f}'] for _, a, b in pairs])}"
                     for f, nd in (("psnr_garment_db", "garment"), ("psnr_subject_db", "subject"), ("psnr_db", "box"),
                                   ("iou", "IoU")))


def _paired(ref: list[dict], new: list[dict], scenes: list[str]) -> list[tuple[str, dict, dict]]:
    """(scene, its row in ``ref``, its row in ``new``) for each of ``scenes`` that both lists have."""
    out = []
    for sc in scenes:
        a = [r for r in ref if r["scene"] == sc]
        b = [r for r in new if r["scene"] == sc]
        if a and b:
            out.append((sc, a[0], b[0]))
    return out


def _suite_head(m: dict, what: str, budgets: tuple[float, ...]) -> list[str]:
    return [f"- command: `.venv/bin/python -m benchmarks.bench_field {what}` (git {m['git']}, {m['date']}); {m['cpu']}; "
            f"load {m['load_start']} at the start, {m['load_end']} at the end", _fits_line(m),
            "- scenes: config/field_suite.yaml (`benchmarks/fit_suite.py --seed 26 --prefix fsuite --count 6 "
            "--novel-pose`), each through the pipeline (`snakemake` with the suite overlay) for its masks, rig and "
            f"fits. Tuning subset (the field's settings were chosen on it): {', '.join(m['tuning'])}; held out: "
            f"{', '.join(m['held_out'])}. No per-scene settings. The synthetic scenes give exact body poses (a "
            "capture's are estimated)",
            f"- this code at {', '.join(str(max(1, round(b * m['steps']))) for b in budgets)} steps of "
            f"{int(config()['field']['train']['rays_per_step'])} rays (its default: {m['steps']}); the reference at "
            "its own default (600 steps x 2048 rays). Quality = subject and garment PSNR in novel view and in novel "
            "pose; time to quality = the training wall time of the smallest budget reaching all four figures of "
            "the reference"]


def _time_to_quality_lines(rows: list[dict], label: str) -> list[str]:
    tq = time_to_quality(rows)
    L = ["| scene | variant | reference: wall s (CPU s) | this code: steps reaching it, wall s (CPU s) | "
         "wall-time ratio |", "| --- | --- | --- | --- | --- |"]
    for t in tq:
        a, r = t["ref"], t["reach"]
        got = "not reached within the budgets" if r is None else \
            f"{r['steps']}, {_f(r['train_wall_s'], 1)} ({_f(r['train_cpu_s'], 1)})"
        L.append(f"| {t['scene']} | {t['variant']} | {_f(a['train_wall_s'], 1)} ({_f(a['train_cpu_s'], 1)}) | {got} | "
                 f"{_f(t['ratio'], 3)} |")
    ok = [t["ratio"] for t in tq if t["ratio"] is not None]
    missing = sum(t["ratio"] is None for t in tq)
    if ok:
        L.append(f"- {label}: wall-time ratio median {statistics.median(ok):.3f} (1/{1 / statistics.median(ok):.1f}), "
                 f"worst {max(ok):.3f} over {len(ok)} fields" + (f"; {missing} not reached" if missing else ""))
    return L


def suite_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    held, steps = m["held_out"], m["steps"]
    L = _suite_head(m, "suite", BUDGETS) + [""]
    dflt = [r for r in rows if r["code"] != "." or r["steps"] == steps]
    L += [f"| scene | variant | code | train wall s | {FIG_HEAD[0]} | {FIG_HEAD[1]} |",
          "| --- | --- | --- | --- | --- | --- |"]
    for r in sorted(dflt, key=lambda r: (r["scene"], r["variant"], r["code"] == ".")):
        L.append(f"| {r['scene']} | {r['variant']} | {r['method']} | {_f(r['train_wall_s'], 0)} | {_figs(r, 'nv')} | "
                 f"{_figs(r, 'np')} |")
    L += ["", "This code at its defaults minus the reference, over the held-out scenes (PSNR dB; IoU):", ""]
    for variant in ("full", "body_only"):
        ref = [r for r in dflt if r["variant"] == variant and r["code"] != "."]
        new = [r for r in dflt if r["variant"] == variant and r["code"] == "."]
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            L.append(f"- `{variant}`, {name}: " + _change_summary(ref, new, held, k))
    L.append("")
    mine = {v: [r for r in dflt if r["code"] == "." and r["variant"] == v] for v in ("full", "body_only")}
    both = _paired(mine["body_only"], mine["full"], held)
    for k, name in (("nv", "novel view"), ("np", "novel pose")):
        g = f"{k}_psnr_garment_db"
        margins = [(sc, full[g] - body[g]) for sc, body, full in both]
        if margins:
            L.append(f"- `full` - `body_only`, garment PSNR, {name}, this code: " +
                     ", ".join(f"{sc} {v:+.2f}" for sc, v in margins) +
                     f"; `full` ahead on {sum(v > 0 for _, v in margins)} of {len(margins)}")
    L += ["", "Render CPU s per image, this code at its defaults over the reference (one thread; the same images):", ""]
    for variant in ("full", "body_only"):
        pairs = _paired([r for r in dflt if r["variant"] == variant and r["code"] != "."],
                        [r for r in dflt if r["variant"] == variant and r["code"] == "."], held)
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            f = f"{k}_render_cpu_s_per_image"
            ratios = [b[f] / a[f] for _, a, b in pairs if a.get(f) and b.get(f)]
            if ratios:
                L.append(f"- `{variant}`, {name}: median {statistics.median(ratios):.2f}x, worst {max(ratios):.2f}x "
                         f"over {len(ratios)} scenes")
    L += ["", "### Time to the reference's quality (held out)", ""] + _time_to_quality_lines(rows, "held out")
    return L


def convergence_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    L = _suite_head(m, "convergence", CURVE)
    L += ["", "| scene | variant | code | steps | train wall s (CPU s) | novel view subject / garment PSNR | "
          "novel pose subject / garment PSNR |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: (r["scene"], r["variant"], r["code"] == ".", r["steps"])):
        L.append(f"| {r['scene']} | {r['variant']} | {r['method']} | {r['steps']} | {_f(r['train_wall_s'], 1)} "
                 f"({_f(r['train_cpu_s'], 1)}) | {_f(r['nv_psnr_subject_db'])} / {_f(r['nv_psnr_garment_db'])} | "
                 f"{_f(r['np_psnr_subject_db'])} / {_f(r['np_psnr_garment_db'])} |")
    L += ["", "Time to the reference's quality (tuning):", ""] + _time_to_quality_lines(rows, "tuning")
    return L


def attribution_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    L = [f"- command: `.venv/bin/python -m benchmarks.bench_field attribution` (git {m['git']}, {m['date']}); "
         f"{m['cpu']}; load {m['load_start']} at the start, {m['load_end']} at the end",
         _fits_line(m),
         "- one row per cause, the same training budget (this code's default steps and rays) unless the row is the "
         "budget; `full` unless named. Rig floor: the rig's bone transforms fitted to the ground-truth garment "
         "meshes. Dense ground-truth deformation (benchmarks/field_oracle.py): each garment sample carried to the "
         "template through the ground-truth mesh of its frame (nearest face, barycentric coordinates and the offset "
         "along its normal), which approximately bounds any deformation model of the garment; where folds bring "
         "two layers within a centimetre a sample may take the wrong one (its share is in the job's log)", "",
         "| row | scene | novel view garment / subject PSNR | novel pose garment / subject PSNR | novel pose box PSNR, "
         "IoU | train wall s |", "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        L.append(f"| {r['method']} | {r['scene']} | {_f(r['nv_psnr_garment_db'])} / {_f(r['nv_psnr_subject_db'])} | "
                 f"{_f(r['np_psnr_garment_db'])} / {_f(r['np_psnr_subject_db'])} | {_f(r['np_psnr_db'])}, "
                 f"{_f(r['np_iou'], 4)} | {_f(r['train_wall_s'], 0)} |")
    return L


def options_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    base = OPTIONS[0][0]
    L = [f"- command: `.venv/bin/python -m benchmarks.bench_field options` (git {m['git']}, {m['date']}); "
         f"{m['cpu']}; load {m['load_start']} at the start, {m['load_end']} at the end",
         _fits_line(m),
         f"- held-out scenes {', '.join(m['held_out'])} (tuning: {', '.join(m['tuning'])}), variant `full`, the "
         "pipeline's fits, this code's default budget; each row changes one setting", "",
         f"| scene | row | train wall s | {FIG_HEAD[0]} | {FIG_HEAD[1]} |", "| --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: r["scene"]):
        L.append(f"| {r['scene']} | {r['method']} | {_f(r['train_wall_s'], 0)} | {_figs(r, 'nv')} | "
                 f"{_figs(r, 'np')} |")
    L += ["", "Each row minus the defaults, over the held-out scenes (PSNR dB; IoU):", ""]
    ref = [r for r in rows if r["method"] == base]
    for label, _, _ in OPTIONS[1:]:
        new = [r for r in rows if r["method"] == label]
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            L.append(f"- {label}, {name}: " + _change_summary(ref, new, m["held_out"], k))
    return L


#: issue 46's targets over the reference on the held-out scenes (median): garment and subject PSNR, dB
BOUND_TARGETS = {"psnr_garment_db": 3.0, "psnr_subject_db": 2.0}


def bound_table(d: dict) -> list[str]:
    m, rows = d["meta"], d["rows"]
    held = m["held_out"]
    suite, options = read("suite"), read("options")
    ref = [r for r in (suite or {}).get("rows", []) if r["code"] != "." and r["variant"] == "full"]
    now = [r for r in (options or {}).get("rows", []) if r["method"] == OPTIONS[0][0]]
    L = [f"- command: `.venv/bin/python -m benchmarks.bench_field bound` (git {m['git']}, {m['date']}); {m['cpu']}; "
         f"load {m['load_start']} at the start, {m['load_end']} at the end", _fits_line(m),
         f"- held-out scenes {', '.join(held)}, variant `full`, this code's default budget. Rig floor: the rig's bone "
         "transforms fitted to the ground-truth garment meshes in place of the fits (training and novel-pose "
         "sequences); dense ground-truth deformation: every garment sample carried to the template through the "
         "true mesh of its frame (the attribution's oracle), a bound on any garment pose or deformation model, "
         "refinement through the images included. The reference (git 6aee398) rows are the suite run's, this "
         "code's the options run's", "",
         f"| scene | row | train wall s | {FIG_HEAD[0]} | {FIG_HEAD[1]} |", "| --- | --- | --- | --- | --- |"]
    labelled = [dict(r, method=f"reference {REFERENCE}") for r in ref] + \
        [dict(r, method="this code, the pipeline's fits") for r in now] + rows
    for sc in held:
        for r in [r for r in labelled if r["scene"] == sc]:
            L.append(f"| {sc} | {r['method']} | {_f(r['train_wall_s'], 0)} | {_figs(r, 'nv')} | {_figs(r, 'np')} |")
    L += ["", f"Each row minus the reference {REFERENCE}, over the held-out scenes (PSNR dB; IoU); issue 46 asks for "
          "a median of +3 dB garment and +2 dB subject PSNR in novel view and novel pose:", ""]
    for label in ("this code, the pipeline's fits", "rig floor", "dense ground-truth deformation"):
        new = [r for r in labelled if r["method"] == label]
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            L.append(f"- {label}, {name}: " + _change_summary(ref, new, held, k))
    dense = [r for r in labelled if r["method"] == "dense ground-truth deformation"]
    for f, target in BOUND_TARGETS.items():
        for k, name in (("nv", "novel view"), ("np", "novel pose")):
            vals = [b[f"{k}_{f}"] - a[f"{k}_{f}"] for sc in held for a in ref if a["scene"] == sc
                    for b in dense if b["scene"] == sc]
            if vals:
                med = statistics.median(vals)
                L.append(f"- target {f.split('_')[1]} +{target:g} dB, {name}: the dense ground-truth bound reaches "
                         f"median {med:+.2f} dB: " + ("within reach of a perfect garment model" if med >= target
                                                      else "beyond the bound"))
    return L


def write(args) -> None:
    L = ["# Pose-driven radiance field benchmark (`anidress_core.field`): this code against git 6aee398", "",
         "Generated by `benchmarks/bench_field.py` (its module docstring has the commands); each section names the "
         "run it comes from. PSNR `box`: inside the projected 3D box of the subject (the paper's and Neural Body's "
         "convention, mostly black background); `subject` / `garment` / `body`: pooled over the pixels inside the "
         "ground-truth subject mask and its garment and body labels (evaluate_field). LPIPS / DISTS: not available "
         "on this machine (no pretrained weights), not replaced.", ""]
    rows_csv = []
    md, csv_path = ROOT / "benchmarks" / "field.md", ROOT / "benchmarks" / "field.csv"
    kept_md = _sections(md.read_text()) if md.is_file() else {}
    kept_csv = []
    if csv_path.is_file():
        with open(csv_path, newline="") as fh:
            kept_csv = list(csv.DictReader(fh))
    for kind, table in (("demo", demo_table), ("profile", profile_table), ("suite", suite_table),
                        ("convergence", convergence_table), ("attribution", attribution_table),
                        ("options", options_table), ("bound", bound_table)):
        d = read(kind)
        if d is None:  # no run on disk (a fresh clone): the section as field.md has it, else "not run"
            if TITLES[kind] in kept_md:
                L += kept_md[TITLES[kind]] + [""]
                rows_csv += [{k: v for k, v in r.items() if v != ""} for r in kept_csv if r["section"] == kind]
            else:
                L += [f"## {TITLES[kind]}", "", f"not run (`python -m benchmarks.bench_field {kind}`)", ""]
            continue
        L += [f"## {TITLES[kind]}", ""]
        failed = [r for r in d["rows"] if "failed" in r]
        d["rows"] = [r for r in d["rows"] if "failed" not in r]
        L += table(d) + [""]
        if failed:
            L += [f"- failed jobs of this run (not in the table): " + "; ".join(
                f"{r['method']}, {r['scene']} {r['variant']}: {r['failed']}" for r in failed), ""]
        for r in d["rows"]:
            if kind == "profile":
                flat = {"section": kind, "method": r["method"], "scene": r["scene"], "variant": r["variant"],
                        "threads": r["threads"], "train_cpu_s_per_step": r["train_cpu_s_per_step"],
                        "render_cpu_s_per_image": r["render_cpu_s_per_image"],
                        **{f"part_{k}_cpu_s": v for k, v in r["parts_cpu_s"].items()}}
            else:
                flat = {"section": kind, **{k: v for k, v in r.items() if k != "spec"}}
            flat["reference"] = "" if r.get("method") == REFERENCE else REFERENCE
            rows_csv.append(flat)
    md.write_text("\n".join(L).rstrip() + "\n")
    cols = []
    for r in rows_csv:
        cols += [k for k in r if k not in cols]
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, lineterminator="\n")
        w.writeheader()
        for r in rows_csv:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    print(ROOT / "benchmarks" / "field.md")


def _sections(text: str) -> dict[str, list[str]]:
    """{heading: its lines, the heading included, trailing blank lines left out} of the ``## `` sections of a
    field.md."""
    out: dict[str, list[str]] = {}
    cur = None
    for line in text.splitlines():
        if line.startswith("## "):
            cur = line[3:]
            out[cur] = []
        if cur is not None:
            out[cur].append(line)
    for lines in out.values():
        while lines and not lines[-1].strip():
            lines.pop()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["demo", "profile", "suite", "convergence", "attribution", "options", "bound",
                                     "write"])
    ap.add_argument("--workers", type=int, default=2, help="jobs side by side (one torch thread each)")
    args = ap.parse_args()
    {"demo": run_demo, "profile": run_profile, "suite": run_suite, "convergence": run_convergence,
     "attribution": run_attribution, "options": run_options, "bound": run_bound, "write": write}[args.what](args)


if __name__ == "__main__":
    main()
