"""The ``anidress`` command: every pipeline stage, runnable and timeable on its own.

The Snakemake scripts in workflow/scripts call the same stage functions.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from . import __version__

log = logging.getLogger("anidress.cli")


def _cmd_synth(args: argparse.Namespace) -> None:
    from .config import load_config, scene_config
    from .stages.synth import run_synth

    cfg = load_config(args.config)
    scene = scene_config(cfg, args.scene)
    if not scene["synthetic"]:
        raise SystemExit(f"scene {args.scene!r} is not synthetic (scenes/{args.scene}/synthetic is false)")
    out = Path(args.out) if args.out else Path("data") / args.scene
    run_synth(scene, args.scene, out, threads=args.threads, progress=not args.quiet)
    print(out)


def _cmd_template(args: argparse.Namespace) -> None:
    from .io.scene import load_body, read_scene
    from .stages.template import run_template

    scene_dir = Path(args.scene_dir)
    info = read_scene(scene_dir)
    src = args.template or (scene_dir / info["garment_template"] if info.get("garment_template") else None)
    kind = args.kind or info.get("garment_kind")
    if kind is None:
        raise ValueError(f"{scene_dir / 'scene.yaml'}: no garment_kind; pass --kind skirt|dress")
    out = Path(args.out)
    run_template(src, kind, load_body(scene_dir, info), args.vertices, out / "template.ply", out / "template.npz")
    print(out / "template.npz")


def _cmd_motion(args: argparse.Namespace) -> None:
    from .config import load_config
    from .stages.simulate import run_motion

    run_motion(args.name, args.scene_dir, load_config(args.config)["simulate"], args.out, body_dir=args.body)
    print(args.out)


def _cmd_simulate(args: argparse.Namespace) -> None:
    from .config import load_config
    from .stages.simulate import run_simulate

    sim = load_config(args.config)["simulate"]
    if args.ensemble:  # as rule simulate_ensemble: the members' mean
        from .stages.simulate import run_simulate_ensemble

        run_simulate_ensemble(args.template, args.motion, args.scene_dir, sim["cloth"], sim["ensemble_bend_stiffness"],
                              args.out, progress=not args.quiet, settle_frames=sim["ensemble_settle_frames"])
    else:
        run_simulate(args.template, args.motion, args.scene_dir, sim["cloth"], args.out, progress=not args.quiet)
    print(args.out)


def _cues_cfg(args: argparse.Namespace) -> dict:
    from .config import load_config

    return load_config(args.config)["cues"]


def _cmd_rig(args: argparse.Namespace) -> None:
    from .config import load_config
    from .stages.rig import run_rig

    params = load_config(args.config)["rig"]
    for key in ("bones", "iters", "nnz"):
        if getattr(args, key) is not None:
            params[key] = getattr(args, key)
    run_rig(args.template, args.sims, params, args.out)
    print(args.out)


def _cmd_rig_decompose(args: argparse.Namespace) -> None:
    from .stages.rig import run_rig_decompose

    model = run_rig_decompose(args.seq, args.out, bones=args.bones, iters=args.iters, nnz=args.nnz,
                              smooth=args.smooth, seed=args.seed)
    print(f"{args.out}: {model.num_bones} bones, RMSE {model.rmse:.6g}")


def _cmd_masks(args: argparse.Namespace) -> None:
    from .stages.cues import run_masks

    cfg = dict(_cues_cfg(args)["masks"])
    if args.method:
        cfg["method"] = args.method
    run_masks(args.scene_dir, args.seq, args.out, cfg, template_npz=args.template, cameras=args.cameras,
              threads=args.threads, progress=not args.quiet, undistorted_dir=args.undistorted)
    print(args.out)


def _cmd_flows(args: argparse.Namespace) -> None:
    from .stages.cues import run_flows

    cfg = dict(_cues_cfg(args)["flows"])
    if args.method:
        cfg["method"] = args.method
    if args.no_prior:
        cfg["prior"] = False
    run_flows(args.scene_dir, args.seq, args.masks, args.out, cfg, template_npz=args.template, cameras=args.cameras,
              threads=args.threads, progress=not args.quiet, undistorted_dir=args.undistorted)
    print(args.out)


def _cmd_normals(args: argparse.Namespace) -> None:
    from .stages.cues import run_normals

    run_normals(args.scene_dir, args.seq, args.normals, args.out, cameras=args.cameras,
                undistorted_dir=args.undistorted)
    print(args.out)


def _cmd_cues_eval(args: argparse.Namespace) -> None:
    from .io.files import write_text
    from .stages.cues import evaluate_cues, format_table

    res = evaluate_cues(args.scene_dir, args.seq, args.masks, args.flows, args.normals, cameras=args.cameras)
    rows = [{"metric": k, "value": v} for k, v in res.items()]
    print(format_table(rows, ["metric", "value"]))
    if args.out:
        write_text(args.out, "metric,value\n" + "".join(f"{k},{v}\n" for k, v in res.items()))


def _cmd_fit(args: argparse.Namespace) -> None:
    from .config import load_config, scene_section
    from .stages.fit import run_fit

    scene = Path(args.scene_dir)
    params = scene_section(load_config(args.config), "fit", scene.name)  # as the workflow's rule fit
    if args.views is not None:
        params["views"] = args.views
    if args.threads:
        params["threads"] = args.threads
    if args.anchor_reference:
        params["anchor_reference"] = args.anchor_reference
    src = Path(args.undistorted) if args.undistorted else scene / args.seq  # shipped normals: undistorted too
    normals = None if args.no_normals else (args.normals or (str(src / "normals")
                                                             if (src / "normals").is_dir() else None))
    run_fit(scene, args.seq, args.rig, args.template, args.masks, args.flows, normals, params, args.out,
            ablation=args.ablation, progress=not args.quiet, cue_source="command line",
            undistorted_dir=args.undistorted, motions_dir=args.motions, body_dir=args.body,
            sim_ensemble_npz=args.sim_ensemble)
    print(args.out)


def _cmd_fit_eval(args: argparse.Namespace) -> None:
    from .stages.fit_eval import run_fit_eval

    fits = {}
    for item in args.fits:
        name, _, path = item.rpartition("=")
        fits[name or Path(path).parent.name] = path
    run_fit_eval(args.scene_dir, args.seq, args.rig, fits, args.out, samples=args.samples)
    print(args.out)


def _field_cfg(path: str) -> dict:
    from .config import load_config

    return load_config(path)


def _cmd_train(args: argparse.Namespace) -> None:
    import torch

    from .metrics.image import load_lpips
    from .stages.field import run_train

    cfg = _field_cfg(args.config)
    params = {k: cfg["field"][k] for k in ("model", "priors", "sampler", "train", "render")}
    if args.steps:
        params["train"] = {**params["train"], "steps": args.steps}
    if args.threads:
        torch.set_num_threads(args.threads)
    lpips = load_lpips(**cfg["metrics"]["lpips"]) if params["train"]["lpips_weight"] > 0 else None
    run_train(args.scene_dir, args.seq, args.variant, args.masks, args.out, params, template_npz=args.template,
              rig_npz=args.rig, garment_poses_npz=args.poses, lpips=lpips, device=args.device or cfg["field"]["device"],
              progress=not args.quiet, undistorted_dir=args.undistorted, body_dir=args.body)
    print(args.out)


def _cmd_render(args: argparse.Namespace) -> None:
    import torch

    from .stages.field import run_render
    from .io.scene import read_scene

    cfg = _field_cfg(args.config)
    params = {k: cfg["field"][k] for k in ("sampler", "render")}
    if args.threads:
        torch.set_num_threads(args.threads)
    info = read_scene(args.scene_dir)
    cams = {"test": info["cameras"]["test"], "train": info["cameras"]["train"],
            "all": info["cameras"]["train"] + info["cameras"]["test"]}.get(args.cameras)
    if cams is None:
        cams = args.cameras.split(",")
    stride = args.frame_stride or cfg["field"]["render"]["frame_stride"]
    if args.library_motion:
        name = args.library_name or Path(args.library_motion).stem
        run_render(args.field, args.scene_dir, args.out, params, cameras=cams, template_npz=args.template,
                   rig_npz=args.rig, library_motion_npz=args.library_motion, library_name=name, frame_stride=stride,
                   device=args.device or cfg["field"]["device"], progress=not args.quiet,
                   undistorted_dir=args.undistorted)
    else:
        if not args.seq:
            raise ValueError("render: give --seq SEQ (a captured sequence) or --library-motion NPZ")
        run_render(args.field, args.scene_dir, args.out, params, seq=args.seq, cameras=cams,
                   template_npz=args.template, rig_npz=args.rig, garment_poses_npz=args.poses, frame_stride=stride,
                   device=args.device or cfg["field"]["device"], progress=not args.quiet,
                   use_occupancy=not args.no_occupancy, cull_joints=not args.no_joint_culling,
                   undistorted_dir=args.undistorted, body_dir=args.body)
    print(args.out)


def _cmd_evaluate(args: argparse.Namespace) -> None:
    from .metrics.image import load_dists, load_lpips
    from .stages.evaluate import run_evaluate

    cfg = _field_cfg(args.config)
    renders = []
    for item in args.renders:
        parts = item.split(":", 2)
        if len(parts) != 3 or parts[0] not in ("novel_view", "novel_pose"):
            raise ValueError(f"evaluate: renders are KIND:SEQ:DIR with KIND novel_view|novel_pose, got {item!r}")
        renders.append(tuple(parts))
    m = cfg["metrics"]
    summary = args.summary or str(Path(args.out).with_name("metrics_summary.json"))
    undistorted = dict(item.split("=", 1) for item in args.undistorted or [])
    masks = dict(item.split("=", 1) for item in args.masks or [])
    bodies = dict(item.split("=", 1) for item in args.body or [])
    run_evaluate(args.scene_dir, renders, args.out, summary, m, lpips=load_lpips(**m["lpips"]),
                 dists=load_dists(**m["dists"]), progress=not args.quiet, undistorted=undistorted, masks=masks,
                 bodies=bodies)
    print(args.out)


def _cmd_undistort(args: argparse.Namespace) -> None:
    from .stages.undistort import run_undistort

    rec = run_undistort(args.scene_dir, args.seq, args.out, threads=args.threads, progress=not args.quiet)
    print(f"{args.out}: cameras {', '.join(rec['distorted']) or 'none'} undistorted "
          f"({rec['frames']} frames, {rec['files']} files)")


def _report_import(rec: dict) -> None:
    """The imported scene's check (validate_scene) and the config entry to run it with."""
    import yaml

    from .stages.validate import format_summary, validate_scene

    summary = validate_scene(rec["scene_dir"])
    print(format_summary(summary))
    name = Path(rec["scene_dir"]).name
    print(f"the pipeline's config entry for it (scenes/{name}; data/{name} is where the workflow reads it):")
    print(yaml.safe_dump({"scenes": {name: rec["config_entry"]}}, sort_keys=False).rstrip())
    bare = [q for q, v in summary["sequences"].items()
            if not v["masks"] and not (Path(rec["scene_dir"]) / q / "backgrounds").is_dir()]
    if bare:  # rule masks estimates them; the default plates do not exist (validate_scene in the workflow says so)
        print(f"sequences {', '.join(bare)} ship neither masks nor background plates: run the workflow with "
              "cues/masks/background: temporal_median (a global setting; the default 'plate' stops at validate_scene)")


