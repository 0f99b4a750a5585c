"""Stages `train` and `render`: the pose-driven radiance field (DESIGN.md §4, §9; paper §3.3).

Artifacts (under ``results/<scene>/<seq>/<variant>/``, seq = a training sequence,
variant = ``full`` | ``body_only``):

* ``field.pt`` (:mod:`anidress_core.io.field`, written atomically): ``format`` ("anidress-field/2"),
  ``variant``, ``scene``, ``sequence``, ``field_config`` (architecture),
  ``state_dict`` (canonical field + motion-weight volume incl. its prior and the
  canonical box), ``num_body_joints`` (24), ``num_bones`` (B; 0 for body_only / tight),
  ``history`` (loss, batch PSNR, samples per ray per logged step), ``wall_s``,
  ``steps``, ``lpips`` ("used" or why not), ``sampling`` (occupied fraction, samples
  per ray kept / considered), ``config_hash``, ``code_version``.
  While training, ``field.pt.ckpt`` holds the last checkpoint, resumed by a rerun with the
  same settings, data and code (``resume_key``: config hash without ``checkpoint_every``, the file
  format, a digest of the field package's sources and of the training tensors; else ignored and
  overwritten); removed when training ends. A
  resumed training ends with the same field as an uninterrupted one (tests/workflow/test_killed_runs.py).
* ``renders/<kind>/`` with kind ``novel_view`` (test cameras, training frames),
  ``novel_pose/<seq>`` (all cameras of a held-out sequence, its own garment poses) or
  ``library/<motion>`` (a simulated library motion: body motion + the rig's garment
  poses, paper §4.5): ``rgb/<cam>/<frame:06d>.png`` (composited over the background
  colour), ``alpha/<cam>/<frame:06d>.png`` (16-bit, opacity x 65535),
  ``depth/<cam>/<frame:06d>.exr`` (metres along the ray, 0 where empty) and
  ``render.json`` (frames, cameras, garment-pose source, seconds and samples per image).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .. import __version__
from ..camera import pixel_rays, project
from ..config import section_defaults
from ..field.deform import channel_last
from ..field.encoding import HashGridConfig
from ..field.model import AnimatableField, FieldConfig, canonical_occupancy
from ..field.sampler import build_occupancy, mask_boxes, occupancy_pixels, occupied_centres
from ..field.subject import BodyRest, GarmentRest, canonical_setup, posed_parts, unified_pose
from ..field.refine import PoseRefiner
from ..field.train import TrainConfig, TrainData, render_view, train_field
from ..io import files
from ..io.garment_poses import read_garment_poses
from ..io.body_motion import read_motion
from ..io.field import FIELD_FORMAT as FORMAT
from ..io.field import (FieldCheckpoint, read_field_checkpoint, read_training_state, training_state_path,
                        write_field_checkpoint, write_training_state)
from ..io.rig import read_rig
from ..io.scene import image_path, load_body, load_sequence_motion, read_scene, scene_cameras, sequence_source
from ..io.template import read_template

__all__ = ["run_train", "run_render", "load_field", "field_config_from_params", "train_config_from_params",
           "LoadedField", "FORMAT"]

log = logging.getLogger("anidress.field")

# --------------------------------------------------------------------------- config


def field_config_from_params(p: dict) -> FieldConfig:
    """``field`` config section -> FieldConfig (its ``model`` part; absent keys take the schema's defaults)."""
    m = section_defaults("field", p)["model"]
    grid = HashGridConfig(levels=int(m["hash_levels"]), features=int(m["hash_features"]),
                          log2_size=int(m["hash_log2_size"]), base_resolution=int(m["hash_base_resolution"]),
                          max_resolution=int(m["hash_max_resolution"]))
    return FieldConfig(grid=grid, width=int(m["width"]), volume_res=int(m["volume_res"]),
                       density_bias=float(m["density_bias"]), warp_iterations=int(m["warp_iterations"]))


def train_config_from_params(p: dict) -> TrainConfig:
    """``field/train`` (+ ``field/sampler/step_m``, ``field/render/background``) -> TrainConfig (absent keys take
    the schema's defaults)."""
    f = section_defaults("field", p)
    t = dict(f["train"])
    t.pop("frame_stride", None)
    t["step_m"] = float(f["sampler"]["step_m"])
    t["background"] = tuple(float(c) for c in f["render"]["background"])
    known = {fl.name for fl in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(t) - known)
    if unknown:
        raise ValueError(f"field/train: unknown keys {unknown}")
    return TrainConfig(**t)


def _device(device: str | None) -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


# --------------------------------------------------------------------------- inputs


@dataclasses.dataclass
class _Inputs:
    body: BodyRest
    garment: GarmentRest | None
    num_bones: int


def rest_inputs(scene_dir: Path, info: dict, template_npz, rig_npz, variant: str, shapes) -> _Inputs:
    """The subject at rest: the shaped body, and for ``full`` the garment template with the rig's bones."""
    body_model = load_body(scene_dir, info)
    v, J = body_model.shaped(shapes[None] if shapes is not None else None)
    body = BodyRest(v.reshape(-1, 3).float(), body_model.faces, body_model.weights.float(), J.reshape(24, 3).float())
    if template_npz is None:
        return _Inputs(body, None, 0)
    tpl = read_template(template_npz)
    rig_w = None
    B = 0
    if rig_npz is not None and variant == "full":
        rig = read_rig(rig_npz)
        if rig.model.rest.shape[0] != tpl.verts.shape[0]:
            raise files.ArtifactError(f"{rig_npz}: rig has {rig.model.rest.shape[0]} vertices but {template_npz} "
                                      f"has {tpl.verts.shape[0]}")
        rig_w = rig.model.weights.float()
        B = rig.model.num_bones if variant == "full" else 0
    elif variant == "full":
        raise ValueError(f"variant 'full' needs a rig (rig.npz) for the garment of {scene_dir}")
    g = GarmentRest(torch.as_tensor(tpl.verts).float(), torch.as_tensor(tpl.faces).long(), rig_w,
                    torch.as_tensor(tpl.body_weights).float())
    return _Inputs(body, g, B)


def read_views(seq_dir: Path, cams: Sequence[str], frames: Sequence[int], masks_dir: Path | None,
                background: Sequence[float]):
    """Images (T, C, H, W, 3) uint8 masked onto the background and labels (T, C, H, W) uint8."""
    imgs, labs = [], []
    bg = np.asarray(background, np.float32)
    for f in frames:
        ri, rl = [], []
        for c in cams:
            img = files.read_image(image_path(seq_dir, c, f))
            if masks_dir is not None:
                lab = files.read_mask(masks_dir / c / f"{f:06d}.png")
                if lab.shape != img.shape[:2]:
                    raise files.ArtifactError(f"{masks_dir / c / f'{f:06d}.png'}: mask {lab.shape} does not match "
                                              f"image {img.shape[:2]}")
                img = np.where(lab[..., None] > 0, img, bg)
                rl.append(lab)
            ri.append(np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8))
        imgs.append(np.stack(ri))
        if rl:
            labs.append(np.stack(rl))
    return torch.from_numpy(np.stack(imgs)), (torch.from_numpy(np.stack(labs)) if labs else None)


