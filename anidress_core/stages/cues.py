"""Stages `masks`, `flows`, `normals` and the cue evaluation (DESIGN.md §6, §7).

Per sequence of a scene, for the selected cameras (``train``: the scene's training
cameras, ``all``: every camera), directory outputs::

    <out>/masks/<cam>/<frame:06d>.png   labels 0 background, 1 body, 2 garment
                                        (anidress_core.io.files.write_mask / read_mask)
    <out>/flows/<cam>/<frame:06d>.exr   channels X, Y, valid: forward flow from frame-1
                                        to frame in pixels on frame-1's pixel grid; no file
                                        for the first frame; valid = 1 inside the processed
                                        region (dilated subject box of both frames), else 0
    <out>/normals.json                  the normal cue: the folder the fit reads and the axis convention
                                        found, or {"skipped": true, "reason": ..., "normal_weight": 0}
    <out>/normals/<cam>/<frame:06d>.exr a captured sequence's shipped normals in the pipeline's format and
                                        axes (run_normals with out_dir); empty otherwise

Masks, normals and flows shipped with a sequence (``data/<scene>/<seq>/masks``, ``normals``,
``flows``) in the formats scene.yaml's ``cues`` names (:mod:`anidress_core.io.shipped_cues`) are
used, not estimated: label masks as they are, a human parser's masks converted to labels
(:func:`run_convert_masks`), flows converted with ``cues/flows/method: files``
(:func:`run_convert_flows`), normals checked for their axis convention against the posed body
(:func:`run_normals`). ``data/<scene>/<seq>/gt`` is ground truth for evaluation only and is never
read by the estimators. A sequence whose cameras have lens distortion is read
from its copy undistorted to pinhole working cameras (``undistorted_dir``, rule undistort;
:func:`anidress_core.io.scene.sequence_source` decides). A directory output is written into a hidden
temporary sibling and renamed into place at the end: a failure leaves nothing
half-written.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from .. import __version__
from ..cues import evaluate as cue_eval
from ..cues import flow as cue_flow
from ..cues import masks as cue_masks
from ..cues import normals as cue_normals
from ..geometry import lbs
from ..io import cue_files, files, shipped_cues
from ..io.scene import (frame_files, image_path, load_body, load_sequence_motion, plate_path, read_scene, scene_cameras,
                        sequence_source)
from ..io.scene_info import cue_formats, select_cameras
from ..io.template import read_template
from ..synth import LABEL_GARMENT

__all__ = [
    "select_cameras",
    "sequence_frames",
    "mask_params",
    "ShapePrior",
    "run_masks",
    "run_convert_masks",
    "run_flows",
    "run_convert_flows",
    "run_normals",
    "evaluate_cues",
    "format_table",
]

log = logging.getLogger("anidress.cues")


# --------------------------------------------------------------------------- scene helpers


def sequence_frames(seq_dir: str | os.PathLike, cams: Sequence[str]) -> list[int]:
    """Frame numbers of a sequence: the images of its first camera; every camera must have them all."""
    seq_dir = Path(seq_dir)
    frames = None
    for cam in cams:
        d = seq_dir / "images" / cam
        if not d.is_dir():
            raise FileNotFoundError(f"{d}: image folder not found")
        fr = sorted(frame_files(d))
        if not fr:
            raise FileNotFoundError(f"{d}: no <frame>.png/.jpg images")
        if frames is None:
            frames = fr
        elif fr != frames:
            missing = sorted(set(frames) ^ set(fr))[:5]
            raise FileNotFoundError(f"{d}: frames differ from camera {cams[0]!r} (e.g. {missing})")
    return frames


@contextlib.contextmanager
def _drained() -> Iterator[list]:
    """A list for the futures of writes into a :func:`~anidress_core.io.files.atomic_dir` made on a pool that
    outlives it:
    on an exception, the writes not started are cancelled and the running ones waited for, so that
    none recreates the temporary folder after atomic_dir has removed it."""
    pending: list = []
    try:
        yield pending
    except BaseException:
        for p in pending:
            p.cancel()
        concurrent.futures.wait(pending)
        raise


def _cameras(seq_dir: Path, names: Sequence[str], info: dict):
    return scene_cameras(seq_dir.parent, seq_dir.name, list(names), info, dtype=torch.float32)


def _read_rgb(path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    img = files.read_image(path)
    if shape is not None and img.shape[:2] != tuple(shape):
        raise files.ArtifactError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected "
                                  f"{shape[1]}x{shape[0]}")
    return img


# --------------------------------------------------------------------------- masks


def mask_params(cfg: dict) -> cue_masks.MaskParams:
    """MaskParams from a validated ``cues/masks`` config section (extra keys ignored)."""
    names = {f.name for f in dataclasses.fields(cue_masks.MaskParams)}
    return cue_masks.MaskParams(**{k: v for k, v in cfg.items() if k in names})


class ShapePrior:
    """The shape prior of one sequence: posed body + skinned garment template, per frame.

    cams: :class:`anidress_core.camera.Cameras` (C cameras, H x W) of ``frames``;
    :meth:`labels` renders the prior's labels (C, H, W) uint8 (1 body, 2 garment) of a frame, :meth:`flow` its
    flow (C, H, W, 2) between two frames; the masks and flows stages start from them.
    """

    def __init__(self, scene_dir: Path, seq: str, info: dict, template_npz: str | os.PathLike | None,
                 cams, frames: list[int]):
        body = load_body(scene_dir, info)
        motion = load_sequence_motion(scene_dir, seq, info["fps"])
        smpl_frames = sorted(int(p.stem) for p in (scene_dir / seq / "smpl").glob("*.json"))
        index = {f: i for i, f in enumerate(smpl_frames)}
        missing = [f for f in frames if f not in index]
        if missing:
            raise FileNotFoundError(f"{scene_dir / seq / 'smpl'}: no body parameters for frames {missing[:5]}")
        sel = torch.tensor([index[f] for f in frames])
        posed = body.pose(motion.poses[sel], motion.Rh[sel], motion.Th[sel], motion.shapes)
        self.body_verts, self.body_faces = posed.vertices.float(), body.faces
        self.garment_verts = self.garment_faces = None
        if template_npz is not None:
            tpl = read_template(template_npz)
            # garment vertices follow the body: x = sum_k w_k A_k x_rest (template body weights)
            self.garment_verts = lbs(torch.from_numpy(tpl.verts).float(), torch.from_numpy(tpl.body_weights).float(),
                                     posed.transforms.float())
            self.garment_faces = torch.from_numpy(tpl.faces)
        self.cams, self.frame_pos = cams, {f: i for i, f in enumerate(frames)}

    def labels(self, frame: int) -> np.ndarray:
        t = self.frame_pos[frame]
        g = None if self.garment_verts is None else self.garment_verts[t]
        return cue_masks.render_prior(self.body_verts[t], self.body_faces, g, self.garment_faces, self.cams.K,
                                      self.cams.world_to_cam, self.cams.height, self.cams.width).numpy()

    def body_normals(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Where the posed body is seen (C, H, W) bool (not hidden by the skinned garment template) and the
        camera-space normals (C, H, W, 3) of the visible surface, OpenCV axes, facing the camera."""
        from ..raster import rasterize, render_face_normals

        v, faces = self._mesh(self.frame_pos[frame])
        K, w2c = self.cams.K.float(), self.cams.world_to_cam.float()
        frags = rasterize(v, faces, K, w2c, self.cams.height, self.cams.width)
        body = (frags.face_id >= 0) & (frags.face_id < self.body_faces.shape[0])
        return body.numpy(), render_face_normals(v, faces, w2c, frags).numpy()

    def _mesh(self, t: int) -> tuple[Tensor, Tensor]:
        if self.garment_verts is None:
            return self.body_verts[t], self.body_faces
        return (torch.cat([self.body_verts[t], self.garment_verts[t]]),
                torch.cat([self.body_faces, self.garment_faces + self.body_verts.shape[1]]))

    def flow(self, frame_prev: int, frame: int, downsample: int = 1, sigma_px: float = 4.0) -> np.ndarray:
        """Flow (C, H, W, 2) of the prior mesh from ``frame_prev`` to ``frame``, extended beyond it
        (:func:`anidress_core.cues.flow.extend_flow`); computed at 1/``downsample`` of the image
        size (the rasteriser is the cost; the estimator refines the details) and resized."""
        import cv2

        from ..raster import rasterize

        cams = self.cams if downsample == 1 else self.cams.scaled(1.0 / downsample)
        v0, faces = self._mesh(self.frame_pos[frame_prev])
        v1, _ = self._mesh(self.frame_pos[frame])
        K, w2c = cams.K.float(), cams.world_to_cam.float()
        frags = rasterize(v0, faces, K, w2c, cams.height, cams.width)
        fl = cue_flow.mesh_flow(frags.face_id, frags.bary, v1, faces, K, w2c).numpy()
        hit = (frags.face_id >= 0).numpy()
        out = np.stack([cue_flow.extend_flow(fl[c], hit[c], sigma_px / downsample) for c in range(fl.shape[0])])
        if downsample == 1:
            return out
        H, W = self.cams.height, self.cams.width
        sx, sy = W / cams.width, H / cams.height
        return np.stack([cv2.resize(o, (W, H), interpolation=cv2.INTER_LINEAR) * np.float32([sx, sy]) for o in out])


