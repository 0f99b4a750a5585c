"""Stages `fit` and `fit_eval`: garment poses from 2D cues, measured against ground truth.

``fit`` (paper §3.2, DESIGN.md §8) reads, for one sequence ``<seq>`` of ``data/<scene>``, the rig
(``results/<scene>/rig.npz``, :func:`anidress_core.io.rig.read_rig`), the cameras of ``<seq>`` (or of its copy
undistorted to pinholes by rule undistort: :func:`anidress_core.io.scene.sequence_source`), the body posed per frame
(the occluder), and per training camera (``scene.yaml`` ``cameras.train``, optionally an evenly spread subset) and
frame the cues (:class:`CueReader`): ``<masks_dir>/<cam>/<frame:06d>.png`` (labels, garment = 2),
``<normals_dir>/<cam>/<frame:06d>.exr`` (camera-space unit normals), ``<flows_dir>/<cam>/<frame:06d>.exr``
(channels X, Y, valid: forward flow frame-1 -> frame on frame-1's grid) and, with L_anchor on, the images. Where
the settings need them (:func:`anidress_core.fit.plan_fit`) it also reads the template (``template.npz``: the
``body`` start, the UVs), the garment texture, the stiffness ensemble (``results/<scene>/sim_ensemble/seq-<seq>.npz``,
rule simulate_ensemble: :func:`ensemble_transforms`, :func:`ensemble_prior_scales`) and the body motions of the
rig's simulated sequences (``motions_dir``, rule motions: the ``nearest`` baseline's database). It writes
``garment_poses.npz`` (:mod:`anidress_core.io.garment_poses`): transforms, verts, the weighted loss and every
unweighted term ``loss_<term>`` per frame, with the loss variant that ran, every weight as used and the plan's
notes in the header; ``meta['frame_notes']`` says per frame what the fit did about defective cues
(:attr:`anidress_core.fit.FrameFit.notes`), which pose the ``nearest`` baseline kept, and on the last frame of
each window refined jointly its loss before and after.

``fit_eval`` writes ``fit_metrics.csv``: per method and frame, vertex RMSE against the ground-truth garment carried
onto the template's vertices, the rig's floor on that frame, Chamfer distance and normal consistency against the
ground-truth mesh, temporal jitter and acceleration error (see :mod:`anidress_core.metrics.mesh`).
"""
from __future__ import annotations

import csv
import dataclasses
import functools
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
from ..io.cue_files import read_flow
from ..io.garment_poses import load_garment_poses, save_garment_poses
from ..io.rig import read_rig
from ..io.scene import (garment_texture_path, image_path, load_body, load_sequence_motion, read_scene, scene_cameras,
                        sequence_source)
from ..io.template import read_template
from ..synth import LABEL_GARMENT

__all__ = ["select_views", "CueReader", "gt_correspondence", "gt_template_vertices", "run_fit", "load_garment_poses",
           "run_fit_eval", "FIT_METRIC_COLUMNS"]

log = logging.getLogger("anidress.fit")

FIT_METRIC_COLUMNS = (
    "method", "frame", "vertex_rmse_m", "rig_floor_rmse_m", "chamfer_m", "rig_floor_chamfer_m", "reprojection_px",
    "rig_floor_reprojection_px", "normal_consistency",
    "jitter_m", "gt_jitter_m", "accel_error_m", "loss", *(f"loss_{k}" for k in FIT.TERM_NAMES), "iterations", "wall_s",
)


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


