"""Stage ``fit``: garment poses from 2D cues (paper §3.2, DESIGN.md §8).

For one sequence ``<seq>`` of ``data/<scene>`` it reads the rig (``results/<scene>/rig.npz``,
:func:`anidress_core.io.rig.read_rig`), the cameras of ``<seq>`` (or of its copy undistorted to pinholes by rule
undistort: :func:`anidress_core.io.scene.sequence_source`), the body posed per frame (the occluder), and per
training camera (``scene.yaml`` ``cameras.train``, optionally an evenly spread subset) and frame the cues
(:class:`anidress_core.io.fit_cues.CueReader`: masks, normals, flows and, with L_anchor on, the images). Where the
settings need them (:func:`anidress_core.fit.plan_fit`) it also reads the template (``template.npz``: the ``body``
start, the UVs), the garment texture, the stiffness ensemble (``results/<scene>/sim_ensemble/seq-<seq>.npz``, rule
simulate_ensemble: :func:`ensemble_transforms`, :func:`ensemble_prior_scales`) and the body motions of the rig's
simulated sequences (``motions_dir``, rule motions: the ``nearest`` baseline's database). It writes
``garment_poses.npz`` (:mod:`anidress_core.io.garment_poses`): transforms, verts, the weighted loss and every
unweighted term ``loss_<term>`` per frame, with the loss variant that ran, every weight as used and the plan's notes
in the header; ``meta['frame_notes']`` says per frame what the fit did about defective cues
(:attr:`anidress_core.fit.FrameFit.notes`), which pose the ``nearest`` baseline kept, and on the last frame of each
window refined jointly its loss before and after.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from .. import fit as FIT
from ..fit import ensemble as ENS
from ..io import files
from ..io.fit_cues import CueReader
from ..io.garment_poses import save_garment_poses
from ..io.rig import read_rig
from ..io.scene import (garment_texture_path, load_body, load_sequence_motion, read_scene, scene_cameras,
                        sequence_source)
from ..io.template import read_template

__all__ = ["select_views", "run_fit"]

log = logging.getLogger("anidress.fit")


def simulation_database(art, motions_dir: str | os.PathLike | None, body):
    """The simulation database of the ``nearest`` baseline (:func:`anidress_core.fit.nearest.make_database`):
    every simulated sequence of the rig (``rig.npz`` ``sequences``) with the body it was simulated
    on, ``<motions_dir>/<name>.npz`` (rule motions), posed by the scene's body model."""
    from ..fit.nearest import make_database
    from ..io.body_motion import read_motion

    if motions_dir is None:
        raise ValueError("the method 'nearest' needs the simulated body motions (motions_dir: "
                         "results/<scene>/motions, rule motions)")
    seqs = {}
    for name in art.sequences:
        path = Path(motions_dir) / f"{name}.npz"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: body motion of the simulated sequence {name} not found (rule motions; "
                                    "needed by the nearest baseline)")
        m = read_motion(path)
        G = art.transforms_of(name).double()
        if m.poses.shape[0] != G.shape[0]:
            raise files.ArtifactError(f"{path}: {m.poses.shape[0]} frames, the rig has {G.shape[0]} for {name}")
        joints = body.pose(m.poses, m.Rh, m.Th, m.shapes).transforms.double()
        seqs[name] = (G.cpu(), joints, m.fps)
    return make_database(seqs)  # on the CPU (the candidates are moved to the fit's device)


def select_views(train: Sequence[str], count: int) -> list[str]:
    """``count`` training cameras spread evenly over the list (0 or >= len: all of them)."""
    train = list(train)
    if count <= 0 or count >= len(train):
        return train
    idx = sorted({int(np.floor(i * len(train) / count + 0.5)) % len(train) for i in range(count)})
    return [train[i] for i in idx]


