"""The demo skirt as a capture (issue 24 items 4, 5): the workflow on the synthetic scene and on its
``anidress export-capture`` variants, scored against the held-back truth.

Reduced scale (stated in the output): the demo skirt scene (config/config.yaml scenes/skirt: 12
cameras, 8 train, 256 x 256, 3K-vertex garment) with ``--frames`` frames of walk (train) and of dance
(novel pose), one library motion (sway, 60 frames) for the rig, the ``full`` field only with
``--steps`` steps, novel-pose renders of every ``--render-stride``-th frame of dance (12 cameras).

Variants (``--variants``, in order; each a separate Snakemake run in ``WORK/<variant>``, one at a time):

* ``synthetic``: the scene as rule synth writes it (plates, texture, exact poses, pinhole, square), the fit's
  L_anchor on the texture (fit/anchor_reference: texture);
* ``capture``: every degradation (distortion, 4:3 images, 2 cm body noise, no masks: the pipeline's
  masks from a temporal median, no plates, no texture: fit anchor on image references);
* ``crutchless``: no plates, no texture (always dropped by the export) but pinhole, square, exact poses;
* ``pose_noise``: crutchless + 2 cm body noise; ``distort``: crutchless + distortion and 4:3 images;
* ``parser``: crutchless + parser-like masks shipped with the scene;
* ``image_anchor``: the synthetic run (copied with its Snakemake records) with fit/anchor_reference: images:
  the garment texture unused (the one crutch an export cannot drop alone);
* ``parser_pose_noise``: parser + 2 cm body noise (the noise with good masks);
* ``capture_parser``: capture with parser-like masks shipped (a user who runs a human parser);
* ``*_refined``: ``pose_noise``, ``parser_pose_noise``, ``capture_parser`` with rule refine_body on (the
  noisy body poses refined against the masks before motions, fit and field);
* the cue files of the tools users run (issue 47), each against its twin in the pipeline's formats:
  ``parser_files`` (parser + network-like flows shipped, cues/flows/method: files; labels, EXR normals, EXR
  flows), ``parser_easymocap`` (the same cues as EasyMocap's mask-schp silhouettes + SCHP CIHP parsing,
  Sapiens .npy normals in OpenGL axes, RAFT .flo), ``parser_lip_png`` (SCHP LIP palette PNGs, 8-bit (n+1)/2
  normal PNGs, KITTI 16-bit flow PNGs); ``distort_files`` / ``distort_easymocap``: the same with lens
  distortion and 4:3 images (the flow vectors remapped by rule undistort).

Scores (held-back truth, the pipeline's own scorers): the fit of walk by
:func:`anidress_core.stages.fit_eval.run_fit_eval` (vertex RMSE and its ratio to the run's rig floor), the
novel-pose renders of dance by :func:`anidress_core.stages.evaluate.run_evaluate` (PSNR, IoU), in the
working cameras of rule undistort for a distorted variant (truth masks undistorted with the images).

    .venv/bin/python -m benchmarks.bench_capture --work /tmp/capbench [--variants synthetic,capture]

writes benchmarks/capture.md and .csv (``--name``: benchmarks/<name>.md, .csv).
"""
from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

from .benchutil import cpu_model, git_rev