def _plates(seq_dir: Path, cams: Sequence[str], frames: list[int], background: str, shape, median_frames: int,
            pool: ThreadPoolExecutor) -> np.ndarray:
    """Background plates (C, H, W, 3): recorded ``backgrounds/<cam>.<png|jpg|jpeg>`` or temporal medians."""
    if background == "plate":
        paths = [plate_path(seq_dir, c) for c in cams]
        return np.stack(list(pool.map(lambda p: _read_rgb(p, shape), paths)))
    if background != "temporal_median":
        raise ValueError(f"cues/masks/background must be 'plate' or 'temporal_median', got {background!r}")
    pick = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(median_frames, len(frames))).round()
                                         .astype(int))]
    out = []
    for c in cams:
        imgs = np.stack(list(pool.map(lambda f: _read_rgb(image_path(seq_dir, c, f), shape), pick)))
        out.append(cue_masks.temporal_median_plate(imgs))
    return np.stack(out)


def run_masks(scene_dir: str | os.PathLike, seq: str, out_dir: str | os.PathLike, cfg: dict,
              template_npz: str | os.PathLike | None = None, cameras: str | Sequence[str] = "train",
              threads: int = 2, progress: bool = True, undistorted_dir: str | os.PathLike | None = None) -> dict:
    """Estimate body/garment masks of one sequence into ``out_dir/<cam>/<frame>.png``.

    cfg: the ``cues/masks`` config section (:class:`MaskParams` fields plus
    ``background`` ('plate' | 'temporal_median'), ``colour_frames``, ``median_frames``).
    template_npz: the scene's garment template (None: a tight-clothed scene, labels
    are 0/1 only). Returns timing statistics.
    """
    t_start = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    seq_dir = sequence_source(scene_dir, seq, undistorted_dir, info)
    params = mask_params(cfg)
    names = select_cameras(info, cameras, scene_dir)
    cams = _cameras(seq_dir, names, info)
    shape = (cams.height, cams.width)
    frames = sequence_frames(seq_dir, names)
    has_garment = template_npz is not None
    log.info("masks %s/%s: %d cameras x %d frames at %dx%d, method %s, background %s%s", scene_dir.name, seq,
             len(names), len(frames), shape[1], shape[0], params.method, cfg.get("background", "plate"),
             "" if has_garment else " (no garment: labels 0/1)")
    torch.set_num_threads(max(1, threads))
    cam_idx = np.arange(len(names))
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        plates = _plates(seq_dir, names, frames, cfg.get("background", "plate"), shape,
                         int(cfg.get("median_frames", 50)), pool)
        prior = ShapePrior(scene_dir, seq, info, template_npz, cams, frames) if has_garment else None

        def load(frame: int) -> np.ndarray:
            return np.stack(list(pool.map(lambda c: _read_rgb(image_path(seq_dir, c, frame), shape), names)))

        # 1. colour model (method colour) from a few frames spread over the sequence (kept for step 2)
        model, cache = None, {}
        if has_garment and params.method == "colour":
            n = min(int(cfg.get("colour_frames", 12)), len(frames))
            pick = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]
            for f in pick:
                im = load(f)
                cache[f] = (im, cue_masks.subject_masks(im, plates, params), prior.labels(f))
            model = cue_masks.fit_colour_model(
                np.concatenate([c[0] for c in cache.values()]), np.tile(cam_idx, len(cache)),
                np.concatenate([c[1] for c in cache.values()]), np.concatenate([c[2] for c in cache.values()]),
                len(names), params)
            log.info("colour model: %d frames, %d bins per channel", len(pick), params.hist_bins)
        # 2. every frame, all cameras at once
        with files.atomic_dir(out_dir) as tmp, _drained() as pending:
            subject, empty = 0.0, []
            for f in tqdm(frames, desc=f"masks {seq}", unit="frame", disable=not progress):
                if f in cache:
                    im, fg, pr = cache.pop(f)
                else:
                    im, fg = load(f), None
                    pr = prior.labels(f) if has_garment else None
                lab = cue_masks.estimate_masks(im, plates, pr, params, cam_idx, model, has_garment, fg)
                subject += float((lab > 0).mean())
                empty += [f"{cam}/{f:06d}" for c, cam in enumerate(names) if not (lab[c] > 0).any()]
                for c, cam in enumerate(names):
                    pending.append(pool.submit(files.write_mask, tmp / cam / f"{f:06d}.png", lab[c]))
                if len(pending) > 64:
                    for p in pending:
                        p.result()
                    pending.clear()
            for p in pending:
                p.result()
            n_masks = len(names) * len(frames)
            if empty:
                log.warning("masks %s/%s: %d of %d masks have no subject pixel: %s%s", scene_dir.name, seq, len(empty),
                            n_masks, ", ".join(empty[:5]), " ..." if len(empty) > 5 else "")
            limit = float(cfg.get("max_empty_fraction", 0.5))
            if len(empty) > limit * n_masks:  # nothing is written (atomic_dir): no fit or field on empty masks
                raise ValueError(
                    f"{seq_dir}: {len(empty)} of {n_masks} estimated masks hold no subject pixel (more than "
                    f"cues/masks/max_empty_fraction {limit:g}; background {cfg.get('background', 'plate')}): with "
                    "temporal_median, a subject that hardly moves over the frames is its own median plate; ship "
                    "masks/ (e.g. from a human parser) or backgrounds/ plates, or use more frames (median_frames)")
    wall = time.perf_counter() - t_start
    stats = {"cameras": len(names), "frames": len(frames), "wall_s": wall,
             "per_frame_s": wall / max(1, len(frames)), "subject_fraction": subject / max(1, len(frames)),
             "empty_masks": len(empty)}
    log.info("masks %s/%s: wrote %s in %.1f s (%.3f s per frame of %d cameras)", scene_dir.name, seq, out_dir,
             wall, stats["per_frame_s"], len(names))
    return stats