def _cmd_import_zju(args: argparse.Namespace) -> None:
    from .stages.import_capture import run_import_zju

    labels = tuple(int(x) for x in args.garment_labels.split(",") if x.strip())
    rec = run_import_zju(args.src, args.dst, sequence=args.sequence, frames=args.frames, garment=args.garment,
                         garment_kind=args.garment_kind, garment_texture=args.garment_texture, garment_labels=labels,
                         body_model=args.body_model, params=args.params, masks=args.masks, train=args.train,
                         test=args.test, role=args.role, fps=args.fps, link=args.link, height=args.height,
                         threads=args.threads)
    print(f"{rec['scene_dir']}/{rec['sequence']}: {len(rec['cameras'])} cameras x {len(rec['frames'])} frames "
          f"(masks from {', '.join(rec['masks']) or 'none'})")
    _report_import(rec)


def _cmd_import_easymocap(args: argparse.Namespace) -> None:
    from .stages.import_capture import run_import_easymocap

    labels = tuple(int(x) for x in args.garment_labels.split(",") if x.strip())
    rec = run_import_easymocap(args.src, args.dst, sequence=args.sequence, frames=args.frames, smpl=args.smpl,
                               person_id=args.person_id, max_gap=args.max_gap, cameras=args.cameras, masks=args.masks,
                               mask_format=args.mask_format, garment=args.garment, garment_kind=args.garment_kind,
                               garment_texture=args.garment_texture, garment_labels=labels,
                               body_model=args.body_model, train=args.train, test=args.test, role=args.role,
                               fps=args.fps, link=args.link, height=args.height, threads=args.threads)
    print(f"{rec['scene_dir']}/{rec['sequence']}: {len(rec['cameras'])} cameras x {len(rec['frames'])} frames "
          f"(masks {'from ' + rec['masks'] if rec['masks'] else 'none'})")
    _report_import(rec)