REPO = Path(__file__).resolve().parents[1]
VARIANTS = {
    "synthetic": None,
    "capture": {"distort": True, "pose_noise_cm": 2.0, "masks": "none", "image_size": None},
    "crutchless": {"distort": False, "pose_noise_cm": 0.0, "masks": "none", "image_size": "256x256"},
    "pose_noise": {"distort": False, "pose_noise_cm": 2.0, "masks": "none", "image_size": "256x256"},
    "distort": {"distort": True, "pose_noise_cm": 0.0, "masks": "none", "image_size": None},
    "parser": {"distort": False, "pose_noise_cm": 0.0, "masks": "parser", "image_size": "256x256"},
    "image_anchor": None,
    "parser_pose_noise": {"distort": False, "pose_noise_cm": 2.0, "masks": "parser", "image_size": "256x256"},
    "capture_parser": {"distort": True, "pose_noise_cm": 2.0, "masks": "parser", "image_size": None},
    "pose_noise_refined": {"distort": False, "pose_noise_cm": 2.0, "masks": "none", "image_size": "256x256",
                           "refine_body": True},
    "parser_pose_noise_refined": {"distort": False, "pose_noise_cm": 2.0, "masks": "parser", "image_size": "256x256",
                                  "refine_body": True},
    "capture_parser_refined": {"distort": True, "pose_noise_cm": 2.0, "masks": "parser", "image_size": None,
                               "refine_body": True},
    "parser_files": {"distort": False, "pose_noise_cm": 0.0, "masks": "parser", "image_size": "256x256",
                     "flows": True, "cue_files": "pipeline"},
    "parser_easymocap": {"distort": False, "pose_noise_cm": 0.0, "masks": "parser", "image_size": "256x256",
                         "flows": True, "cue_files": "easymocap_sapiens_raft"},
    "parser_lip_png": {"distort": False, "pose_noise_cm": 0.0, "masks": "parser", "image_size": "256x256",
                       "flows": True, "cue_files": "lip_png_kitti"},
    "distort_files": {"distort": True, "pose_noise_cm": 0.0, "masks": "parser", "image_size": None,
                      "flows": True, "cue_files": "pipeline"},
    "distort_easymocap": {"distort": True, "pose_noise_cm": 0.0, "masks": "parser", "image_size": None,
                          "flows": True, "cue_files": "easymocap_sapiens_raft"},
}
TWINS = {"parser_easymocap": "parser_files", "parser_lip_png": "parser_files", "distort_easymocap": "distort_files"}
"""Each tool-format variant and its twin in the pipeline's formats (the same cues)."""
TWIN_TOLERANCE = {"novel_pose_psnr_db": 0.1, "fit_ratio_to_floor": 0.05}
"""Issue 47: a tool-format variant lies within these of its twin (8-bit normals and 16-bit flows quantise)."""
"""Export options of each variant; None: the synthetic scene itself (``image_anchor``: a copy of the
synthetic run with fit/anchor_reference: images, i.e. the garment texture unused: its cost alone).
``refine_body``: the run has rule refine_body on (the body poses refined against the masks)."""
COLUMNS = ["variant", "distort", "image_size", "pose_noise_cm", "refine_body", "masks", "cue_files", "flows",
           "plates", "texture",
           "body_joint_error_cm", "body_joint_angle_deg", "body_jitter_cm", "refined_joint_error_cm",
           "refined_joint_angle_deg", "refined_jitter_cm", "mask_images", "mask_iou_person",
           "mask_iou_garment", "fit_frames", "fit_vertex_rmse_mm", "rig_floor_mm", "fit_ratio_to_floor",
           "novel_pose_images", "novel_pose_psnr_db", "novel_pose_iou", "jobs", "jobs_wall_s", "jobs_cpu_s",
           "status"]


def _config(args, scene: str, entry: dict, exported: bool, refine: bool = False, flow_files: bool = False) -> dict:
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["run_scenes"] = [scene]
    cfg["scenes"] = {scene: entry}
    cfg["simulate"]["library"] = ["sway"]
    cfg["simulate"]["library_frames"] = 60
    cfg["field"]["variants"] = ["full"]
    cfg["field"]["train"]["steps"] = args.steps
    cfg["field"]["train"]["checkpoint_every"] = args.steps
    cfg["field"]["render"]["frame_stride"] = args.render_stride
    cfg["field"]["render"]["library"] = []
    if exported:
        cfg.setdefault("cues", {}).setdefault("masks", {})["background"] = "temporal_median"
    cfg["refine_body"] = dict(cfg.get("refine_body") or {}, enabled=bool(refine))
    if flow_files:
        cfg["cues"]["flows"]["method"] = "files"
    return cfg