class CueReader:
    """Reads one frame's cues for the selected cameras (the only file access of the fit).

    cams: the selected cameras; masks_dir: label maps ``<cam>/<t:06d>.png``; normals_dir, flows_dir: EXR folders
    of the same layout, or None (that term off); body_verts (T, Vb, 3) and body_faces: the posed body, rasterised
    as the occluder; views: :class:`anidress_core.fit.Views` of ``cams``; num_frames: the last frame read ahead;
    seq_dir: the sequence folder whose images L_anchor reads (None: not read). ``cues(t)`` ->
    :class:`anidress_core.fit.FrameCues`, ``flow(t)`` -> (flow, valid) of t-1 -> t or None; ``close()`` stops the
    helper thread, which reads the files of frame t + 1 while frame t is fitted. Non-finite normals and flow
    vectors are left out (counted in ``bad_values``).
    """

    def __init__(self, cams, masks_dir, normals_dir, flows_dir, body_verts, body_faces, views, device,
                 num_frames: int | None = None, seq_dir: Path | None = None):
        from concurrent.futures import ThreadPoolExecutor

        self.cams, self.views, self.device, self.num_frames = cams, views, device, num_frames
        self.dirs = {"masks": masks_dir, "normals": normals_dir, "flows": flows_dir, "images": seq_dir}
        self.body_verts, self.body_faces = body_verts, body_faces
        self.bad_values = 0
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._ahead: dict = {}  # frame -> the future of its files

    def close(self):
        self._pool.shutdown(wait=True)

    def _files(self, t: int) -> tuple:
        """:meth:`_read` of frame t, with frame t + 1 read ahead."""
        for s in (t, t + 1):
            if s not in self._ahead and (s == t or s < (self.num_frames or 0)):
                self._ahead[s] = self._pool.submit(self._read, s)
        for s in [s for s in self._ahead if s < t]:
            del self._ahead[s]
        return self._ahead[t].result()

    def cues(self, t: int) -> FIT.FrameCues:
        masks, nrm, img, _ = self._files(t)
        dev = self.device
        return FIT.FrameCues(torch.as_tensor(masks, device=dev),
                             None if nrm is None else torch.as_tensor(nrm, device=dev).double(), None,
                             (self.body_verts[t].to(dev), self.body_faces.to(dev)),
                             None if img is None else torch.as_tensor(img, device=dev))

    def flow(self, t: int):
        fl = self._files(t)[3]
        return None if fl is None else (torch.as_tensor(fl[0], device=self.device).double(),
                                        torch.as_tensor(fl[1], device=self.device))

    def _path(self, kind: str, cam: str, t: int) -> Path:
        if kind == "images":
            return image_path(self.dirs[kind], cam, t)
        return Path(self.dirs[kind]) / cam / f"{t:06d}.{'png' if kind == 'masks' else 'exr'}"

    def _checked(self, path: Path, arr: np.ndarray, channels: int = 0, what: str = "") -> np.ndarray:
        """``arr`` checked to be (H, W[, >= channels]); with ``what``, its non-finite pixels counted and logged."""
        H, W = self.cams.height, self.cams.width
        if arr.shape[:2] != (H, W) or (channels and (arr.ndim != 3 or arr.shape[2] < channels)):
            raise files.ArtifactError(f"{path}: expected ({H}, {W}{f', {channels}' if channels else ''}) for "
                                      f"camera image size {H}x{W}, got {arr.shape}")
        bad = int((~np.isfinite(arr[..., :channels]).all(-1)).sum()) if what else 0
        if bad:
            self.bad_values += bad
            log.warning("%s: %d pixels with NaN/inf %s ignored", path, bad, what)
        return arr

    def _read(self, t: int) -> tuple:
        """Frame t's masks (C, H, W) bool, normals (C, H, W, 3) or None, images (C, H, W, 3) or None and flow
        t-1 -> t: (flow (C, H, W, 2), valid (C, H, W) bool) or None."""
        masks, normals, images, flow = [], [], [], None
        for cam in self.cams.names:
            p = self._path("masks", cam, t)
            masks.append(self._checked(p, files.read_mask(p)) == LABEL_GARMENT)
            if self.dirs["normals"] is not None:
                p = self._path("normals", cam, t)
                normals.append(self._checked(p, files.read_exr(p), 3, "normals")[..., :3])
            if self.dirs["images"] is not None:
                p = self._path("images", cam, t)
                images.append(self._checked(p, files.read_image(p), 3))
        if self.dirs["flows"] is not None and t > 0:
            paths = [self._path("flows", cam, t) for cam in self.cams.names]
            missing = [str(p) for p in paths if not p.is_file()]
            if missing:
                log.warning("fit: frame %d: no flow file %s", t, missing[0])
            else:
                fv = [read_flow(p) for p in paths]
                flow = (np.stack([self._checked(p, f, 2, "flow") for p, (f, _) in zip(paths, fv)]),
                        np.stack([v & np.isfinite(f).all(-1) for f, v in fv]))
        return (np.stack(masks), np.stack(normals) if normals else None, np.stack(images) if images else None,
                flow)


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


# --------------------------------------------------------------------------------------
# evaluation against ground truth
# --------------------------------------------------------------------------------------