def run_fit(scene_dir: str | os.PathLike, seq: str, rig_npz: str | os.PathLike, template_npz: str | os.PathLike,
            masks_dir: str | os.PathLike, flows_dir: str | os.PathLike | None,
            normals_dir: str | os.PathLike | None, params: Mapping, out_npz: str | os.PathLike,
            ablation: str | None = None, progress: bool = True, cue_source: str = "",
            undistorted_dir: str | os.PathLike | None = None, motions_dir: str | os.PathLike | None = None,
            body_dir: str | os.PathLike | None = None, starts: torch.Tensor | None = None,
            sim_ensemble_npz: str | os.PathLike | None = None) -> dict:
    """Fit the garment poses of sequence ``seq`` and write ``out_npz`` (see the module docstring).

    params: the config section ``fit`` (:meth:`anidress_core.fit.FitConfig.from_config`); ablation: None (the
    section's ``loss``) or a loss variant (:data:`anidress_core.fit.VARIANTS`) to run instead. motions_dir: the
    ``nearest`` baseline's body motions (:func:`simulation_database`). body_dir: the sequence's body poses refined
    by rule refine_body, read instead of its smpl/. starts: (T, B, 4, 4) a start for every frame (an oracle for
    benchmarks, e.g. the rig floor). sim_ensemble_npz: the ensemble's mean simulation of ``seq``
    (:func:`ensemble_transforms`). Returns the header metadata written.
    """
    t_start = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    cfg = FIT.FitConfig.from_config(params, ablation)
    if int(params.get("threads", 0) or 0) > 0:
        torch.set_num_threads(int(params["threads"]))
    dev_name = params.get("device", "auto")
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if dev_name == "auto" else dev_name)
    # 1. cameras (training views, optionally a subset) of the images as the fit reads them (pinhole)
    train = (info.get("cameras") or {}).get("train")
    if not train:
        raise files.ArtifactError(f"{scene_dir / 'scene.yaml'}: no cameras/train list")
    names = select_views(train, int(params.get("views", 0)))
    for cam in names:  # fail early, naming the file
        if not (Path(masks_dir) / cam / "000000.png").is_file():
            raise FileNotFoundError(f"{Path(masks_dir) / cam / '000000.png'}: mask of camera {cam} frame 0 not found")
    src = sequence_source(scene_dir, seq, undistorted_dir, info)
    cams = scene_cameras(scene_dir, seq, names, info, seq_dir=src).to(device=device)
    # 2. rig, body (the occluder) per frame
    art = read_rig(rig_npz, device=device, dtype=torch.float64)
    rig = FIT.RigParts.make(art.model.rest, art.model.weights, art.model.bone_centres,
                            torch.as_tensor(art.faces, device=device))
    body = load_body(scene_dir, info)
    motion = load_sequence_motion(scene_dir, seq, info["fps"], body_dir)
    posed = body.pose(motion.poses, motion.Rh, motion.Th, motion.shapes)
    T = int(posed.vertices.shape[0])
    if T == 0:
        raise files.ArtifactError(f"{scene_dir / seq / 'smpl'}: no frames")
    if int(params.get("frames", 0) or 0) > 0:  # a prefix of the sequence (quick runs, benchmarks)
        T = min(T, int(params["frames"]))
    # 3. the plan: the settings and the artifacts, each file read only where the settings need it
    sim_name = f"seq-{seq}"

    def body_start():  # the template skinned by the body at frame 0
        tpl = read_template(template_npz)
        if tpl.verts.shape != tuple(rig.rest.shape):
            raise files.ArtifactError(f"{template_npz}: template has {tpl.verts.shape[0]} vertices, the rig "
                                      f"{rig.rest.shape[0]}")
        return tpl.skin(posed.transforms[:1].double()).to(device)

    def rig_sim():  # the rig's simulation of the observed motion
        return art.transforms_of(sim_name).double().to(device), f"rig transforms of the simulated sequence {sim_name}"

    plan = FIT.plan_fit(
        cfg, rig, FIT.Views.from_cameras(cams), T, params.get("first_frame_init", "auto"), body_start=body_start,
        ensemble=lambda: ensemble_transforms(sim_ensemble_npz, art, T, device),
        rig_sim=rig_sim if sim_name in art.sequences else None,
        spread=lambda: ensemble_prior_scales(sim_ensemble_npz, T, cfg.prior_spread_floor).to(device),
        texture=lambda: garment_texture(scene_dir, info, template_npz, rig.faces),
        database=lambda: (simulation_database(art, motions_dir, body), posed.transforms.double().cpu(),
                          float(info["fps"])),
        own=sim_name, starts=None if starts is None else torch.as_tensor(starts).double().to(device),
        normals=normals_dir is not None, rig_name=f"{rig_npz} (simulated sequences {sorted(art.sequences)})")
    cfg, w = plan.cfg, plan.cfg.weights
    log.info("fit %s/%s (loss %s, method %s): %d frames, %d views %s, %d vertices, %d bones, weights %s, device %s; %s",
             scene_dir.name, seq, cfg.loss, cfg.method, T, len(names), names, rig.rest.shape[0], rig.weights.shape[1],
             dataclasses.asdict(w), device, {k: v for k, v in plan.notes.items() if v})
    # 4. fit, the cues of frame t + 1 read while frame t is fitted
    reader = CueReader(cams, masks_dir, None if w.normal == 0 else normals_dir, None if w.flow == 0 else flows_dir,
                       posed.vertices.double(), body.faces, plan.views, device, num_frames=T,
                       seq_dir=src if w.anchor > 0 else None)
    t_fit, c_fit = time.perf_counter(), time.process_time()
    try:
        res = FIT.fit_sequence(plan, reader.cues, reader.flow, progress=progress, log=log)
    finally:
        reader.close()
    wall_fit, cpu_fit = time.perf_counter() - t_fit, time.process_time() - c_fit
    # 5. write
    curve = np.full((T, max(len(r.curve) for r in res)), np.nan)
    for t, r in enumerate(res):
        curve[t, :len(r.curve)] = r.curve
    tf = torch.stack([r.transforms for r in res])
    vs = torch.stack([r.verts.detach() for r in res])
    if not (bool(torch.isfinite(tf).all()) and bool(torch.isfinite(vs).all())):  # fit_frame guarantees it
        raise RuntimeError(f"fit {seq}: non-finite poses")
    meta = {
        "method": cfg.method, "loss": cfg.loss, "description": FIT.VARIANTS[cfg.loss].description,
        "weights": dataclasses.asdict(w), "config": dataclasses.asdict(cfg), "params": dict(params),
        "scene": scene_dir.name, "sequence": seq, "cameras": names, "masks_dir": str(masks_dir),
        "normals_dir": None if normals_dir is None else str(normals_dir),
        "flows_dir": None if flows_dir is None else str(flows_dir), "cue_source": cue_source, "rig": str(rig_npz),
        "frames": T, "device": str(device), "wall_fit_s": wall_fit, "wall_total_s": time.perf_counter() - t_start,
        "fps": T / wall_fit, "cpu_fit_s": cpu_fit, "load_average": list(os.getloadavg()),
        "torch_threads": torch.get_num_threads(), "bad_cue_values": reader.bad_values, **plan.notes,
        # what was done about bad cues (anidress_core.fit.FrameFit.notes: views dropped, frames kept at their
        # start, NaN pixels, no flow), the nearest baseline's picks, the windows refined jointly
        "frame_notes": {str(t): r.notes for t, r in enumerate(res) if r.notes},
    }
    save_garment_poses(
        out_npz, tf.float().cpu().numpy(), vs.float().cpu().numpy(), rig.faces.cpu().numpy().astype(np.int64),
        loss=np.array([r.loss for r in res]),
        terms={k: np.array([r.terms[k] for r in res]) for k in FIT.TERM_NAMES},
        weights=dataclasses.asdict(w),
        iterations=np.array([r.iterations for r in res], np.int64),
        converged=np.array([r.converged for r in res], bool),
        wall_s=np.array([r.terms["wall_s"] for r in res]),
        flow_targets=np.array([r.terms["flow_targets"] for r in res], np.int64), curve=curve,
        config=dict(params), meta=meta)
    log.info("fit %s/%s (%s): %d frames in %.1f s (%.2f frames/s), mean %.1f iterations, %d/%d converged",
             scene_dir.name, seq, cfg.loss, T, wall_fit, T / wall_fit, float(np.mean([r.iterations for r in res])),
             sum(r.converged for r in res), T)
    return meta