def sampler_params(p: dict) -> dict:
    """The ray sampler's settings of the config's ``field`` section (``sampler``; the schema's defaults where ``p``
    leaves a key out), typed."""
    s = section_defaults("field", p)["sampler"]
    return {"res": int(s["occupancy_res"]), "dilate_m": float(s["dilate_m"]),
            "body_only_garment_dilate_m": float(s["body_only_garment_dilate_m"]),
            "max_joints": int(s["max_joints"]), "min_weight": float(s["min_joint_weight"]),
            "mask_dilate_px": int(s["mask_dilate_px"]), "step_m": float(s["step_m"])}


# --------------------------------------------------------------------------- train


def run_train(scene_dir: str | os.PathLike, seq: str, variant: str, masks_dir: str | os.PathLike, out_pt: str | os.PathLike,
              params: dict, template_npz: str | os.PathLike | None = None, rig_npz: str | os.PathLike | None = None,
              garment_poses_npz: str | os.PathLike | None = None, lpips=None, device: str | None = None,
              progress: bool = True, max_steps: int | None = None, undistorted_dir: str | os.PathLike | None = None,
              body_dir: str | os.PathLike | None = None) -> dict:
    """Train the field of ``variant`` on the training cameras of sequence ``seq``.

    masks_dir: ``<dir>/<cam>/<frame:06d>.png`` labels (0 background, else subject) of the
    training cameras. Garment scenes need template_npz; variant ``full`` also rig_npz and
    garment_poses_npz (the fitted poses of ``seq``). lpips: a loaded LPIPS (the loss
    gets 0.2 LPIPS on patches) or an ``Unavailable`` / None (MSE only, logged).
    ``max_steps``: stop after this many steps *leaving the checkpoint* (to test resuming).
    ``undistorted_dir``: the sequence undistorted by rule undistort, read instead of the scene's
    images and cameras when they have lens distortion (:func:`anidress_core.io.scene.sequence_source`).
    ``body_dir``: the sequence's body poses refined by rule refine_body, read instead of its smpl/.
    Returns the saved dict (without the state_dict).
    """
    t_start = time.perf_counter()
    scene_dir, out_pt, masks_dir = Path(scene_dir), Path(out_pt), Path(masks_dir)
    dev = _device(device)
    info = read_scene(scene_dir)
    # the interval between checkpoints does not shape the field (a resumed training is exact)
    shaping = dict(params, train={k: v for k, v in params.get("train", {}).items() if k != "checkpoint_every"})
    cfg_hash = files.config_hash({"params": shaping, "variant": variant, "seq": seq})
    sp = sampler_params(params)
    tcfg = train_config_from_params(params)
    fcfg = field_config_from_params(params)
    stride = int(params.get("train", {}).get("frame_stride", 1))
    motion = load_sequence_motion(scene_dir, seq, info["fps"], body_dir)
    T_all = motion.poses.shape[0]
    frames = list(range(0, T_all, stride))
    cams = info["cameras"]["train"]
    log.info("train %s/%s %s: %d frames (stride %d) x %d cameras, device %s", scene_dir.name, seq, variant,
             len(frames), stride, len(cams), dev)
    # 1. the subject: rest body/garment, unified pose of the frames, posed surfaces
    inp = rest_inputs(scene_dir, info, template_npz, rig_npz, variant, motion.shapes)
    body_model = load_body(scene_dir, info)
    idx = torch.tensor(frames)
    posed = body_model.pose(motion.poses[idx], motion.Rh[idx], motion.Th[idx], motion.shapes)
    G = None
    if variant == "full" and inp.garment is not None:
        if garment_poses_npz is None:
            raise ValueError("variant 'full' of a garment scene needs garment poses (garment_poses.npz)")
        G = torch.as_tensor(read_garment_poses(garment_poses_npz, T_all, inp.num_bones).transforms).float()[idx]
    S = unified_pose(posed.transforms.float(), G, variant)
    parts = posed_parts(inp.body, posed.vertices.float(), inp.garment, variant, posed.transforms.float(), G,
                        sp["dilate_m"], sp["body_only_garment_dilate_m"])
    pr = params.get("priors", {})
    box, prior = canonical_setup(inp.body, inp.garment, variant, fcfg.volume_res,
                                 float(pr.get("garment_sigma_m", 0.04)), float(pr.get("box_pad_m", 0.1)),
                                 float(pr.get("ellipsoid_scale", 1.5)))
    t0 = time.perf_counter()
    grid = build_occupancy(parts, (sp["res"],) * 3, sp["max_joints"], sp["min_weight"], progress=progress)
    log.info("occupancy: %d frames, %.1f%% of grid voxels occupied, %d joints (%d body + %d garment), %.1f s",
             grid.num_frames, 100 * grid.occupied_fraction(), S.shape[1], 24, S.shape[1] - 24,
             time.perf_counter() - t0)
    # 2. the images: training cameras, masked; rays in the dilated mask boxes
    src = sequence_source(scene_dir, seq, undistorted_dir, info)
    cameras = scene_cameras(scene_dir, seq, list(cams), info, seq_dir=src).to(dtype=torch.float32)
    imgs, labels = read_views(src, cams, frames, masks_dir, tcfg.background)
    Tn, C, H, W, _ = imgs.shape
    boxes = mask_boxes((labels > 0).reshape(Tn * C, H, W), sp["mask_dilate_px"]).reshape(Tn, C, 4)
    box_frac = float(((boxes[..., 1] - boxes[..., 0]) * (boxes[..., 3] - boxes[..., 2])).sum()) / (Tn * C * H * W)
    rays = pixel_rays(cameras)
    data = TrainData(imgs.to(dev), (labels > 0).to(dev), boxes.to(dev), rays.origins[:, 0, 0].to(dev), rays.directions.to(dev),
                     S.to(dev), grid.to(dev))
    # 3. model, resume, train
    model = AnimatableField(box, prior, fcfg, seed=tcfg.seed).to(dev)
    ckpt_path = training_state_path(out_pt)
    # a checkpoint resumes only the same training: same settings and the same data (images, masks,
    # poses, occupancy, initial model), so a rerun after an upstream change never continues a stale one
    resume_key = files.config_hash({"config": cfg_hash, "lpips": bool(lpips), "format": FORMAT,
                                    "code": field_code_digest(),
                                    "data": _tensor_digest(data, grid, model.state_dict())})
    state = None
    if ckpt_path.is_file():
        st = read_training_state(ckpt_path, device=dev)
        if st.get("resume_key") == resume_key:
            state = st
            log.info("resuming from %s at step %d", ckpt_path, int(st["step"]))
        else:
            log.info("ignoring %s: made with other settings, data or field code", ckpt_path)
    if lpips:
        lp = lpips.to(dev)
        lpips_note = "used"
    else:
        lp = None
        lpips_note = getattr(lpips, "reason", "LPIPS not requested")
        log.info("LPIPS term off (loss = MSE only): %s", lpips_note)

    def save_ckpt(s: dict) -> None:
        s["config_hash"], s["resume_key"] = cfg_hash, resume_key
        write_training_state(ckpt_path, s)

    refiner = regrid = None
    if tcfg.refine_garment and G is not None:
        # the garment bones' centres: their rig weights' mean of the template, posed by the fit
        W = inp.garment.rig_weights.float()
        c = (W.T @ inp.garment.verts.float()) / W.sum(0)[:, None].clamp_min(1e-8)  # (B, 3)
        centres = (G[..., :3, :3] @ c[None, :, :, None])[..., 0] + G[..., :3, 3]  # (T, B, 3)
        refiner = PoseRefiner(centres, first=24).to(dev)

        def regrid(pose: torch.Tensor):
            p2 = posed_parts(inp.body, posed.vertices.float(), inp.garment, variant, posed.transforms.float(),
                             pose[:, 24:].float().cpu(), sp["dilate_m"], sp["body_only_garment_dilate_m"])
            return build_occupancy(p2, (sp["res"],) * 3, sp["max_joints"], sp["min_weight"]).to(dev)

    res = _train_maybe_partial(model, data, tcfg, state, save_ckpt, lp, progress, max_steps, refiner, regrid)
    if res is None:  # stopped early on purpose: the checkpoint stays
        return {"stopped_at": max_steps}
    kept = float(np.mean([h["samples_per_ray"] for h in res.history])) if res.history else float("nan")
    seen = float(np.mean([h["considered_per_ray"] for h in res.history])) if res.history else float("nan")
    out = {
        "format": FORMAT, "variant": variant, "scene": scene_dir.name, "sequence": seq,
        "field_config": dataclasses.asdict(fcfg), "train_config": dataclasses.asdict(tcfg),
        "num_body_joints": 24, "num_bones": int(S.shape[1] - 24), "history": res.history, "wall_s": res.wall_s,
        "cpu_s": res.cpu_s,
        "steps": res.steps, "frames": frames, "cameras": cams, "lpips": lpips_note,
        "sampling": {"occupied_fraction": grid.occupied_fraction(), "samples_per_ray": kept,
                     "considered_per_ray": seen, "ray_box_fraction": box_frac,
                     "occupancy_res": sp["res"], "dilate_m": sp["dilate_m"]},
        "config_hash": cfg_hash, "code_version": __version__, "device": str(dev),
        "stage_wall_s": time.perf_counter() - t_start,
    }
    if refiner is not None:
        with torch.no_grad():
            refined = refiner(S.to(dev))[:, 24:].cpu()
            d = refiner.delta.detach().cpu()
        out["refined_garment_transforms"] = refined
        out["refinement"] = {"rotation_deg_mean": math.degrees(float(d[..., :3].norm(dim=-1).mean())),
                             "translation_mm_mean": float(d[..., 3:].norm(dim=-1).mean()) * 1e3}
        log.info("garment poses refined through the images: mean correction %.2f deg, %.1f mm",
                 out["refinement"]["rotation_deg_mean"], out["refinement"]["translation_mm_mean"])
    write_field_checkpoint(out_pt, FieldCheckpoint(meta=out, state_dict=model.state_dict()))
    if ckpt_path.exists():
        ckpt_path.unlink()
    last = res.history[-1] if res.history else {}
    log.info("trained %s in %.1f s (%.1f CPU s, %d steps): last batch PSNR %.2f dB, %.1f of %.1f samples per ray kept",
             variant, res.wall_s, res.cpu_s, res.steps, last.get("psnr_db", float("nan")), kept, seen)
    return out