def run_convert_masks(scene_dir: str | os.PathLike, seq: str, out_dir: str | os.PathLike, garment: bool = True,
                      threads: int = 2, progress: bool = True,
                      undistorted_dir: str | os.PathLike | None = None) -> dict:
    """A sequence's shipped masks in scene.yaml's ``cues/masks`` format (a human parser's) as labels
    ``out_dir/<cam>/<frame:06d>.png`` (0 background, 1 body, 2 garment), every camera they cover.

    garment False: a tight-clothed scene (garment labels are body). Returns the counts.
    """
    t_start = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    cfg = cue_formats(info, scene_dir)["masks"]
    seq_dir = sequence_source(scene_dir, seq, undistorted_dir, info)
    root = seq_dir / "masks"
    names = [c for c in select_cameras(info, "all", scene_dir) if (root / c).is_dir()]
    if not names:
        raise FileNotFoundError(f"{root}: no camera folders of shipped masks")
    cams = _cameras(seq_dir, names[:1], info)
    shape = (cams.height, cams.width)
    frames = sequence_frames(seq_dir, names[:1])
    labels = shipped_cues.garment_labels(cfg) if cfg["format"] == "schp" else (2,)
    log.info("masks %s/%s: shipped %s masks (%s) of %d cameras x %d frames converted to labels; garment labels %s",
             scene_dir.name, seq, cfg["format"], cfg.get("label_set"), len(names), len(frames),
             list(labels) if garment else "none (tight)")
    garment_px = subject_px = 0
    with files.atomic_dir(out_dir) as tmp, ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        def one(job):
            cam, f = job
            lab = shipped_cues.read_mask_labels(root, cam, f, cfg, shape, garment)
            files.write_mask(tmp / cam / f"{f:06d}.png", lab)
            return int((lab == 2).sum()), int((lab > 0).sum())

        jobs = [(c, f) for c in names for f in frames]
        for g, a in tqdm(pool.map(one, jobs), total=len(jobs), desc=f"masks {seq}", unit="mask",
                         disable=not progress):
            garment_px += g
            subject_px += a
    if garment and garment_px == 0:
        raise ValueError(f"{root}: no pixel of the shipped masks carries a garment label {list(labels)} of label set "
                         f"{cfg.get('label_set')!r}: set scene.yaml cues/masks/garment_labels (or label_set)")
    stats = {"cameras": len(names), "frames": len(frames), "garment_fraction": garment_px / max(1, subject_px),
             "wall_s": time.perf_counter() - t_start}
    log.info("masks %s/%s: wrote %s in %.1f s (garment %.0f%% of the subject's pixels)", scene_dir.name, seq, out_dir,
             stats["wall_s"], 100 * stats["garment_fraction"])
    return stats