def _cmd_export_capture(args: argparse.Namespace) -> None:
    from .stages.export_capture import run_export_capture

    rec = run_export_capture(args.src, args.out, distort=args.distort, pose_noise_cm=args.pose_noise_cm,
                             masks=args.masks, image_size=args.image_size, seed=args.seed, normals=args.normals,
                             truth=args.truth, threads=args.threads, flows=args.flows, cue_files=args.cue_files)
    for seq, r in rec["sequences"].items():
        b = r["body_noise"]
        print(f"{rec['scene_dir']}/{seq}: {len(r['cameras'])} cameras x {r['frames']} frames at "
              f"{rec['options']['image_size']}, distortion {'on' if rec['options']['distort'] else 'off'}, body joint "
              f"error {b['joint_error_cm']:.2f} cm (angles {b['joint_angle_deg']:.2f} deg, jitter {b['jitter_cm']:.2f} "
              f"cm/frame), masks {rec['options']['masks']}"
              + (f" (IoU person {r['mask_iou']['person']:.3f})" if r.get("mask_iou") else ""))
    print(f"held back for scoring: {rec['truth_dir']} (export.json, gt/, exact smpl/)")
    _report_import(rec)


def _cmd_refine_body(args: argparse.Namespace) -> None:
    from .body.refine import ADAM_SETTINGS, RefineConfig
    from .stages.refine_body import run_refine_body

    cfg = RefineConfig(**ADAM_SETTINGS) if args.method == "adam" else RefineConfig()
    if args.cameras not in ("all", "train"):
        args.cameras = [c.strip() for c in args.cameras.split(",") if c.strip()]
    rec = run_refine_body(args.scene_dir, args.sequence, args.out, masks_dir=args.masks,
                          undistorted_dir=args.undistorted, chunk=args.chunk,
                          max_frames=args.max_frames, cfg=cfg, threads=args.threads, cameras=args.cameras)
    print(f"{args.out}/smpl: {rec['frames']} frames x {len(rec['cameras'])} cameras refined in {rec['seconds']:.1f} s "
          f"({rec['seconds_per_frame']:.2f} s/frame); body silhouette IoU {rec['body_iou_before']:.3f} -> "
          f"{rec['body_iou_after']:.3f}")