def field_code_digest() -> str:
    """sha256 of the field package's sources (anidress_core/field/*.py): a training checkpoint resumes only
    in the code that wrote it."""
    h = hashlib.sha256()
    for p in sorted((Path(__file__).resolve().parents[1] / "field").glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def _tensor_digest(*objs) -> str:
    """sha256 of every tensor in ``objs`` (tensors, named tuples / dataclasses / dicts of them, nested;
    other values by their repr), in order: dtype, shape and bytes."""
    h = hashlib.sha256()

    def feed(o):
        if isinstance(o, torch.Tensor):
            t = o.detach().cpu().contiguous()
            h.update(f"{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.numpy().tobytes())
        elif isinstance(o, dict):
            for k in sorted(o, key=str):
                h.update(str(k).encode())
                feed(o[k])
        elif isinstance(o, (list, tuple)):
            for v in o:
                feed(v)
        elif dataclasses.is_dataclass(o) and not isinstance(o, type):
            for f in dataclasses.fields(o):
                h.update(f.name.encode())
                feed(getattr(o, f.name))
        else:
            h.update(repr(o).encode())

    for o in objs:
        feed(o)
    return h.hexdigest()


def _train_maybe_partial(model, data, cfg, state, save_ckpt, lp, progress, max_steps, refiner=None, regrid=None):
    kw = {"refiner": refiner, "regrid": regrid}
    if max_steps is None or max_steps >= cfg.steps:
        return train_field(model, data, cfg, state=state, checkpoint=save_ckpt, lpips=lp, progress=progress, **kw)

    class _Stop(Exception):
        pass

    def ckpt_then_stop(s: dict) -> None:
        save_ckpt(s)
        if s["step"] >= max_steps:
            raise _Stop

    try:
        train_field(model, data, cfg, state=state, checkpoint=ckpt_then_stop, lpips=lp, progress=progress, **kw)
    except _Stop:
        return None
    return None


# --------------------------------------------------------------------------- load / render


@dataclasses.dataclass
class LoadedField:
    model: AnimatableField
    meta: dict


def load_field(path: str | os.PathLike, device: str | None = None) -> LoadedField:
    """Read ``field.pt`` written by :func:`run_train`."""
    ck = read_field_checkpoint(path)
    fc = ck.meta["field_config"]
    fcfg = FieldConfig(grid=HashGridConfig(**fc["grid"]), **{k: v for k, v in fc.items() if k != "grid"})
    sd = ck.state_dict
    model = AnimatableField(sd["canonical.box"], sd["weights.log_prior"].exp(), fcfg)
    model.load_state_dict(sd)
    model.eval()
    return LoadedField(model.to(_device(device)), ck.meta)


def _projected_box(grid_lo: torch.Tensor, grid_hi: torch.Tensor, cams, pad_px: int) -> torch.Tensor:
    """Rect (C, 4) y0, y1, x0, x1 covering the projection of a world box (3,), (3,) in every camera."""
    corners = torch.stack(torch.meshgrid(*[torch.stack([grid_lo[a], grid_hi[a]]) for a in range(3)], indexing="ij"),
                          -1).reshape(8, 3)
    pr = project(corners.to(cams.dtype), cams)
    uv = pr.uv  # (C, 8, 2)
    H, W = cams.height, cams.width
    x0 = (uv[..., 0].min(1).values.floor() - pad_px).clamp(0, W)
    x1 = (uv[..., 0].max(1).values.ceil() + 1 + pad_px).clamp(0, W)
    y0 = (uv[..., 1].min(1).values.floor() - pad_px).clamp(0, H)
    y1 = (uv[..., 1].max(1).values.ceil() + 1 + pad_px).clamp(0, H)
    behind = (pr.depth <= 0).any(1)
    box = torch.stack([y0, y1, x0, x1], -1).long()
    full = torch.tensor([0, H, 0, W])
    return torch.where(behind[:, None], full, box)


def _occupancy_pixels(grid, frame: int, cams) -> torch.Tensor:
    """(C, H, W) pixels whose rays can meet the frame's occupied voxels (camera model incl. distortion)."""
    centres = occupied_centres(grid, frame).cpu().to(cams.dtype)
    pr = project(centres, cams)
    f = torch.maximum(cams.K[:, 0, 0].abs(), cams.K[:, 1, 1].abs())
    zmin = pr.depth.min(1).values.clamp_min(1e-6) if centres.shape[0] else torch.ones(len(cams))
    radius = (f * 0.5 * float(grid.voxel[frame].norm()) / zmin).ceil()
    return occupancy_pixels(pr.uv, pr.depth, radius, cams.height, cams.width).to(grid.index.device)


def run_render(field_pt: str | os.PathLike, scene_dir: str | os.PathLike, out_dir: str | os.PathLike, params: dict,
               seq: str | None = None, cameras: Sequence[str] | None = None, template_npz=None, rig_npz=None,
               garment_poses_npz=None, library_motion_npz=None, library_name: str | None = None,
               frame_stride: int = 1, device: str | None = None, progress: bool = True,
               use_occupancy: bool = True, cull_joints: bool = True, undistorted_dir: str | os.PathLike | None = None,
               body_dir: str | os.PathLike | None = None) -> dict:
    """Render a sequence with a trained field into ``out_dir`` (layout in the module doc).

    Body motion: the EasyMocap ``smpl/`` of ``seq`` (captured; refined by rule refine_body when
    ``body_dir`` is given) or ``library_motion_npz``
    (a motion of the library; then garment poses are ``rig.transforms_of(library_name)``).
    Garment poses (variant ``full``): ``garment_poses_npz`` for a captured sequence.
    Cameras: ``cameras`` of ``seq`` (or of the training sequence for a library motion); the pinhole
    working cameras of ``undistorted_dir`` when they have lens distortion (as the training).
    """

    t_start = time.perf_counter()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    dev = _device(device)
    lf = load_field(field_pt, device=str(dev))
    model, meta = lf.model, lf.meta
    variant = meta["variant"]
    info = read_scene(scene_dir)
    params = section_defaults("field", params)  # the schema's defaults where params leave a key out
    sp, rp = sampler_params(params), params["render"]
    bg = torch.tensor(rp["background"], dtype=torch.float32, device=dev)
    cam_seq = seq if library_motion_npz is None else meta["sequence"]
    if library_motion_npz is not None:
        motion = read_motion(library_motion_npz)
        source = f"rig.transforms_of({library_name!r})"
    else:
        motion = load_sequence_motion(scene_dir, seq, info["fps"], body_dir)
        source = str(garment_poses_npz) if garment_poses_npz else "none"
    T_all = motion.poses.shape[0]
    frames = list(range(0, T_all, max(1, int(frame_stride))))
    inp = rest_inputs(scene_dir, info, template_npz, rig_npz, variant, motion.shapes)
    if inp.num_bones != meta["num_bones"]:
        raise ValueError(f"{field_pt}: trained with {meta['num_bones']} garment bones, the rig has {inp.num_bones}")
    body_model = load_body(scene_dir, info)
    idx = torch.tensor(frames)
    posed = body_model.pose(motion.poses[idx], motion.Rh[idx], motion.Th[idx], motion.shapes)
    G = None
    if variant == "full" and inp.garment is not None:
        if library_motion_npz is not None:
            G = read_rig(rig_npz).transforms_of(library_name).float()
            if G.shape[0] != T_all:
                raise files.ArtifactError(f"{rig_npz}: {library_name} has {G.shape[0]} garment-pose frames, the body "
                                          f"motion {library_motion_npz} {T_all}")
            G = G[idx]
        else:
            if garment_poses_npz is None:
                raise ValueError("rendering variant 'full' needs the garment poses of the sequence")
            G = torch.as_tensor(read_garment_poses(garment_poses_npz, T_all, inp.num_bones).transforms).float()[idx]
            if seq == meta["sequence"] and "refined_garment_transforms" in meta:
                # the training frames' poses as the field refined them (the fit's elsewhere)
                trained = {f: i for i, f in enumerate(meta["frames"])}
                for i, f in enumerate(frames):
                    if f in trained:
                        G[i] = meta["refined_garment_transforms"][trained[f]].float()
                source += " (training frames refined through the images)"
    S = unified_pose(posed.transforms.float(), G, variant)
    parts = posed_parts(inp.body, posed.vertices.float(), inp.garment, variant, posed.transforms.float(), G,
                        sp["dilate_m"], sp["body_only_garment_dilate_m"])
    grid = build_occupancy(parts, (sp["res"],) * 3, sp["max_joints"], sp["min_weight"], progress=False).to(dev)
    S = S.to(dev)
    all_cams = scene_cameras(scene_dir, cam_seq, None, info, seq_dir=sequence_source(
        scene_dir, cam_seq, undistorted_dir, info)).to(dtype=torch.float32)
    names = list(cameras) if cameras else all_cams.names
    cams = all_cams.select(names)
    rays = pixel_rays(cams)
    origins, dirs = rays.origins[:, 0, 0].to(dev), rays.directions.to(dev)
    chunk = int(rp["chunk"])
    with torch.no_grad():
        volume = model.weights()
        volume_last = channel_last(volume) if model.cfg.warp_iterations > 0 else None
    skip = None
    if float(rp["skip_density"]) > 0:
        t0 = time.perf_counter()
        skip = canonical_occupancy(model, int(rp["skip_res"]), float(rp["skip_density"]))
        log.info("canonical occupancy %d^3: %.1f%% of the cells have density above %g/m (%.1f s)", skip.occupied.shape[0],
                 100 * float(skip.occupied.float().mean()), float(rp["skip_density"]), time.perf_counter() - t0)
    per_image = []
    todo = [(i, f, c) for i, f in enumerate(frames) for c in range(len(names))]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(todo), desc=f"render {out_dir.name}", unit="img")
    early = float(rp["early_stop"])
    for i, f in enumerate(frames):
        lo, hi = grid.box(torch.tensor([i], device=dev))
        boxes = _projected_box(lo[0].cpu(), hi[0].cpu(), cams, 2)
        # rays only through pixels that can see an occupied voxel (the projected occupancy);
        # with the occupancy ablation, every pixel of the projected grid box
        pix = _occupancy_pixels(grid, i, cams) if use_occupancy else None
        for c, name in enumerate(names):
            t0, c0 = time.perf_counter(), time.process_time()
            r = render_view(model, origins[c], dirs[c], boxes[c], i, S, grid, sp["step_m"], bg, chunk=chunk,
                            volume=volume, use_occupancy=use_occupancy, cull_joints=cull_joints, early_stop=early,
                            skip=skip, volume_last=volume_last,
                            pixels=None if pix is None else pix[c])
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            files.write_png(out_dir / "rgb" / name / f"{f:06d}.png", r.rgb.cpu().numpy())
            files.write_png(out_dir / "alpha" / name / f"{f:06d}.png",
                            (r.alpha.clamp(0, 1).cpu().numpy() * 65535 + 0.5).astype(np.uint16))
            files.write_exr(out_dir / "depth" / name / f"{f:06d}.exr", r.depth.cpu().numpy())
            per_image.append({"camera": name, "frame": f, "seconds": dt, "cpu_seconds": dc, "rays": r.rays,
                              "samples": r.num_samples,
                              "considered": r.considered})
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    secs = [p["seconds"] for p in per_image]
    summary = {
        "field": str(field_pt), "variant": variant, "sequence": seq if library_motion_npz is None else library_name,
        "body_motion": str(library_motion_npz) if library_motion_npz is not None else f"{scene_dir / seq / 'smpl'}",
        "garment_poses": source if variant == "full" and inp.garment is not None else "none (body joints only)",
        "frames": frames, "cameras": names, "images": len(per_image),
        "seconds_per_image_median": float(np.median(secs)) if secs else float("nan"),
        "cpu_seconds_per_image_median": float(np.median([p["cpu_seconds"] for p in per_image])) if secs else float("nan"),
        "samples_per_ray": float(sum(p["samples"] for p in per_image) / max(1, sum(p["rays"] for p in per_image))),
        "considered_per_ray": float(sum(p["considered"] for p in per_image) / max(1, sum(p["rays"] for p in per_image))),
        "background": bg.cpu().tolist(), "use_occupancy": use_occupancy, "cull_joints": cull_joints,
        "early_stop": early, "skip_density": float(rp["skip_density"]),
        "per_image": per_image,
        "wall_s": time.perf_counter() - t_start, "code_version": __version__,
    }
    files.write_text(out_dir / "render.json", json.dumps(summary, indent=1))
    log.info("rendered %d images into %s: %.2f s per image (median), %.1f samples per ray", len(per_image), out_dir,
             summary["seconds_per_image_median"], summary["samples_per_ray"])
    return summary