# --------------------------------------------------------------------------- flows


def _read_labels(path: Path, shape) -> np.ndarray:
    m = files.read_mask(path)
    if shape is not None and m.shape != tuple(shape):
        raise files.ArtifactError(f"{path}: mask is {m.shape[1]}x{m.shape[0]}, expected {shape[1]}x{shape[0]}")
    return m


class _CameraFlow:
    """Flows of one camera, frame after frame (each image and mask is read once)."""

    def __init__(self, seq_dir: Path, masks_dir: Path, cam: str, method: str, margin: int, shape, out: Path,
                 refine_window: int = 0):
        self.seq_dir, self.masks_dir, self.cam, self.method, self.margin = seq_dir, masks_dir, cam, method, margin
        self.shape, self.out, self.refine_window = shape, out, refine_window
        self.est = cue_flow.make_estimator(method)
        self.prev_img = self.prev_mask = None
        self.compute, self.refine_s, self.refined, self.pixels, self.pairs = 0.0, 0.0, 0, 0, 0

    def step(self, frame: int, init: np.ndarray | None) -> None:
        img = cue_flow.to_gray8(_read_rgb(image_path(self.seq_dir, self.cam, frame), self.shape))
        mask = _read_labels(self.masks_dir / self.cam / f"{frame:06d}.png", self.shape)
        if self.prev_img is not None:
            region = cue_flow.flow_region(self.prev_mask, mask, self.margin)
            if region is None:
                r = cue_flow.FlowEstimate(np.zeros(self.shape + (2,), np.float32), np.zeros(self.shape, bool),
                                          None, 0.0)
            else:
                r = cue_flow.estimate_flow(self.prev_img, img, self.method, region, self.est, init)
                self.pixels += (region.y1 - region.y0) * (region.x1 - region.x0)
                if self.refine_window:  # the garment's pixels of frame t-1 (what the fit samples)
                    t0 = time.perf_counter()
                    f, n = cue_flow.refine_lk(self.prev_img, img, r.flow, (self.prev_mask == LABEL_GARMENT) & r.valid,
                                              self.refine_window)
                    r = r._replace(flow=f)
                    self.refine_s += time.perf_counter() - t0
                    self.refined += n
            self.compute += r.compute_s
            self.pairs += 1
            files.write_exr(self.out / self.cam / f"{frame:06d}.exr",
                            np.concatenate([r.flow, r.valid[..., None].astype(np.float32)], -1), ("X", "Y", "valid"))
        self.prev_img, self.prev_mask = img, mask