def garment_texture(scene_dir: Path, info: Mapping, template_npz, faces: torch.Tensor):
    """The template's face UVs (F, 3, 2) and the scene's garment texture (Ht, Wt, 3), float64 on the device of the
    rig's ``faces`` (F, 3), and a line naming it: L_anchor's references with ``fit/anchor_reference: texture``."""
    path = garment_texture_path(scene_dir, info)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: fit/anchor_reference is 'texture' but the garment has no texture "
                                f"(set garment_texture in {scene_dir / 'scene.yaml'}, or anchor_reference: images)")
    tpl = read_template(template_npz)
    if tpl.face_uv is None or not np.array_equal(np.asarray(tpl.faces), faces.cpu().numpy()):
        raise files.ArtifactError(f"{template_npz}: no UVs, or faces that are not the rig's")
    tex = files.read_image(path)
    return (torch.as_tensor(np.asarray(tpl.face_uv), device=faces.device).double(),
            torch.as_tensor(tex, device=faces.device).double(), f"{path} ({tex.shape[1]}x{tex.shape[0]})")


def _ensemble(path: str | os.PathLike | None, use):
    """``use`` of the ensemble's mean simulation at ``path`` (:func:`anidress_core.io.sim.read_sim`, rule
    simulate_ensemble), its ValueError an ArtifactError naming the file."""
    from ..io.sim import read_sim

    if path is None or not Path(path).is_file():
        raise FileNotFoundError(f"{path}: fit/prior_reference 'sim_ensemble' needs the ensemble's mean simulation of "
                                "the observed motion (rule simulate_ensemble: "
                                "results/<scene>/sim_ensemble/seq-<seq>.npz); or set fit/prior_reference: sim")
    s = read_sim(path, members=False)
    try:
        return use(s)
    except ValueError as e:
        raise files.ArtifactError(f"{path}: {e}") from e


def ensemble_transforms(path: str | os.PathLike | None, art, frames: int | None, device) -> tuple[torch.Tensor, str]:
    """:func:`anidress_core.fit.ensemble.ensemble_transforms` of the ensemble's mean at ``path`` for the rig ``art``,
    and a line saying what it is."""
    return _ensemble(path, lambda s: (ENS.ensemble_transforms(art.model, s.frames, frames, device),
                                      f"{path}: {ENS.ensemble_note(s.meta)}, rig transforms fitted to it"))


def ensemble_prior_scales(path: str | os.PathLike, frames: int, floor: float) -> torch.Tensor:
    """:func:`anidress_core.fit.ensemble.ensemble_prior_scales` of the spread stored with the ensemble's mean at
    ``path`` (none: rerun rule simulate_ensemble, or set fit/prior_spread_floor: null)."""

    def scales(s):
        if s.spread is None:
            raise ValueError("no 'spread' (the members' spread about their mean; written by rule simulate_ensemble "
                             "since fit/prior_spread_floor exists: rerun it), or set fit/prior_spread_floor: null")
        return ENS.ensemble_prior_scales(s.spread, frames, floor)

    return _ensemble(path, scales)