def _cmd_validate(args: argparse.Namespace) -> None:
    from .stages.validate import format_summary, run_validate

    summary = run_validate(args.scene_dir, args.out, images="all" if args.all_images else "ends")
    print(format_summary(summary))
    if args.out:
        print(args.out)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="anidress",
        description="AniDress pipeline stages (the Snakemake workflow runs the same functions).",
    )
    p.add_argument("--version", action="version", version=f"anidress {__version__}")
    p.add_argument("--log", help="also write the log to this file")
    sub = p.add_subparsers(dest="command", metavar="STAGE", required=True)

    s = sub.add_parser("synth", help="generate a synthetic scene with full ground truth (data/<scene>/)")
    s.add_argument("--config", default="config/config.yaml", help="pipeline config (default: %(default)s)")
    s.add_argument("--scene", required=True, help="scene name, a key of `scenes` in the config")
    s.add_argument("--out", help="output folder (default: data/<scene>)")
    s.add_argument("--threads", type=int, default=2, help="writer threads (default: %(default)s)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)

    s = sub.add_parser("template", help="clean, remesh and attach a garment template (template.ply/.npz)")
    s.add_argument("scene_dir", help="data/<scene> (scene.yaml, body model, garment/template.obj)")
    s.add_argument("--template", help="garment mesh (default: the scene's garment/template.obj; "
                                      "none: the procedural garment of --kind)")
    s.add_argument("--kind", choices=["skirt", "dress"], help="garment kind (default: from scene.yaml)")
    s.add_argument("--vertices", type=int, default=3000, help="target vertex count (default: %(default)s)")
    s.add_argument("-o", "--out", required=True, help="output folder")
    s.set_defaults(func=_cmd_template)

    s = sub.add_parser("motion", help="write a body motion to simulate (seq-<sequence>, lib-<name>, amass-<stem>)")
    s.add_argument("name")
    s.add_argument("scene_dir")
    s.add_argument("--config", default="config/config.yaml")
    s.add_argument("-o", "--out", required=True, help="output .npz")
    s.add_argument("--body", help="seq-<sequence>: its body poses refined by `anidress refine-body`, read instead "
                                  "of its smpl/")
    s.set_defaults(func=_cmd_motion)

    s = sub.add_parser("simulate", help="simulate the garment template on a body motion (sim/<motion>.npz)")
    s.add_argument("template", help="template.npz from `anidress template`")
    s.add_argument("motion", help="motion .npz from `anidress motion`")
    s.add_argument("scene_dir", help="data/<scene> (for its body model)")
    s.add_argument("--config", default="config/config.yaml", help="cloth parameters: simulate/cloth")
    s.add_argument("--ensemble", action="store_true", help="simulate once per simulate/ensemble_bend_stiffness and "
                                                           "ensemble_settle_frames and write the members' mean "
                                                           "(rule simulate_ensemble)")
    s.add_argument("-o", "--out", required=True, help="output .npz")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_simulate)
    s = sub.add_parser("masks", help="estimate body/garment masks of a sequence (<out>/<cam>/<frame>.png)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="sequence name")
    s.add_argument("-o", "--out", required=True, help="output folder (results/<scene>/<seq>/masks)")
    s.add_argument("--template", help="garment template.npz (the shape prior); none: tight clothes, labels 0/1")
    s.add_argument("--config", default="config/config.yaml", help="settings: cues/masks (default: %(default)s)")
    s.add_argument("--method", choices=["prior", "colour", "grabcut"], help="override cues/masks/method")
    s.add_argument("--cameras", default="train", choices=["train", "all"])
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--undistorted", help="the sequence undistorted by `anidress undistort` (needed when its "
                                         "cameras have lens distortion)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_masks)

    s = sub.add_parser("flows", help="forward optical flow t-1 -> t of a sequence (<out>/<cam>/<frame>.exr)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="sequence name")
    s.add_argument("--masks", required=True, help="the sequence's masks (bound the processed region)")
    s.add_argument("--template", help="garment template.npz (flow prior: posed body + skinned garment; "
                                      "none: the body alone)")
    s.add_argument("--no-prior", action="store_true", help="no body/garment flow initialisation (cues/flows/prior)")
    s.add_argument("-o", "--out", required=True, help="output folder (results/<scene>/<seq>/flows)")
    s.add_argument("--config", default="config/config.yaml", help="settings: cues/flows (default: %(default)s)")
    s.add_argument("--method", choices=["dis_ultrafast", "dis_fast", "dis_medium", "deepflow", "tvl1", "farneback"],
                   help="override cues/flows/method")
    s.add_argument("--cameras", default="train", choices=["train", "all"])
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--undistorted", help="the sequence undistorted by `anidress undistort` (needed when its "
                                         "cameras have lens distortion)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_flows)

    s = sub.add_parser("normals", help="check a sequence's shipped normal maps and record them (or the skip)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="sequence name")
    s.add_argument("--normals", help="normal maps folder (default: none, the stage is skipped)")
    s.add_argument("-o", "--out", required=True, help="output record (results/<scene>/<seq>/normals.json)")
    s.add_argument("--cameras", default="train", choices=["train", "all"])
    s.add_argument("--undistorted", help="the sequence undistorted by `anidress undistort` (needed when its "
                                         "cameras have lens distortion)")
    s.set_defaults(func=_cmd_normals)

    s = sub.add_parser("cues-eval", help="compare masks / flows / normals with the synthetic ground truth")
    s.add_argument("scene_dir", help="data/<scene> (a synthetic scene with gt/)")
    s.add_argument("seq", help="sequence name")
    s.add_argument("--masks", help="estimated masks folder")
    s.add_argument("--flows", help="estimated flows folder")
    s.add_argument("--normals", help="normal maps folder (e.g. data/<scene>/<seq>/normals)")
    s.add_argument("--cameras", default="train", choices=["train", "all"])
    s.add_argument("--out", help="also write the table as CSV (metric,value)")
    s.set_defaults(func=_cmd_cues_eval)

    s = sub.add_parser("fit", help="fit the garment poses of a sequence to its cues (garment_poses.npz)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="sequence name")
    s.add_argument("--rig", required=True, help="rig.npz (rule rig)")
    s.add_argument("--template", required=True, help="template.npz (for --first-frame-init body)")
    s.add_argument("--masks", required=True, help="masks folder <cam>/<frame>.png (labels 0/1/2)")
    s.add_argument("--flows", help="flows folder <cam>/<frame>.exr (X, Y, valid); none: no flow loss")
    s.add_argument("--normals", help="normal maps folder (default: <scene>/<seq>/normals if present)")
    s.add_argument("--no-normals", action="store_true", help="normal loss off")
    from .fit.variants import VARIANTS as FIT_VARIANTS

    s.add_argument("--ablation", choices=list(FIT_VARIANTS),
                   help="run this loss variant instead of fit/loss (anidress_core.fit.variants.VARIANTS)")
    s.add_argument("--views", type=int, help="use N training cameras spread evenly (default: fit/views)")
    s.add_argument("--anchor-reference", choices=["images", "texture"],
                   help="L_an's references (default: fit/anchor_reference, or the scene's scenes/<scene>/fit)")
    s.add_argument("--config", default="config/config.yaml",
                   help="settings: fit, then scenes/<scene directory name>/fit (default: %(default)s)")
    s.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's)")
    s.add_argument("-o", "--out", required=True, help="output garment_poses.npz")
    s.add_argument("--undistorted", help="the sequence undistorted by `anidress undistort` (needed when its "
                                         "cameras have lens distortion)")
    s.add_argument("--motions", help="the simulated body motions results/<scene>/motions (rule motions): the "
                                     "database of the nearest baseline (--ablation nearest)")
    s.add_argument("--body", help="the sequence's body poses refined by `anidress refine-body` (OUT of it), read "
                                  "instead of its smpl/")
    s.add_argument("--sim-ensemble", help="`anidress simulate --ensemble` of seq-<seq>: L_prior's reference, needed "
                                          "with fit/prior_reference sim_ensemble (the default)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_fit)

    s = sub.add_parser("fit-eval", help="fitted garments against the synthetic ground truth (fit_metrics.csv)")
    s.add_argument("scene_dir", help="data/<scene> (synthetic, with gt/meshes.npz)")
    s.add_argument("seq", help="sequence name")
    s.add_argument("fits", nargs="+", help="garment_poses.npz files, optionally NAME=PATH")
    s.add_argument("--rig", required=True, help="rig.npz the fits used")
    s.add_argument("--samples", type=int, default=20000, help="surface samples per mesh (Chamfer)")
    s.add_argument("-o", "--out", required=True, help="output CSV")
    s.set_defaults(func=_cmd_fit_eval)

    s = sub.add_parser("train", help="train the pose-driven radiance field of a sequence (field.pt)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="training sequence")
    s.add_argument("--variant", choices=["full", "body_only"], default="full")
    s.add_argument("--masks", required=True, help="masks folder <cam>/<frame>.png of the training cameras")
    s.add_argument("--template", help="template.npz (garment scenes)")
    s.add_argument("--rig", help="rig.npz (variant full of a garment scene)")
    s.add_argument("--poses", help="garment_poses.npz of the sequence (variant full)")
    s.add_argument("--config", default="config/config.yaml", help="field and metrics settings")
    s.add_argument("--steps", type=int, help="override field/train/steps")
    s.add_argument("--device", help="cpu | cuda (default: field/device)")
    s.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's)")
    s.add_argument("-o", "--out", required=True, help="output field.pt (field.pt.ckpt beside it while training)")
    s.add_argument("--undistorted", help="the sequence undistorted by `anidress undistort` (needed when its "
                                         "cameras have lens distortion)")
    s.add_argument("--body", help="the sequence's body poses refined by `anidress refine-body` (OUT of it), read "
                                  "instead of its smpl/")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_train)

    s = sub.add_parser("render", help="render a trained field: a captured sequence or a library motion")
    s.add_argument("field", help="field.pt")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("--seq", help="captured sequence to render (its smpl/ motion and cameras)")
    s.add_argument("--poses", help="garment_poses.npz of --seq (variant full)")
    s.add_argument("--library-motion", help="results/<scene>/motions/lib-<name>.npz (garment poses from the rig)")
    s.add_argument("--library-name", help="the rig's sequence name (default: the motion file stem)")
    s.add_argument("--cameras", default="test", help="test | train | all | comma-separated names")
    s.add_argument("--template", help="template.npz (garment scenes)")
    s.add_argument("--rig", help="rig.npz (variant full)")
    s.add_argument("--frame-stride", type=int, default=0, help="every n-th frame (default: field/render)")
    s.add_argument("--no-occupancy", action="store_true", help="ablation: sample the whole grid box")
    s.add_argument("--no-joint-culling", action="store_true", help="ablation: every joint for every sample")
    s.add_argument("--config", default="config/config.yaml")
    s.add_argument("--device", help="cpu | cuda")
    s.add_argument("--threads", type=int, default=0)
    s.add_argument("-o", "--out", required=True, help="output folder (rgb/, alpha/, depth/, render.json)")
    s.add_argument("--undistorted", help="--seq's (or the training sequence's) folder by `anidress undistort` "
                                         "(needed when its cameras have lens distortion)")
    s.add_argument("--body", help="--seq's body poses refined by `anidress refine-body`, read instead of its smpl/")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_render)

    s = sub.add_parser("evaluate", help="image metrics of renders against the ground truth, or a capture's "
                                        "images under the pipeline's masks (metrics.csv)")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("renders", nargs="+", help="KIND:SEQ:DIR with KIND novel_view | novel_pose")
    s.add_argument("--config", default="config/config.yaml", help="metrics settings (LPIPS / DISTS weights)")
    s.add_argument("-o", "--out", required=True, help="output metrics.csv")
    s.add_argument("--summary", help="output summary JSON (default: metrics_summary.json beside --out)")
    s.add_argument("--undistorted", action="append", metavar="SEQ=DIR",
                   help="a sequence undistorted by `anidress undistort` (one per sequence with lens distortion)")
    s.add_argument("--masks", action="append", metavar="SEQ=DIR",
                   help="the pipeline's masks of a sequence without gt/masks (a capture): images are compared under "
                        "them (mask_source pipeline); without either an image is not scored")
    s.add_argument("--body", action="append", metavar="SEQ=DIR",
                   help="a sequence's body poses refined by `anidress refine-body` (the scoring box of a sequence "
                        "without gt/meshes.npz)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_evaluate)
    s = sub.add_parser("rig", help="garment rigging model from a scene's simulations (rig.npz)")
    s.add_argument("template", help="template.npz from `anidress template`")
    s.add_argument("sims", nargs="+", help="sim/<motion>.npz files from `anidress simulate`")
    s.add_argument("--config", default="config/config.yaml", help="SSDR parameters: rig (default: %(default)s)")
    s.add_argument("--bones", type=int, help="override rig/bones")
    s.add_argument("--iters", type=int, help="override rig/iters")
    s.add_argument("--nnz", type=int, help="override rig/nnz")
    s.add_argument("-o", "--out", required=True, help="output rig.npz")
    s.set_defaults(func=_cmd_rig)

    s = sub.add_parser("rig-decompose", help="SSDR of one mesh sequence, file to file (Dem Bones' layout)")
    s.add_argument("seq", help="SEQ.npz with rest (V,3), faces (F,3), frames (T,V,3)")
    s.add_argument("--bones", type=int, default=25, help="bones B (default: %(default)s)")
    s.add_argument("--iters", type=int, default=50, help="global iterations (default: %(default)s)")
    s.add_argument("--nnz", type=int, default=8, help="most bones per vertex (default: %(default)s)")
    s.add_argument("--smooth", type=float, default=1e-4, help="weights smoothness (default: %(default)s)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("-o", "--out", required=True,
                   help="OUT.npz: weights (B,V), transforms (T,B,4,4) with x = sum_b W[b,i] (M[t,b] [rest_i; 1])")
    s.set_defaults(func=_cmd_rig_decompose)
    s = sub.add_parser("undistort", help="undistort a sequence with lens distortion to pinhole working cameras")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("seq", help="sequence name")
    s.add_argument("-o", "--out", required=True, help="output folder (results/<scene>/<seq>/undistorted)")
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_undistort)

    s = sub.add_parser("import-zju", help="convert a ZJU-MoCap capture (annots.npy, params/, mask_cihp/) to a scene")
    s.add_argument("src", help="the capture folder (annots.npy, camera image folders, params/ or new_params/, "
                               "mask/ and/or mask_cihp/)")
    s.add_argument("dst", help="scene folder to write (data/<scene>); an existing captured scene gets one more "
                               "sequence")
    s.add_argument("--sequence", help="sequence name (default: the capture folder's name)")
    s.add_argument("--frames", help="ims entries: START:STOP[:STEP] or a comma list (default: all)")
    s.add_argument("--role", default="train", choices=["train", "novel_pose"], help="the sequence's role")
    s.add_argument("--garment", help="garment template mesh (.obj); none: a tight-clothed scene")
    s.add_argument("--garment-kind", choices=["skirt", "dress"], help="the garment's kind (with --garment)")
    s.add_argument("--garment-texture", help="the garment template's texture image (optional)")
    s.add_argument("--garment-labels", default="6,12",
                   help="CIHP labels of mask_cihp/ that are the garment (default: %(default)s, dress and skirt)")
    s.add_argument("--body-model", help="SMPL model file you own (.npz/.pkl) or a mannequin npz "
                                        "(default: the bundled mannequin)")
    s.add_argument("--height", type=float, default=1.7,
                   help="the bundled mannequin's height in m (default: %(default)s)")
    s.add_argument("--params", help="body parameter folder: params, new_params or a path (default: params/, "
                                    "else new_params/)")
    s.add_argument("--masks", default="auto", choices=["auto", "mask", "mask_cihp", "both", "none"],
                   help="which ZJU mask folders make the masks (default: every one present)")
    s.add_argument("--train", help="training cameras: names, source folder names or 0-based indices, comma-separated")
    s.add_argument("--test", help="test cameras (default: the cameras not training)")
    s.add_argument("--fps", type=float, required=True,
                   help="the capture's frame rate, frames/s (required: annots.npy does not store it; Neural Body's "
                        "ZJU-MoCap sequences are usually taken as 50)")
    s.add_argument("--link", default="symlink", choices=["symlink", "hardlink", "copy"],
                   help="how images reach the scene (default: %(default)s)")
    s.add_argument("--threads", type=int, default=2, help="files placed / masks converted at a time")
    s.set_defaults(func=_cmd_import_zju)

    s = sub.add_parser("import-easymocap", help="convert an EasyMocap capture (intri/extri.yml, images/, "
                                                "output-smpl-3d/smpl/) to a scene")
    s.add_argument("src", help="the capture folder (intri.yml, extri.yml, images/<cam>/, smpl/ or "
                               "output-smpl-3d/smpl/ or output/smpl/)")
    s.add_argument("dst", help="scene folder to write (data/<scene>); an existing captured scene gets one more "
                               "sequence")
    s.add_argument("--sequence", help="sequence name (default: the capture folder's name)")
    s.add_argument("--frames", help="image frames by index: START:STOP[:STEP] or a comma list (default: all)")
    s.add_argument("--role", default="train", choices=["train", "novel_pose"], help="the sequence's role")
    s.add_argument("--smpl", help="body parameter folder (default: the first of smpl/, output-smpl-3d/smpl/, "
                                  "output/smpl/)")
    s.add_argument("--person-id", type=int, help="the EasyMocap person id to take when files hold several people")
    s.add_argument("--max-gap", type=int, default=0, help="interpolate up to this many frames without the person")
    s.add_argument("--cameras", help="a subset of intri.yml's cameras (names or 0-based indices, comma-separated)")
    s.add_argument("--masks", help="mask folder <cam>/<frame:06d>.png (relative to SRC or absolute)")
    s.add_argument("--mask-format", default="person", choices=["person", "cihp", "labels", "schp"],
                   help="person: non-zero is the person; cihp: CIHP part labels; labels: 0/1/2; schp: EasyMocap's "
                        "mask-schp (<frame>_<i>.png silhouettes, CIHP labels in the sibling mask-schp-parsing/) "
                        "(default: %(default)s)")
    s.add_argument("--garment", help="garment template mesh (.obj); none: a tight-clothed scene")
    s.add_argument("--garment-kind", choices=["skirt", "dress"], help="the garment's kind (with --garment)")
    s.add_argument("--garment-texture", help="the garment template's texture image (optional)")
    s.add_argument("--garment-labels", default="6,12", help="CIHP labels that are the garment (default: %(default)s)")
    s.add_argument("--body-model", help="SMPL model file you own (.npz/.pkl) or a mannequin npz "
                                        "(default: the bundled mannequin)")
    s.add_argument("--height", type=float, default=1.7,
                   help="the bundled mannequin's height in m (default: %(default)s)")
    s.add_argument("--train", help="training cameras: names or 0-based indices, comma-separated")
    s.add_argument("--test", help="test cameras (default: the cameras not training)")
    s.add_argument("--fps", type=float, default=30.0, help="the capture's frame rate (not in EasyMocap's files; "
                                                           "default %(default)s, an assumption: give the real one)")
    s.add_argument("--link", default="symlink", choices=["symlink", "hardlink", "copy"],
                   help="how images reach the scene (default: %(default)s)")
    s.add_argument("--threads", type=int, default=2, help="files placed / masks converted at a time")
    s.set_defaults(func=_cmd_import_easymocap)

    s = sub.add_parser("export-capture", help="write a synthetic scene as a capture would be (distorted non-square "
                                              "images, noisy body poses, no plates, texture or gt/)")
    s.add_argument("src", help="a synthetic scene (data/<scene>)")
    s.add_argument("out", help="the capture-like scene to write (a new folder); its truth goes to OUT.truth")
    s.add_argument("--distort", action=argparse.BooleanOptionalAction, default=True,
                   help="apply lens distortion to the images and write it as dist_<cam> (default: on)")
    s.add_argument("--pose-noise-cm", type=float, default=2.0,
                   help="mean joint position error of the written body poses, cm (0: exact; default %(default)s)")
    s.add_argument("--masks", default="none", choices=["none", "parser"],
                   help="none: no masks/; parser: labels with a human parser's errors (default: %(default)s)")
    s.add_argument("--image-size", help="WxH of the written images (crop / pad about the centre; default: the "
                                        "width padded to 4:3)")
    s.add_argument("--seed", type=int, default=0, help="seed of every random choice (default: %(default)s)")
    s.add_argument("--normals", action=argparse.BooleanOptionalAction, default=True,
                   help="keep the scene's predicted normals, warped (default: on)")
    s.add_argument("--flows", action=argparse.BooleanOptionalAction, default=False,
                   help="ship forward flows as an optical-flow network gives them (the true ones, blurred and noisy), "
                        "for cues/flows/method: files (default: off)")
    s.add_argument("--cue-files", default="pipeline", choices=["pipeline", "easymocap_sapiens_raft", "lip_png_kitti"],
                   help="formats of the shipped masks / normals / flows: the pipeline's (labels, EXR, EXR), or "
                        "EasyMocap's mask-schp (silhouettes + SCHP CIHP parsing) / Sapiens .npy / RAFT .flo, or SCHP "
                        "LIP / 8-bit normal PNG / KITTI flow PNG (default: %(default)s)")
    s.add_argument("--truth", help="where the held-back truth goes (default: OUT.truth beside OUT)")
    s.add_argument("--threads", type=int, default=2, help="files written at a time")
    s.set_defaults(func=_cmd_export_capture)

    s = sub.add_parser("refine-body", help="refine a sequence's body poses (smpl/) against its label masks")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("sequence", help="the sequence name")
    s.add_argument("out", help="folder for smpl/<frame>.json and refine_body.json")
    s.add_argument("--masks", help="label masks <cam>/<frame:06d>.png (default: <scene>/<sequence>/masks)")
    s.add_argument("--undistorted", help="the sequence undistorted by rule undistort (cameras with distortion)")
    s.add_argument("--chunk", type=int, default=16, help="frames optimised together (default: %(default)s)")
    s.add_argument("--max-frames", type=int, help="only the first N frames")
    s.add_argument("--method", default="lm", choices=["lm", "adam"],
                   help="optimiser: Levenberg-Marquardt or Adam (default: %(default)s)")
    s.add_argument("--cameras", default="all", help="views refined against: all, train or a comma-separated list "
                   "(the workflow: cues/cameras; default: %(default)s)")
    s.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    s.set_defaults(func=_cmd_refine_body)

    s = sub.add_parser("validate", help="check a scene folder (cameras, frames, images, body, garment) before a run")
    s.add_argument("scene_dir", help="data/<scene>")
    s.add_argument("-o", "--out", help="write the summary JSON here (the workflow: results/<scene>/scene_check.json)")
    s.add_argument("--all-images", action="store_true",
                   help="decode every image (default: every header, first and last frame of each camera decoded)")
    s.set_defaults(func=_cmd_validate)
    return p


def main(argv: list[str] | None = None) -> int:
    from .stages import setup_logging

    args = build_parser().parse_args(argv)
    setup_logging(args.log)
    try:
        args.func(args)
    except (ValueError, FileNotFoundError) as e:
        log.error("%s", e)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