@contextlib.contextmanager
def _cv2_threads(n: int):
    import cv2

    old = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        cv2.setNumThreads(old)


def run_flows(scene_dir: str | os.PathLike, seq: str, masks_dir: str | os.PathLike, out_dir: str | os.PathLike,
              cfg: dict, template_npz: str | os.PathLike | None = None, cameras: str | Sequence[str] = "train",
              threads: int = 2, progress: bool = True, undistorted_dir: str | os.PathLike | None = None) -> dict:
    """Forward optical flow of one sequence into ``out_dir/<cam>/<frame>.exr`` (no file for the first frame).

    cfg: the ``cues/flows`` config section (``method`` (``files``: :func:`run_convert_flows`), ``margin_px``,
    ``prior``, ``refine``,
    ``refine_window``; with ``refine: lk`` the garment's pixels of frame t-1 are then
    re-estimated by :func:`anidress_core.cues.flow.refine_lk`).
    masks_dir: the sequence's masks (shipped or estimated), which bound the processed
    region. With ``prior`` the flow of the posed body + skinned garment template
    (``template_npz``; None: the body alone) initialises the estimator
    (:func:`anidress_core.cues.flow.estimate_flow`). The cameras of a frame run in
    parallel on ``threads`` threads (OpenCV itself single-threaded).
    """
    if cfg["method"] == "files":
        return run_convert_flows(scene_dir, seq, out_dir, cameras, threads, progress, undistorted_dir)
    t_start = time.perf_counter()
    scene_dir, masks_dir = Path(scene_dir), Path(masks_dir)
    info = read_scene(scene_dir)
    seq_dir = sequence_source(scene_dir, seq, undistorted_dir, info)
    names = select_cameras(info, cameras, scene_dir)
    frames = sequence_frames(seq_dir, names)
    method, margin, use_prior = cfg["method"], int(cfg["margin_px"]), bool(cfg.get("prior", False))
    if method not in cue_flow.FLOW_METHODS:
        raise ValueError(f"cues/flows/method must be one of {cue_flow.FLOW_METHODS}, got {method!r}")
    refine = cfg.get("refine", "none")
    if refine not in cue_flow.REFINE_METHODS:
        raise ValueError(f"cues/flows/refine must be one of {cue_flow.REFINE_METHODS}, got {refine!r}")
    refine_window = int(cfg.get("refine_window", 7)) if refine == "lk" else 0
    if refine_window and (refine_window < 3 or refine_window % 2 == 0):
        raise ValueError(f"cues/flows/refine_window must be odd and >= 3, got {refine_window}")
    size = info.get("image_size")
    shape = tuple(size) if size else files.read_image(image_path(seq_dir, names[0], frames[0])).shape[:2]
    log.info("flows %s/%s: %s%s%s, %d cameras x %d pairs, margin %d px, %d threads", scene_dir.name, seq, method,
             " initialised by the body/garment prior" if use_prior else "",
             f", Lucas-Kanade refinement of the garment's pixels (window {refine_window})" if refine_window else "",
             len(names), len(frames) - 1, margin, threads)
    torch.set_num_threads(max(1, threads))
    prior = None
    if use_prior:
        prior = ShapePrior(scene_dir, seq, info, template_npz, _cameras(seq_dir, names, info), frames)
    prior_s = 0.0
    with files.atomic_dir(out_dir) as tmp, _cv2_threads(1), ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        cams = [_CameraFlow(seq_dir, masks_dir, cam, method, margin, shape, tmp, refine_window) for cam in names]
        for i, f in enumerate(tqdm(frames, desc=f"flows {seq}", unit="frame", disable=not progress)):
            init = None
            if prior is not None and i > 0:
                t0 = time.perf_counter()
                init = prior.flow(frames[i - 1], f, int(cfg.get("prior_downsample", 1)))
                prior_s += time.perf_counter() - t0
            list(pool.map(lambda c: cams[c].step(f, None if init is None else init[c]), range(len(cams))))
    wall = time.perf_counter() - t_start
    pairs = sum(c.pairs for c in cams)
    compute = sum(c.compute for c in cams)
    stats = {"method": method, "prior": use_prior, "pairs": pairs, "wall_s": wall,
             "compute_s_per_pair": compute / max(1, pairs), "prior_s_per_frame": prior_s / max(1, len(frames) - 1),
             "region_fraction": sum(c.pixels for c in cams) / max(1, pairs * shape[0] * shape[1]),
             "refine": refine, "refine_s_per_pair": sum(c.refine_s for c in cams) / max(1, pairs),
             "refined_pixels_per_pair": sum(c.refined for c in cams) / max(1, pairs)}
    log.info("flows %s/%s: wrote %s in %.1f s; %.4f s of %s per pair%s%s, %.0f%% of the pixels processed",
             scene_dir.name, seq, out_dir, wall, stats["compute_s_per_pair"], method,
             f" + {stats['prior_s_per_frame']:.3f} s of prior flow per frame" if use_prior else "",
             f" + {stats['refine_s_per_pair']:.4f} s of Lucas-Kanade per pair ({stats['refined_pixels_per_pair']:.0f} "
             "garment pixels refined)" if refine_window else "",
             100 * stats["region_fraction"])
    return stats