def _synthetic_entry(args) -> dict:
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    e = dict(cfg["scenes"]["skirt"])
    e["sequences"] = [{"name": "walk", "motion": "walk", "frames": args.frames, "role": "train"},
                      {"name": "dance", "motion": "dance", "frames": args.frames, "role": "novel_pose"}]
    return e


def _snakemake(work: Path, targets: list[str], cores: int, log: Path) -> tuple[int, float]:
    cmd = [sys.executable, "-m", "snakemake", *targets, "-s", str(REPO / "Snakefile"), "--directory", str(work),
           "--configfile", str(work / "config.yaml"), "--cores", str(cores), "--rerun-triggers", "params", "input",
           "mtime"]
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT,
                            env={**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}).returncode
    return rc, time.perf_counter() - t0


def _score_scene(scene: Path, truth: Path | None, out: Path) -> Path:
    """The scene with the truth's gt/ beside each sequence (symlinks), for the pipeline's scorers."""
    if truth is None:
        return scene
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for p in scene.iterdir():
        if p.is_dir() and (truth / p.name).is_dir():
            (out / p.name).mkdir()
            for q in p.iterdir():
                (out / p.name / q.name).symlink_to(q.resolve())
            (out / p.name / "gt").symlink_to((truth / p.name / "gt").resolve())
        else:
            (out / p.name).symlink_to(p.resolve())
    return out


def _mask_iou(pred_dir: Path, truth_dir: Path) -> dict:
    """Mean IoU of the pipeline's walk masks against the truth (subject: labels > 0; garment: label 2), over
    every camera and frame it wrote (the training cameras)."""
    import numpy as np

    from anidress_core.io import files

    person, garment = [], []
    for p in sorted(pred_dir.glob("*/*.png")):
        a, b = files.read_mask(p), files.read_mask(truth_dir / p.parent.name / p.name)
        for out, x, y in ((person, a > 0, b > 0), (garment, a == 2, b == 2)):
            u = np.logical_or(x, y).sum()
            if u:
                out.append(np.logical_and(x, y).sum() / u)
    return {"mask_iou_person": round(float(np.mean(person)), 4), "mask_iou_garment": round(float(np.mean(garment)), 4),
            "mask_images": len(person)}


def _score(work: Path, scene_name: str, scene: Path, truth: Path | None) -> dict:
    from anidress_core.io.scene import distorted_cameras
    from anidress_core.stages.evaluate import run_evaluate
    from anidress_core.stages.fit_eval import run_fit_eval
    from anidress_core.stages.undistort import run_undistort

    res = work / "results" / scene_name
    sc = _score_scene(scene, truth, work / "score" / scene_name)
    fit = run_fit_eval(sc, "walk", res / "rig.npz", {"pipeline": res / "walk" / "garment_poses.npz"},
                       work / "score" / "fit_metrics.csv")["methods"]["pipeline"]
    und = {}
    for seq in ("walk", "dance"):
        if distorted_cameras(sc, seq):
            run_undistort(sc, seq, work / "score" / f"undistorted_{seq}", threads=1, progress=False)
            und[seq] = work / "score" / f"undistorted_{seq}"
    seq_dir = und.get("walk", sc / "walk")
    pred = res / "walk" / "masks" if (res / "walk" / "masks").is_dir() else seq_dir / "masks"  # else: shipped
    masks = _mask_iou(pred, seq_dir / "gt" / "masks")
    ev = run_evaluate(sc, [("novel_pose", "dance", res / "walk" / "full" / "renders" / "novel_pose" / "dance")],
                      work / "score" / "metrics.csv", work / "score" / "metrics_summary.json", {"box_pad_m": 0.05},
                      progress=False, undistorted=und)
    return {"fit": fit, "eval": ev, "masks": masks}