def gt_correspondence(rest: np.ndarray, gt_rest: np.ndarray, gt_faces: np.ndarray):
    """Each template vertex's closest point on the ground-truth rest mesh: (face (V,), bary (V, 3), dist (V,))."""
    from ..garment import closest_points

    cp = closest_points(rest, gt_rest, gt_faces)
    return cp.face, cp.bary, cp.distance


def gt_template_vertices(scene_dir: str | os.PathLike, seq: str, rest: torch.Tensor, frames: int | None = None):
    """The synthetic ground truth of ``seq`` in the rig template's topology (see :func:`run_fit_eval`).

    rest: (V, 3) the template the rig is built on. Returns Y (T, V, 3) float64 (each template
    vertex's closest point on the ground-truth rest mesh, carried through every frame), the
    ground-truth meshes (T, Vg, 3) and faces (Fg, 3), and the correspondence distances (V,).
    frames: only the first ``frames`` frames. Raises if ``garment/template.obj`` and the
    ground truth differ in topology.
    """
    from ..io.mesh import read_mesh
    from ..metrics import mesh as MM

    scene_dir = Path(scene_dir)
    gt_path = scene_dir / seq / "gt" / "meshes.npz"
    a, _ = files.load_npz(gt_path, required=("garment_vertices", "garment_faces"))
    gt = torch.as_tensor(a["garment_vertices"][:frames]).double()
    gt_faces = torch.as_tensor(a["garment_faces"].astype(np.int64))
    obj = scene_dir / "garment" / "template.obj"
    rest_v, rest_f, _ = read_mesh(obj)
    if rest_v.shape[0] != gt.shape[1] or not np.array_equal(rest_f, gt_faces.numpy()):
        raise files.ArtifactError(f"{obj}: its topology ({rest_v.shape[0]} vertices, {rest_f.shape[0]} faces) differs "
                                  f"from {gt_path} ({gt.shape[1]} vertices, {gt_faces.shape[0]} faces)")
    face, bary, dist = gt_correspondence(torch.as_tensor(rest).double().cpu().numpy(), rest_v, rest_f)
    Y = MM.barycentric_transfer(gt, gt_faces, torch.as_tensor(face), torch.as_tensor(bary))  # (T, V, 3)
    return Y, gt, gt_faces, dist