def run_convert_flows(scene_dir: str | os.PathLike, seq: str, out_dir: str | os.PathLike,
                      cameras: str | Sequence[str] = "train", threads: int = 2, progress: bool = True,
                      undistorted_dir: str | os.PathLike | None = None) -> dict:
    """``cues/flows/method: files``: a sequence's shipped flows (scene.yaml ``cues/flows/format``; a distorted
    capture's, remapped by rule undistort) in the pipeline's ``out_dir/<cam>/<frame:06d>.exr`` (X, Y, valid).

    Every selected camera needs a file per frame but the first (forward flow from frame t-1 to t, named by
    t): each is checked (size, RAFT's padding, finite values) and an error names the first bad or missing
    file. Returns the counts.
    """
    t_start = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    seq_dir = sequence_source(scene_dir, seq, undistorted_dir, info)
    root = seq_dir / "flows"
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: cues/flows/method is 'files' but the sequence ships no flows/ folder "
                                "(<cam>/<frame>.flo, .png (KITTI) or .exr; scene.yaml cues/flows/format)")
    fmt = shipped_cues.source_format(seq_dir, "flows", cue_formats(info, scene_dir)["flows"]["format"])
    names = select_cameras(info, cameras, scene_dir)
    frames = sequence_frames(seq_dir, names)
    cams = _cameras(seq_dir, names[:1], info)
    shape = (cams.height, cams.width)
    for cam in names:
        have = shipped_cues.cue_frames(root / cam, "flows", fmt)
        missing = [f for f in frames[1:] if f not in have]
        if missing:
            raise FileNotFoundError(f"{root / cam}: no {fmt} flow for frames {missing[:5]} (one file per frame but "
                                    f"the first, <frame>{shipped_cues.CUE_SUFFIX[('flows', fmt)]}: the flow from the "
                                    "frame before to it)")
    log.info("flows %s/%s: shipped %s flows of %d cameras x %d pairs", scene_dir.name, seq, fmt, len(names),
             len(frames) - 1)
    valid_px = 0
    with files.atomic_dir(out_dir) as tmp, ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        def one(job):
            cam, f = job
            fl, ok = shipped_cues.read_flow(root, cam, f, fmt, shape)
            files.write_exr(tmp / cam / f"{f:06d}.exr", np.concatenate(
                [np.where(ok[..., None], fl, 0), ok[..., None]], -1).astype(np.float32), ("X", "Y", "valid"))
            return int(ok.sum())

        jobs = [(c, f) for c in names for f in frames[1:]]
        for n in tqdm(pool.map(one, jobs), total=len(jobs), desc=f"flows {seq}", unit="flow", disable=not progress):
            valid_px += n
    stats = {"method": "files", "format": fmt, "pairs": len(jobs), "wall_s": time.perf_counter() - t_start,
             "valid_fraction": valid_px / max(1, len(jobs) * shape[0] * shape[1])}
    log.info("flows %s/%s: wrote %s in %.1f s (%.0f%% of the pixels valid)", scene_dir.name, seq, out_dir,
             stats["wall_s"], 100 * stats["valid_fraction"])
    return stats