def _refined_body_errors(scene: Path, truth: Path, body_dir: Path) -> dict:
    """The exporter's body-noise measure (export_capture.pose_errors) of rule refine_body's walk poses."""
    import numpy as np

    from anidress_core.io.motion import read_easymocap_smpl_dir
    from anidress_core.io.scene import load_body
    from anidress_core.stages.export_capture import pose_errors

    def rd(d: Path) -> dict:
        x = read_easymocap_smpl_dir(d)
        return {k: np.asarray(x[k], np.float64) for k in ("poses", "Rh", "Th")}

    e = pose_errors(load_body(scene), rd(truth / "walk" / "smpl"), rd(body_dir / "smpl"))
    return {"refined_joint_error_cm": round(e["joint_error_cm"], 3),
            "refined_joint_angle_deg": round(e["joint_angle_deg"], 3), "refined_jitter_cm": round(e["jitter_cm"], 3)}


def _job_costs(work: Path, scene: str) -> dict:
    """Jobs, summed wall and CPU seconds of the last run of each job (Snakemake's benchmark files)."""
    rows = []
    for p in sorted((work / "benchmarks" / "runs" / scene).rglob("*.tsv")):
        lines = p.read_text().splitlines()
        if len(lines) >= 2:
            rows.append(dict(zip(lines[0].split("\t"), lines[-1].split("\t"))))
    return {"jobs": len(rows), "jobs_wall_s": round(sum(float(r["s"]) for r in rows), 1),
            "jobs_cpu_s": round(sum(float(r.get("cpu_time") or "nan") for r in rows), 1)}


def _summary_row(ev_json: Path) -> dict:
    """The novel-pose entry of run_evaluate's metrics_summary.json."""
    s = json.loads(ev_json.read_text())
    for m in s.get("metrics", []):
        if m.get("kind") == "novel_pose":
            return m
    raise ValueError(f"{ev_json}: no novel_pose entry in 'metrics'")


def run_variant(args, name: str, work_root: Path) -> dict:
    from anidress_core.stages.export_capture import run_export_capture
    from anidress_core.io.scene_info import scene_config_entry

    opts = VARIANTS[name]
    refine = bool((opts or {}).get("refine_body"))
    flow_files = bool((opts or {}).get("flows"))
    opts = None if opts is None else {k: v for k, v in opts.items() if k != "refine_body"}
    work = work_root / name
    work.mkdir(parents=True, exist_ok=True)
    row = {"variant": name, "status": "ok", "command": " ".join(sys.argv[1:]), "git": git_rev(),
           "date": dt.datetime.now().isoformat(timespec="seconds"), "refine_body": refine}
    if opts is None:
        scene_name, entry, truth = "skirt", _synthetic_entry(args), None
        row.update(distort=False, image_size="256x256", pose_noise_cm=0.0, masks="plate background", plates=True,
                   texture=name == "synthetic", body_joint_error_cm=0.0,
                   body_joint_angle_deg=0.0, body_jitter_cm=0.0)
        # the synthetic run uses the texture the scene hands it; image_anchor the default image references
        entry["fit"] = {**entry.get("fit", {}), "anchor_reference": "texture" if name == "synthetic" else "images"}
        if name == "image_anchor":
            if not (work / "data" / scene_name).is_dir():  # the synthetic run, mtimes and records kept
                shutil.rmtree(work)
                subprocess.run(["cp", "-a", str(work_root / "synthetic"), str(work)], check=True)
    else:
        src = work_root / "synthetic" / "data" / "skirt"
        scene_name = "skirtcap"
        scene = work / "data" / scene_name
        truth = work / "data" / f"{scene_name}.truth"
        if not (truth / "export.json").is_file():
            for d in (scene, truth):
                if d.exists():
                    shutil.rmtree(d)
            rec = run_export_capture(src, scene, seed=args.seed, threads=1, **opts)
        else:
            rec = json.loads((truth / "export.json").read_text())
        entry = scene_config_entry(yaml.safe_load((scene / "scene.yaml").read_text()))
        b = rec["sequences"]["walk"]["body_noise"]
        row.update(distort=opts["distort"], image_size=rec["options"]["image_size"],
                   pose_noise_cm=opts["pose_noise_cm"],
                   masks="temporal median (no plates)" if opts["masks"] == "none" else "parser-like, shipped",
                   cue_files=opts.get("cue_files", "pipeline"),
                   flows="network-like, shipped" if flow_files else "estimated (DIS)",
                   plates=False, texture=False, body_joint_error_cm=round(b["joint_error_cm"], 3),
                   body_joint_angle_deg=round(b["joint_angle_deg"], 3), body_jitter_cm=round(b["jitter_cm"], 3))
    exported = opts is not None
    (work / "config.yaml").write_text(yaml.safe_dump(_config(args, scene_name, entry, exported, refine, flow_files),
                                                     sort_keys=False))
    targets = [f"results/{scene_name}/walk/garment_poses.npz", f"results/{scene_name}/rig.npz",
               f"results/{scene_name}/walk/full/renders/novel_pose/dance"]
    if name == "synthetic":
        targets.insert(0, f"data/{scene_name}")
    rc, wall = _snakemake(work, targets, args.cores, work / "snakemake.log")
    row.update(_job_costs(work, scene_name))
    if rc != 0:
        row["status"] = f"workflow failed (rc {rc}, {work / 'snakemake.log'})"
        return row
    scene = work / "data" / scene_name
    if refine:
        row.update(_refined_body_errors(scene, work / "data" / f"{scene_name}.truth",
                                        work / "results" / scene_name / "walk" / "body"))
    s = _score(work, scene_name, scene, None if not exported else work / "data" / f"{scene_name}.truth")
    f = s["fit"]
    row.update(fit_frames=args.frames, fit_vertex_rmse_mm=round(1e3 * f["vertex_rmse_m"], 2),
               rig_floor_mm=round(1e3 * f["rig_floor_rmse_m"], 2),
               fit_ratio_to_floor=round(f["vertex_rmse_m"] / f["rig_floor_rmse_m"], 3))
    row.update(s["masks"])
    e = _summary_row(work / "score" / "metrics_summary.json")
    row.update(novel_pose_images=e["images"], novel_pose_psnr_db=round(e["psnr_db"], 2),
               novel_pose_iou=round(e["iou"], 4))
    return row


