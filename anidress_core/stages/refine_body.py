"""Stage refine_body: a sequence's body poses refined against its label masks (issue 24 item 5).

Reads ``<scene>/<seq>/smpl/`` (EasyMocap), the cameras (pinholes, or the sequence undistorted by rule
undistort) and label masks ``<masks_dir>/<cam>/<frame:06d>.png`` (0 background, 1 body, 2 garment;
default ``<scene>/<seq>/masks`` or the undistorted copy's; the cue stage's
``results/<scene>/<seq>/masks`` works too), refines the poses with
:func:`anidress_core.body.refine.refine_body_poses` in chunks of ``chunk`` frames, and writes

    <out>/smpl/<frame:06d>.json   refined poses (EasyMocap json, poses of 72 with a zero root; shapes as read)
    <out>/refine_body.json        settings, per chunk: loss terms before/after, seconds; body silhouette IoU
                                  (body pixels, garment pixels ignored) before and after
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..body.refine import RefineConfig, refine_body_poses, silhouette_iou
from ..io import files
from ..io.motion import write_easymocap_smpl_dir
from ..io.scene import load_body, load_sequence_motion, scene_cameras, sequence_source
from ..io.scene_info import read_scene, select_cameras

__all__ = ["run_refine_body"]


def _frame_numbers(smpl_dir: Path) -> list[int]:
    return sorted(int(p.stem) for p in smpl_dir.glob("*.json") if p.stem.isdigit())


def run_refine_body(scene_dir: str | os.PathLike, seq: str, out: str | os.PathLike, masks_dir: str | None = None,
                    undistorted_dir: str | os.PathLike | None = None, chunk: int = 16, max_frames: int | None = None,
                    cfg: RefineConfig = RefineConfig(), threads: int = 1,
                    cameras: str | Sequence[str] = "all") -> dict:
    """Refine the body poses of ``seq``; write ``out``/smpl and ``out``/refine_body.json. Returns the record.

    undistorted_dir: the sequence undistorted to pinhole cameras (rule undistort) when the scene's cameras
    have lens distortion (:func:`anidress_core.io.scene.sequence_source`); its cameras and, by default,
    its ``masks/`` are read (the body motion is the scene's ``smpl/``). cameras: the views refined
    against, ``all``, ``train`` (the scene's training cameras; the pipeline passes cues/cameras, the
    cameras its masks cover) or a list of names.
    """
    torch.set_num_threads(max(1, int(threads)))
    scene_dir, out = Path(scene_dir), Path(out)
    info = read_scene(scene_dir)
    src = sequence_source(scene_dir, seq, undistorted_dir, info)
    cams = scene_cameras(scene_dir, seq, select_cameras(info, cameras, scene_dir), info=info, dtype=torch.float32,
                         seq_dir=src)
    if cams.dist is not None and bool((cams.dist != 0).any()):
        raise ValueError(f"{src / 'intri.yml'}: dist_<cam> is not zero; refine_body needs pinhole cameras "
                         "(rule undistort)")
    motion = load_sequence_motion(scene_dir, seq, float(info.get("fps", 30.0)))
    frames = _frame_numbers(scene_dir / seq / "smpl")
    if len(frames) != motion.poses.shape[0]:
        raise ValueError(f"{scene_dir / seq / 'smpl'}: {len(frames)} frame files but "
                         f"{motion.poses.shape[0]} frames read")
    T = len(frames) if max_frames is None else min(len(frames), int(max_frames))
    body = load_body(scene_dir, info)
    mdir = src / "masks" if masks_dir is None else Path(masks_dir)
    H, W = int(cams.height), int(cams.width)

    def read(t: int) -> np.ndarray:
        m = np.stack([files.read_mask(mdir / cam / f"{frames[t]:06d}.png") for cam in cams.names])
        if m.shape[1:] != (H, W):
            raise ValueError(f"{mdir / cams.names[0] / f'{frames[t]:06d}.png'}: size {m.shape[1:]}, "
                             f"cameras say {(H, W)}")
        return m

    masks = torch.from_numpy(np.stack([read(t) for t in range(T)]))  # (T, C, H, W)
    P, R, Th = motion.poses[:T], motion.Rh[:T], motion.Th[:T]
    K, E = cams.K, cams.world_to_cam
    outP, outR, outT, chunks = [], [], [], []
    t0 = time.perf_counter()
    for a in range(0, T, chunk):  # chunks bound the memory (T x C x V projections per step)
        b = min(T, a + chunk)
        r = refine_body_poses(body, K, E, masks[a:b], P[a:b], R[a:b], Th[a:b], motion.shapes, cfg)
        outP.append(r.poses), outR.append(r.Rh), outT.append(r.Th)
        chunks.append({"frames": [frames[a], frames[b - 1]], "seconds": r.seconds, "terms_before": r.terms_before,
                       "terms_after": r.terms_after})
    seconds = time.perf_counter() - t0
    Pn, Rn, Tn = torch.cat(outP), torch.cat(outR), torch.cat(outT)
    iou_before = silhouette_iou(body, K, E, masks, P, R, Th, motion.shapes)
    iou_after = silhouette_iou(body, K, E, masks, Pn, Rn, Tn, motion.shapes)
    rec = {
        "scene_dir": str(scene_dir), "sequence": seq, "method": cfg.method, "masks_dir": str(mdir), "frames": T,
        "cameras": list(cams.names),
        "config": dataclasses.asdict(cfg), "chunk": chunk, "seconds": seconds, "seconds_per_frame": seconds / max(T, 1),
        "body_iou_before": iou_before, "body_iou_after": iou_after, "chunks": chunks,
    }
    with files.atomic_dir(out) as tmp:  # a failure leaves nothing half-written
        write_easymocap_smpl_dir(tmp / "smpl", Pn, Rn, Tn, motion.shapes.double(), start_frame=0)
        # frame numbers as read (write_easymocap_smpl_dir numbers from start_frame; rename when not 0..T-1)
        if frames[:T] != list(range(T)):
            for i in reversed(range(T)):
                (tmp / "smpl" / f"{i:06d}.json").rename(tmp / "smpl" / f"{frames[i]:06d}.json.tmp")
            for p in (tmp / "smpl").glob("*.json.tmp"):
                p.rename(p.with_suffix(""))
        files.write_text(tmp / "refine_body.json", json.dumps(rec, indent=1) + "\n")
    return rec