# --------------------------------------------------------------------------- normals


def run_normals(scene_dir: str | os.PathLike, seq: str, normals_dir: str | os.PathLike | None,
                out_json: str | os.PathLike, cameras: str | Sequence[str] = "train",
                reason: str | None = None, undistorted_dir: str | os.PathLike | None = None,
                template_npz: str | os.PathLike | None = None, out_dir: str | os.PathLike | None = None,
                check_frames: int = 4, threads: int = 2) -> dict:
    """The normal cue of a sequence: shipped normal maps checked, their axis convention found, or the skip.

    With a folder (scene.yaml ``cues/normals/format``, :mod:`anidress_core.io.shipped_cues`): every
    selected camera and frame must have a readable map of the image size with finite values (an error
    names the first bad file). The axis convention is found on ``check_frames`` frames spread over the
    sequence: the signed axis permutation that turns the maps into the posed body's rendered normals
    on the pixels where the body is seen (:func:`anidress_core.cues.normals.find_convention`; none
    agreeing is an error). ``out_dir`` given (a captured sequence): every map is written there in the
    pipeline's format and axes, ``<cam>/<frame:06d>.exr``, and the fit reads it; None (synthetic: the
    pipeline's own maps): a convention other than the identity is an error, the folder is used as it is.
    Without a folder (``normals_dir`` None): the stage is skipped, the fitting's normal weight is 0, and
    the record says why. ``out_json`` records the folder the fit reads (``dir``) and the convention.
    """
    t0 = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    seq_dir = sequence_source(scene_dir, seq, undistorted_dir, info)
    names = select_cameras(info, cameras, scene_dir)
    rec = {"scene": scene_dir.name, "sequence": seq, "cameras": names, "code_version": __version__}
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    if normals_dir is None:
        why = reason or f"{seq_dir / 'normals'}: the sequence ships no normal maps"
        log.warning("normals %s/%s skipped: %s; the fitting's normal weight is 0", scene_dir.name, seq, why)
        rec.update(skipped=True, reason=why, dir=None, normal_weight=0.0)
        files.write_json(out_json, rec)
        return rec
    normals_dir = Path(normals_dir)
    fmt = shipped_cues.source_format(normals_dir.parent, "normals", cue_formats(info, scene_dir)["normals"]["format"])
    crops = cue_files.read_crops(normals_dir / shipped_cues.CROPS_FILE) if fmt == "icon" else None
    frames = sequence_frames(seq_dir, names)
    cams = _cameras(seq_dir, names[:1], info)
    shape = (cams.height, cams.width)
    for cam in names:
        have = shipped_cues.cue_frames(normals_dir / cam, "normals", fmt)
        missing = [f for f in frames if f not in have]
        if missing:
            raise FileNotFoundError(f"{normals_dir / cam}: no {fmt} normal map for frames {missing[:5]}")

    def read(job):
        cam, f = job
        return shipped_cues.read_normals(normals_dir, cam, f, fmt, shape, crops)

    # 1. the axis convention, on a few frames spread over the sequence
    pick = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, min(check_frames, len(frames))).round()
                                         .astype(int))]
    prior = ShapePrior(scene_dir, seq, info, template_npz, _cameras(seq_dir, names, info), pick)
    pred, ref, image = [], [], []
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        for k, f in enumerate(pick):
            seen, nb = prior.body_normals(f)
            maps = np.stack(list(pool.map(read, [(c, f) for c in names])))
            sel = seen & (np.linalg.norm(maps, axis=-1) > 0.5)
            pred.append(maps[sel])
            ref.append(nb[sel])
            image.append(k * len(names) + np.nonzero(sel)[0])
    conv = cue_normals.find_convention(np.concatenate(pred), np.concatenate(ref), np.concatenate(image),
                                       where=f"{normals_dir} (scene.yaml cues/normals/format {fmt})")
    identity = bool(np.array_equal(conv.matrix, np.eye(3)))
    log.info("normals %s/%s: %s maps; axis convention (%s) agrees with the posed body at a mean cosine of %.3f over "
             "%d body pixels of %d frames (%.2f needed; next best %.3f, beaten in %.0f%% of the images)",
             scene_dir.name, seq, fmt, cue_normals.describe(conv.matrix), conv.score, conv.pixels, len(pick),
             cue_normals.AGREEMENT, conv.runner_up, 100 * conv.consistency)
    rec.update(skipped=False, reason=None, format=fmt, frames=len(frames), convention=conv.matrix.tolist(),
               convention_axes=cue_normals.describe(conv.matrix), agreement=round(conv.score, 4),
               runner_up=round(conv.runner_up, 4), consistency=round(conv.consistency, 4), check_pixels=conv.pixels,
               check_frames=pick)
    # 2. every map checked; a captured sequence's written in the pipeline's format and axes
    if out_dir is None:
        if not identity or fmt != "exr":
            raise ValueError(f"{normals_dir}: normal maps read in place must be the pipeline's (exr, OpenCV axes); "
                             f"found format {fmt}, axes {cue_normals.describe(conv.matrix)}")
        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            list(pool.map(read, [(c, f) for c in names for f in frames]))
        rec.update(dir=str(normals_dir), source="shipped, used as they are")
    else:
        M = conv.matrix.astype(np.float32)
        with files.atomic_dir(out_dir) as tmp, ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            def write(job):
                cam, f = job
                files.write_exr(tmp / cam / f"{f:06d}.exr", (read(job) @ M.T).astype(np.float32))

            list(pool.map(write, [(c, f) for c in names for f in frames]))
        rec.update(dir=str(out_dir), source=f"shipped {fmt}, converted to exr in OpenCV axes")
    rec["wall_s"] = round(time.perf_counter() - t0, 3)
    log.info("normals %s/%s: %s (%d cameras x %d frames checked, %.1f s)", scene_dir.name, seq, rec["source"],
             len(names), len(frames), rec["wall_s"])
    files.write_json(out_json, rec)
    return rec