def scale_word(args) -> str:
    """DEMO where the runs have the demo's frames, training steps and render stride (config/config.yaml), else
    REDUCED (the simulation library and the field variants are reduced either way: see the line)."""
    demo = args.frames == 60 and args.steps == 600 and args.render_stride == 12
    return "the demo's frames, training steps and render stride (library and variants reduced)" if demo else "REDUCED"


def write_outputs(rows: list[dict], args, argv: list[str], started: str) -> None:
    out_csv, out_md = REPO / "benchmarks" / f"{args.name}.csv", REPO / "benchmarks" / f"{args.name}.md"
    with open(out_csv, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in COLUMNS})
    lines = [
        "# The demo skirt as a capture: synthetic scene against its export-capture variants",
        "",
        f"- written {started}; rows measured {', '.join(sorted(dict.fromkeys(r.get('date', '?')[:16] for r in rows)))} "
        f"(scored), code git {', '.join(dict.fromkeys(r.get('git', '?') for r in rows))}",
        f"- machine: {cpu_model()}, {os.cpu_count()} logical CPUs (shared with other jobs)",
        "- commands (rows kept in WORK/rows.json between invocations): "
        + "; ".join(f"`.venv/bin/python -m benchmarks.bench_capture {c}`"
                    for c in dict.fromkeys(r.get("command", " ".join(argv)) for r in rows)),
        f"- scale: {scale_word(args)}. The demo skirt scene (12 cameras, 8 train, 256x256, 3K-vertex garment) with {args.frames} "
        f"frames of walk (train) and {args.frames} of dance (novel pose); simulate library [sway] x 60 frames; field "
        f"variant full only, {args.steps} training steps (demo: 600); novel-pose renders of every "
        f"{args.render_stride}th dance frame x 12 cameras. Each variant: one Snakemake run (--cores {args.cores}) of "
        "the workflow to the walk fit, the rig and the novel-pose renders; exported scenes with "
        "cues/masks/background: temporal_median (no plates) and fit/anchor_reference: images (no texture).",
        "- scores: the pipeline's scorers against the held-back truth (OUT.truth of export-capture): "
        "`stages.fit_eval.run_fit_eval` on walk (vertex RMSE, ratio to the rig floor of the same run), "
        "`stages.evaluate.run_evaluate` on the dance renders (PSNR in the subject box, IoU of the rendered alpha; "
        "distorted variants in the working cameras of rule undistort, truth masks undistorted with the images)",
        "- jobs wall / CPU: summed over the last run of each job of the variant's workflow (Snakemake's benchmark "
        "files; the exported variants do not include rule synth, which made the scene they were exported from)",
        "- walk mask IoU: the masks the fit and the field used (the pipeline's, or the shipped parser-like ones "
        "as rule masks passes them on) against the true labels, in the working cameras, over every camera x frame "
        "of the folder used (the pipeline estimates the 8 training cameras; shipped masks cover all 12)",
        "- rig floor: that of the run's own rig (noisy body poses change the simulations of the captured motions, "
        "hence the rig); `image_anchor` is a copy of the `synthetic` run with fit, train_field and the render rerun: "
        "its jobs columns include the copied jobs",
        "- one run per variant, one export seed: runs are deterministic on one machine (README), so the differences "
        "are not run-to-run noise, but the spread over seeds and scenes is not measured",
        "- body noise: the exporter's own measure on walk (mean joint position error; mean local joint angle "
        "error; mean frame-to-frame change of the joint error, i.e. jitter), in export.json; with refine_body on, "
        "`given -> refined` (the same measure of results/<scene>/walk/body against the held-back truth)",
        "",
        "| variant | distortion | image | body joint error (cm) / angle (deg) / jitter (cm) | refine_body "
        "| masks | cue files | flows | plates | texture "
        "| walk mask IoU subject / garment | fit RMSE (mm) "
        "| rig floor (mm) | fit / floor | novel-pose PSNR (dB) | IoU | images | jobs | jobs wall (s) | jobs CPU (s) "
        "| status |",
        "|" + " --- |" * 10 + " ---: |" * 10 + " --- |",
    ]
    for r in rows:
        ref = {k: (f" -> {r[f'refined_{k}']}" if r.get(f"refined_{k}") not in (None, "") else "")
               for k in ("joint_error_cm", "joint_angle_deg", "jitter_cm")}
        r = dict(r, body_noise=f"{r.get('body_joint_error_cm', '')}{ref['joint_error_cm']} / "
                               f"{r.get('body_joint_angle_deg', '')}{ref['joint_angle_deg']} / "
                               f"{r.get('body_jitter_cm', '')}{ref['jitter_cm']}",
                 mask_iou=f"{r.get('mask_iou_person', '')} / {r.get('mask_iou_garment', '')}")
        lines.append("| " + " | ".join(str(r.get(k, "")) for k in (
            "variant", "distort", "image_size", "body_noise", "refine_body", "masks", "cue_files", "flows", "plates",
            "texture", "mask_iou",
            "fit_vertex_rmse_mm", "rig_floor_mm", "fit_ratio_to_floor", "novel_pose_psnr_db", "novel_pose_iou",
            "novel_pose_images", "jobs", "jobs_wall_s", "jobs_cpu_s", "status")) + " |")
    ok = {r["variant"]: r for r in rows if r["status"] == "ok"}
    causes = [("garment texture unused (fit anchor on image references)", "image_anchor", "synthetic"),
              ("no background plates (masks from a temporal median), given no texture", "crutchless", "image_anchor"),
              ("no plates and no texture together", "crutchless", "synthetic"),
              ("lens distortion + 4:3 images (undistorted by rule undistort)", "distort", "crutchless"),
              ("body-pose noise", "pose_noise", "crutchless"),
              ("parser-like masks shipped instead of the temporal-median masks", "parser", "crutchless"),
              ("body-pose noise, with the parser-like masks", "parser_pose_noise", "parser"),
              ("body-pose refinement (rule refine_body), temporal-median masks", "pose_noise_refined", "pose_noise"),
              ("body-pose refinement, parser-like masks", "parser_pose_noise_refined", "parser_pose_noise"),
              ("body-pose refinement, every degradation with parser-like masks", "capture_parser_refined",
               "capture_parser"),
              ("all degradations of `capture`", "capture", "synthetic"),
              ("all degradations, parser-like masks shipped (`capture_parser`)", "capture_parser", "synthetic")]
    att = [(what, a, b) for what, a, b in causes if a in ok and b in ok]
    if att:
        lines += ["", "Attribution: each cause as the difference of two variants that differ by it alone "
                  "(`a - b`: fit / floor, novel-pose PSNR, IoU, walk mask IoU of the subject):", ""]
        for what, a, b in att:
            ra, rb = ok[a], ok[b]
            d_fit = ra["fit_ratio_to_floor"] - rb["fit_ratio_to_floor"]
            d_psnr = ra["novel_pose_psnr_db"] - rb["novel_pose_psnr_db"]
            lines.append(f"- {what} (`{a}` - `{b}`): fit / floor {d_fit:+.3f}, PSNR {d_psnr:+.2f} dB, IoU "
                         f"{ra['novel_pose_iou'] - rb['novel_pose_iou']:+.4f}, mask IoU "
                         f"{ra['mask_iou_person'] - rb['mask_iou_person']:+.4f}")
        singles = [("crutchless", "synthetic"), ("distort", "crutchless"), ("pose_noise", "crutchless")]
        if all(a in ok and b in ok for a, b in singles) and "capture" in ok:
            tot = sum(ok[a]["fit_ratio_to_floor"] - ok[b]["fit_ratio_to_floor"] for a, b in singles)
            tot_p = sum(ok[a]["novel_pose_psnr_db"] - ok[b]["novel_pose_psnr_db"] for a, b in singles)
            lines.append(f"- sum of the single causes (plates + texture, distortion, pose noise): fit / floor "
                         f"{tot:+.3f}, PSNR {tot_p:+.2f} dB; against `capture` - `synthetic`: "
                         f"{ok['capture']['fit_ratio_to_floor'] - ok['synthetic']['fit_ratio_to_floor']:+.3f}, "
                         f"{ok['capture']['novel_pose_psnr_db'] - ok['synthetic']['novel_pose_psnr_db']:+.2f} dB "
                         "(the rest: interactions and run-to-run spread, not measured here)")
    twins = [(a, b) for a, b in TWINS.items() if a in ok and b in ok]
    if twins:
        lines += ["", "Cue files in the tools' formats against the same cues in the pipeline's formats (`a - b`; "
                  f"issue 47 asks for |PSNR| <= {TWIN_TOLERANCE['novel_pose_psnr_db']} dB and |fit / floor| <= "
                  f"{TWIN_TOLERANCE['fit_ratio_to_floor']}):", ""]
        for a, b in twins:
            d = {k: ok[a][k] - ok[b][k] for k in TWIN_TOLERANCE}
            within = all(abs(d[k]) <= tol for k, tol in TWIN_TOLERANCE.items())
            lines.append(f"- `{a}` ({ok[a].get('cue_files')}) - `{b}`: PSNR {d['novel_pose_psnr_db']:+.2f} dB, fit / floor "
                         f"{d['fit_ratio_to_floor']:+.3f}, IoU {ok[a]['novel_pose_iou'] - ok[b]['novel_pose_iou']:+.4f}, "
                         f"mask IoU {ok[a]['mask_iou_person'] - ok[b]['mask_iou_person']:+.4f}: "
                         + ("within" if within else "OUTSIDE") + " the tolerance")
    missing = [v for v in VARIANTS if v not in {r["variant"] for r in rows}]
    if missing:
        lines += ["", f"Not run in this benchmark run: {', '.join(missing)}."]
    out_md.write_text("\n".join(lines) + "\n")


