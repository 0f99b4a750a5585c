"""Stages `motions` and `simulate` (DESIGN.md §4).

``motions``: every captured sequence of a scene (its EasyMocap ``smpl/`` folder), the
procedural library and any configured AMASS files, each written as
``motions/<name>.npz`` (poses (T, 72), Rh, Th (T, 3), shapes, fps;
:mod:`anidress_core.io.body_motion`).
``simulate``: one garment simulation per motion, ``sim/<name>.npz`` holding
``frames`` (T, V, 3) float32 and per-frame stability statistics, with the cloth
parameters in the header (:mod:`anidress_core.io.sim`).
``simulate_ensemble``: a captured sequence's motion simulated once per bending stiffness of
``simulate/ensemble_bend_stiffness`` and settle length of ``simulate/ensemble_settle_frames``,
``sim_ensemble/seq-<sequence>.npz`` holding the mean of the members' frames and their spread
(the fit's L_prior follows it, ``fit/prior_reference: sim_ensemble``).
"""
from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .. import sim
from ..body.motions import Motion, make_motion, resample
from ..io.body_motion import read_motion, write_motion
from ..io.motion import read_amass_npz
from ..io.scene import load_body, load_sequence_motion, read_scene
from ..io.sim import SimSequence, write_sim
from ..io.template import read_template

__all__ = ["motion_names", "run_motion", "run_simulate", "run_simulate_ensemble"]

log = logging.getLogger("anidress.simulate")

CAPTURED, LIBRARY, AMASS = "seq-", "lib-", "amass-"


def motion_names(scene_info: dict, sim_cfg: dict) -> list[str]:
    """Names of the motions a scene simulates: seq-<sequence>, lib-<motion>, amass-<file stem>."""
    names = [CAPTURED + s["name"] for s in scene_info["sequences"]]
    names += [LIBRARY + m for m in sim_cfg["library"]]
    names += [AMASS + Path(p).stem for p in sim_cfg["amass"]]
    return names


def run_motion(name: str, scene_dir: str | os.PathLike, sim_cfg: dict, out_npz: str | os.PathLike,
               body_dir: str | os.PathLike | None = None) -> Motion:
    """Write one body motion to simulate (see :func:`motion_names` for the naming).

    body_dir: a captured sequence's poses refined by rule refine_body, read instead of its smpl/
    (:func:`anidress_core.io.scene.load_sequence_motion`).
    """
    info = read_scene(scene_dir)
    if name.startswith(CAPTURED):
        m = load_sequence_motion(scene_dir, name[len(CAPTURED):], info["fps"], body_dir)
    elif name.startswith(LIBRARY):
        m = make_motion(name[len(LIBRARY):], sim_cfg["library_frames"], sim_cfg["library_fps"], seed=0,
                        body=load_body(scene_dir, info))
    elif name.startswith(AMASS):
        stem = name[len(AMASS):]
        paths = [p for p in sim_cfg["amass"] if Path(p).stem == stem]
        if not paths:
            raise ValueError(f"motion {name!r}: no AMASS file with stem {stem!r} in the config")
        d = read_amass_npz(paths[0])
        from ..body.model import global_orient_to_rh_th

        body = load_body(scene_dir, info)
        poses = torch.as_tensor(d["poses"], dtype=torch.float32)
        Rh, Th = global_orient_to_rh_th(poses[:, :3], torch.as_tensor(d["trans"], dtype=torch.float32),
                                        body.joints_rest[0])
        poses = poses.clone()
        poses[:, :3] = 0
        m = Motion(name=stem, fps=float(d["fps"]), poses=poses, Rh=Rh, Th=Th, shapes=torch.zeros(10))
        m = resample(m, sim_cfg["library_fps"])
    else:
        raise ValueError(f"motion {name!r}: expected a name starting with {CAPTURED}, {LIBRARY} or {AMASS}")
    write_motion(out_npz, m, config=sim_cfg, meta={"name": name, "frames": int(m.poses.shape[0])})
    return m


class _Inputs(NamedTuple):
    """What every simulation of one motion reads: the template, the motion, the scene's body posed by it."""

    tpl: object
    motion: object
    body: object
    posed: object


def _inputs(template_npz: str | os.PathLike, motion_npz: str | os.PathLike, scene_dir: str | os.PathLike) -> _Inputs:
    motion = read_motion(motion_npz)
    body = load_body(scene_dir)
    return _Inputs(read_template(template_npz), motion, body,
                   body.pose(motion.poses, motion.Rh, motion.Th, motion.shapes))


def _simulate(x: _Inputs, params: sim.ClothParams, progress: bool, what: str) -> sim.SimResult:
    """The cloth solver on ``x`` with ``params``, logged (``what``: the run's name in the log)."""
    log.info("simulating %s: %d frames, %d vertices", what, x.motion.poses.shape[0], x.tpl.verts.shape[0])
    res = sim.simulate(x.tpl.verts, x.tpl.faces, x.tpl.band, x.tpl.body_weights, x.body.v_template, x.body.faces,
                       x.body.weights, x.posed.transforms, x.motion.fps, params, progress=progress)
    st = res.stats
    log.info("%s: %d frames, %d vertices, max stretch %.3f (p99 %.3f), max penetration %.1f mm, NaN %d, "
             "%d recoveries, %.1f s", what, res.frames.shape[0], res.frames.shape[1],
             float(st.max_stretch.max()), float(st.p99_stretch.max()), 1e3 * float(st.max_penetration_m.max()),
             int(st.nan_count.sum()), len(st.recoveries), st.wall_s)
    return res