# --------------------------------------------------------------------------- evaluation


def evaluate_cues(scene_dir: str | os.PathLike, seq: str, masks_dir: str | os.PathLike | None = None,
                  flows_dir: str | os.PathLike | None = None, normals_dir: str | os.PathLike | None = None,
                  cameras: str | Sequence[str] = "train", frames: Sequence[int] | None = None) -> dict:
    """Compare cues with the synthetic ground truth ``<scene>/<seq>/gt`` (masks, flows, normals).

    Returns the :meth:`CueErrors.summary` dict plus ``cameras`` and ``frames`` counts,
    and the reference rows ``epe_zero_*`` (error of a zero flow: the scale of the motion).
    """
    scene_dir = Path(scene_dir)
    seq_dir = scene_dir / seq
    info = read_scene(scene_dir)
    names = select_cameras(info, cameras, scene_dir)
    all_frames = sequence_frames(seq_dir, names)
    frames = list(frames) if frames is not None else all_frames
    gt = seq_dir / "gt"
    if not gt.is_dir():
        raise FileNotFoundError(f"{gt}: no ground truth (only synthetic scenes have it)")
    acc, zero = cue_eval.CueErrors(), cue_eval.CueErrors()
    for cam in names:
        for f in frames:
            gl = files.read_mask(gt / "masks" / cam / f"{f:06d}.png")
            if masks_dir is not None:
                acc.add_masks(_read_labels(Path(masks_dir) / cam / f"{f:06d}.png", gl.shape), gl)
            if normals_dir is not None:
                n = files.read_exr(Path(normals_dir) / cam / f"{f:06d}.exr")
                acc.add_normals(n[..., :3], files.read_exr(gt / "normals" / cam / f"{f:06d}.exr")[..., :3], gl)
            if flows_dir is not None and f != all_frames[0]:
                prev = all_frames[all_frames.index(f) - 1]
                g = files.read_exr(gt / "flows" / cam / f"{f:06d}.exr")
                p = Path(flows_dir) / cam / f"{f:06d}.exr"
                e = files.read_exr(p)
                if e.shape[-1] < 2 or e.shape[:2] != g.shape[:2]:
                    raise files.ArtifactError(f"{p}: flow must be ({g.shape[0]}, {g.shape[1]}, >=2), got {e.shape}")
                gl0 = files.read_mask(gt / "masks" / cam / f"{prev:06d}.png")
                valid = g[..., 2] > 0.5
                acc.add_flow(e[..., :2], g[..., :2], valid, gl0)
                zero.add_flow(np.zeros_like(g[..., :2]), g[..., :2], valid, gl0)
    out = acc.summary()
    if flows_dir is not None:
        out.update({k.replace("epe_", "epe_zero_", 1): v for k, v in zero.summary().items() if k.startswith("epe_")
                    and k.endswith("_px")})
    out.update(cameras=len(names), frames=len(frames))
    return out


def format_table(rows: list[dict], columns: Sequence[str]) -> str:
    """A GitHub markdown table of ``rows`` (floats with 4 significant digits)."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    lines = ["| " + " | ".join(columns) + " |", "| " + " | ".join("---" for _ in columns) + " |"]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)