def earlier_rows(name: str) -> dict[str, dict]:
    """The rows of the committed benchmarks/<name>.csv as run_variant returns them, each with the commit, date and
    command of its run as benchmarks/<name>.md states them (its header: one commit, the commands)."""
    import re

    md = (REPO / "benchmarks" / f"{name}.md").read_text()
    git = re.search(r"code git ([^\s,]+)", md)
    written = re.search(r"- written (\S+);", md)
    cmds = re.findall(r"`\.venv/bin/python -m benchmarks\.bench_capture ([^`]+)`", md)
    out = {}
    with open(REPO / "benchmarks" / f"{name}.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            row = {}
            for k, v in r.items():
                if v in ("True", "False"):
                    row[k] = v == "True"
                elif v == "":
                    row[k] = None
                else:
                    try:
                        row[k] = int(v) if re.fullmatch(r"-?\d+", v) else float(v)
                    except ValueError:
                        row[k] = v
            if row.get("flows") is None:
                row["flows"] = "estimated (DIS)"
            if row.get("cue_files") is None:
                row["cue_files"] = "pipeline"
            v = row["variant"]
            row["git"] = git.group(1) if git else "?"
            row["date"] = written.group(1) if written else "?"
            row["command"] = next((c for c in cmds if v in re.split(r"[ ,]", c)), "?")
            out[v] = row
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_capture", description=__doc__.split("\n\n")[0])
    p.add_argument("--work", required=True, help="scratch folder of the runs (never results/ of the repository)")
    p.add_argument("--variants", default="synthetic,capture", help=f"comma list of {list(VARIANTS)}")
    p.add_argument("--frames", type=int, default=16, help="frames of walk and of dance (demo: 60)")
    p.add_argument("--steps", type=int, default=200, help="field training steps (demo: 600)")
    p.add_argument("--render-stride", type=int, default=4, help="render every n-th dance frame")
    p.add_argument("--cores", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="export-capture seed")
    p.add_argument("--name", default="capture", help="output stem: benchmarks/<name>.md, .csv (default: %(default)s)")
    p.add_argument("--earlier-rows", action="store_true",
                   help="without WORK/rows.json, start from the rows of the committed benchmarks/<name>.csv (each "
                        "keeps the commit and command of its run, from <name>.md)")
    p.add_argument("--report-only", action="store_true",
                   help="only rewrite <name>.md / .csv from WORK/rows.json (the rows of earlier invocations)")
    args = p.parse_args(argv)
    names = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in names if v not in VARIANTS]
    if bad:
        p.error(f"unknown variants {bad}; choose from {list(VARIANTS)}")
    have_synthetic = (Path(args.work) / "synthetic" / "data" / "skirt").is_dir()
    if not args.report_only and names and names[0] != "synthetic" and not have_synthetic:
        p.error("the other variants need the synthetic run first (put synthetic first)")
    work = Path(args.work).resolve()
    if work == (REPO / "results").resolve() or REPO.resolve() in work.parents and "results" in work.parts:
        p.error("--work must be a scratch folder, not the repository's results/")
    started = dt.datetime.now().isoformat(timespec="seconds")
    rows = []
    prev = work / "rows.json"
    done = {r["variant"]: r for r in json.loads(prev.read_text())} if prev.is_file() else {}
    if args.earlier_rows and not done:
        done = earlier_rows(args.name)
    if args.report_only:
        if not done:
            p.error(f"{prev}: no rows to report")
        for v, r in done.items():  # rows of runs before the date was kept: the time they were scored
            m = work / v / "score" / "metrics_summary.json"
            if "date" not in r and m.is_file():
                r["date"] = dt.datetime.fromtimestamp(m.stat().st_mtime).isoformat(timespec="seconds")
        write_outputs([done[k] for k in VARIANTS if k in done], args, argv, started)
        return 0
    for v in names:
        print(f"[bench_capture] {v} ...", flush=True)
        row = run_variant(args, v, work)
        done[v] = row
        print(f"[bench_capture] {v}: {row}", flush=True)
        prev.write_text(json.dumps(list(done.values()), indent=1))
        rows = [done[k] for k in VARIANTS if k in done]
        write_outputs(rows, args, argv, started)
    return 0


if __name__ == "__main__":
    sys.exit(main())