def run_simulate(template_npz: str | os.PathLike, motion_npz: str | os.PathLike, scene_dir: str | os.PathLike,
                 cloth_cfg: dict, out_npz: str | os.PathLike, progress: bool = True) -> sim.SimResult:
    """Simulate the scene's garment template on one body motion and write ``sim/<motion>.npz``."""
    x = _inputs(template_npz, motion_npz, scene_dir)
    params = sim.ClothParams(**cloth_cfg)
    res = _simulate(x, params, progress, x.motion.name)
    st = res.stats
    write_sim(out_npz, SimSequence(
        frames=res.frames.astype(np.float32), faces=x.tpl.faces, fps=x.motion.fps, max_stretch=st.max_stretch,
        p99_stretch=st.p99_stretch, max_penetration_m=st.max_penetration_m, nan_count=st.nan_count,
        substeps=st.substeps, meta={"motion": x.motion.name, "params": dataclasses.asdict(params),
                                    "recoveries": st.recoveries, "wall_s": st.wall_s}), config=cloth_cfg)
    return res


def run_simulate_ensemble(template_npz: str | os.PathLike, motion_npz: str | os.PathLike,
                          scene_dir: str | os.PathLike, cloth_cfg: dict, bend_stiffness: list[float],
                          out_npz: str | os.PathLike, progress: bool = True,
                          settle_frames: list[int] | None = None) -> SimSequence:
    """Simulate one motion once per bending stiffness (J) and settle length and write the members' mean to
    ``out_npz``.

    The cloth of a capture is not the simulator's material, and its state when the capture starts is
    unknown: the garment's motion is estimated by the mean over an ensemble of bending stiffnesses
    (after the stiffness ensemble of Pan et al. 2022, SIGGRAPH; the mean as the fit's L_prior reference
    is ours, studies/fit section 16), each started by ``settle_frames`` frames of blending from the
    T-pose into the first pose (``ClothParams.settle_frames``; several lengths give several states at
    frame 0, studies/fit section 18; None or [] = ``cloth_cfg``'s alone). Members: every stiffness at
    every settle length. Every other cloth parameter is ``cloth_cfg``'s. ``frames`` (T, V, 3) is the
    per-vertex mean over the members, ``spread`` (T, V) the members' RMS distance from it (the fit's
    L_prior pulls less where they disagree, ``fit/prior_spread_floor``), ``members`` (M, T, V, 3) every
    member's frames (for studies; the fit reads the mean and the spread); the stability statistics per
    frame are the worst member's; the header's ``members`` lists each member's stiffness, settle
    length, NaN count, recoveries and wall time. Raises when a member's frames hold a non-finite value
    (no member is dropped silently).
    """
    if not bend_stiffness:
        raise ValueError("simulate_ensemble: simulate/ensemble_bend_stiffness is empty")
    base = sim.ClothParams(**cloth_cfg)
    settles = [int(n) for n in settle_frames] if settle_frames else [base.settle_frames]
    if any(n < 0 for n in settles):
        raise ValueError(f"simulate_ensemble: simulate/ensemble_settle_frames must be >= 0, got {settles}")
    x = _inputs(template_npz, motion_npz, scene_dir)
    tpl, motion = x.tpl, x.motion
    frames, stats, members = [], [], []
    for k in bend_stiffness:
        for n in settles:
            params = dataclasses.replace(base, bend_stiffness=float(k), settle_frames=n)
            res = _simulate(x, params, progress, f"{motion.name} at bending stiffness {k:g} J, {n} settle frames")
            if not np.isfinite(res.frames).all():
                raise FloatingPointError(f"{motion_npz}: the simulation with bending stiffness {k:g} J, {n} settle "
                                         f"frames has non-finite vertices ({int(res.stats.nan_count.sum())} NaN "
                                         "counted)")
            frames.append(res.frames.astype(np.float64))
            stats.append(res.stats)
            members.append({"bend_stiffness": float(k), "settle_frames": n,
                            "nan_count": int(res.stats.nan_count.sum()), "recoveries": res.stats.recoveries,
                            "wall_s": res.stats.wall_s})
    worst = lambda name: np.max(np.stack([getattr(st, name) for st in stats]), axis=0)  # noqa: E731
    X = np.stack(frames)  # (M, T, V, 3)
    mean = X.mean(axis=0)
    out = SimSequence(frames=mean.astype(np.float32), faces=tpl.faces, fps=motion.fps,
                      spread=np.sqrt(((X - mean) ** 2).sum(-1).mean(0)).astype(np.float32),
                      members=X.astype(np.float32),
                      max_stretch=worst("max_stretch"), p99_stretch=worst("p99_stretch"),
                      max_penetration_m=worst("max_penetration_m"), nan_count=worst("nan_count"),
                      substeps=worst("substeps"),
                      meta={"motion": motion.name, "params": dataclasses.asdict(base),
                            "ensemble": "mean over bend_stiffness x settle_frames", "members": members,
                            "wall_s": float(sum(m["wall_s"] for m in members))})
    write_sim(out_npz, out, config={"cloth": cloth_cfg, "ensemble_bend_stiffness": [float(k) for k in bend_stiffness],
                                    "ensemble_settle_frames": settles})
    return out