def run_fit_eval(scene_dir: str | os.PathLike, seq: str, rig_npz: str | os.PathLike,
                 fits: Mapping[str, str | os.PathLike], out_csv: str | os.PathLike, samples: int = 20000,
                 seed: int = 0) -> dict:
    """Measure fitted garments against the synthetic ground truth; write ``fit_metrics.csv``.

    Ground truth: ``<seq>/gt/meshes.npz`` (garment_vertices (T, Vg, 3), garment_faces),
    whose rest shape is ``garment/template.obj`` (checked: same vertex count and faces).
    The template the rig is built on is a remeshing of that file, so each template
    vertex is tied to its closest point (face, barycentrics) on the ground-truth rest
    mesh, and that point, carried through every ground-truth frame, is the vertex's
    ground truth. The rig floor is the RMSE of ``rig.fit_transforms`` on those meshes.
    The 2D reprojection error (pixels) is measured in the sequence's training cameras, the
    views the fit sees (:func:`anidress_core.metrics.mesh.reprojection_error`), for the fit and
    for the rig floor.
    Returns a summary (per method: mean vertex RMSE etc.).
    """
    from ..metrics import mesh as MM
    from ..rig import fit_transforms, reconstruct

    gt_path = Path(scene_dir) / seq / "gt" / "meshes.npz"
    art = read_rig(rig_npz, dtype=torch.float64)
    Y, gt, gt_faces, dist = gt_template_vertices(scene_dir, seq, art.model.rest)
    log.info("fit_eval %s: template -> ground-truth rest correspondence, distance mean %.2f mm, max %.2f mm",
             seq, 1e3 * float(dist.mean()), 1e3 * float(dist.max()))
    floor_M = fit_transforms(art.model, Y)
    floor_X = reconstruct(art.model.rest, art.model.weights, floor_M)
    floor = MM.vertex_rmse(floor_X, Y)
    info = read_scene(scene_dir)
    cams = scene_cameras(scene_dir, seq, list(info["cameras"]["train"]), info)
    floor_px = MM.reprojection_error(floor_X, Y, cams)
    tpl_faces = torch.as_tensor(np.asarray(art.faces))

    @functools.cache
    def gt_samples(t: int) -> MM.SurfaceSamples:  # seeded per frame: the same for every method and run
        return MM.surface_samples(gt[t], gt_faces, samples, torch.Generator().manual_seed(seed + t))

    @functools.cache
    def floor_chamfer(t: int) -> float:  # the rig floor's surface error, the reference for the Chamfer column
        return MM.chamfer_normal(MM.surface_samples(floor_X[t], tpl_faces, samples,
                                                    torch.Generator().manual_seed(seed + 200003 + t)),
                                 gt_samples(t)).chamfer

    rows, summary = [], {"correspondence_mean_m": float(dist.mean()), "correspondence_max_m": float(dist.max()),
                         "rig_floor_rmse_m": float(floor.mean()), "methods": {}}
    for name, path in fits.items():
        f, h = load_garment_poses(path)
        X = torch.as_tensor(f["verts"]).double()
        if X.shape[1:] != Y.shape[1:] or X.shape[0] > Y.shape[0]:
            raise files.ArtifactError(f"{path}: verts {tuple(X.shape)} do not match the ground truth "
                                      f"{tuple(Y.shape)} of {gt_path} in template topology")
        T = X.shape[0]  # a fit of the first T frames is measured on those frames
        Yt, floor_t, gjit = Y[:T], floor[:T], MM.temporal_jitter(Y[:T])
        faces = torch.as_tensor(f["faces"])
        rm = MM.vertex_rmse(X, Yt)
        px = MM.reprojection_error(X, Yt, cams)
        jit = MM.temporal_jitter(X)
        acc = MM.acceleration_error(X, Yt)
        cn = [MM.chamfer_normal(MM.surface_samples(X[t], faces, samples,
                                                   torch.Generator().manual_seed(seed + 100003 + t)), gt_samples(t))
              for t in range(T)]
        for t in range(T):
            inner = 1 <= t <= T - 2
            rows.append({
                "method": name, "frame": t, "vertex_rmse_m": float(rm[t]), "rig_floor_rmse_m": float(floor_t[t]),
                "chamfer_m": cn[t].chamfer, "rig_floor_chamfer_m": floor_chamfer(t),
                "reprojection_px": float(px[t]), "rig_floor_reprojection_px": float(floor_px[t]),
                "normal_consistency": cn[t].normal_consistency,
                "jitter_m": float(jit[t - 1]) if inner else float("nan"),
                "gt_jitter_m": float(gjit[t - 1]) if inner else float("nan"),
                "accel_error_m": float(acc[t - 1]) if inner else float("nan"),
                "loss": float(f["loss"][t]),
                **{f"loss_{k}": float(f.get(f"loss_{k}", np.full(T, np.nan))[t]) for k in FIT.TERM_NAMES},
                "iterations": int(f["iterations"][t]),
                "wall_s": float(f.get("wall_s", np.full(T, np.nan))[t]),
            })
        summary["methods"][name] = {"vertex_rmse_m": float(rm.mean()), "rig_floor_rmse_m": float(floor_t.mean()),
                                    "accel_error_m": float(acc.mean()) if acc.numel() else float("nan"),
                                    "chamfer_m": float(np.mean([c.chamfer for c in cn])),
                                    "rig_floor_chamfer_m": float(np.mean([floor_chamfer(t) for t in range(T)])),
                                    "reprojection_px": float(px.mean()),
                                    "rig_floor_reprojection_px": float(floor_px[:T].mean()),
                                    "normal_consistency": float(np.mean([c.normal_consistency for c in cn])),
                                    "fps": h.get("meta", {}).get("fps")}
        log.info("fit_eval %s %s: vertex RMSE %.2f mm (rig floor %.2f mm), Chamfer %.2f mm, NC %.3f, "
                 "acceleration error %.2f mm", seq, name, 1e3 * float(rm.mean()), 1e3 * float(floor_t.mean()),
                 1e3 * summary["methods"][name]["chamfer_m"], summary["methods"][name]["normal_consistency"],
                 1e3 * summary["methods"][name]["accel_error_m"])
    with files.atomic_path(out_csv) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=FIT_METRIC_COLUMNS)
            w.writeheader()
            w.writerows(rows)
    return summary
