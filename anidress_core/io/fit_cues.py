"""The cue files the garment fit reads per frame (rule fit; :mod:`anidress_core.stages.fit`).

Per selected camera ``<cam>`` and frame ``t``: ``<masks_dir>/<cam>/<t:06d>.png`` (labels, garment = 2),
``<normals_dir>/<cam>/<t:06d>.exr`` (camera-space unit normals), ``<flows_dir>/<cam>/<t:06d>.exr`` (channels X, Y,
valid: forward flow t-1 -> t on frame t-1's grid, :func:`anidress_core.io.cue_files.read_flow`) and, with L_anchor
on, the sequence's images (:func:`anidress_core.io.images.image_path`). Read as :class:`anidress_core.fit.FrameCues`
and flow arrays on the fit's device.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from .. import fit as FIT
from ..synth import LABEL_GARMENT
from . import files
from .cue_files import read_flow
from .images import image_path

__all__ = ["CueReader"]

log = logging.getLogger("anidress.fit")


class CueReader:
    """Reads one frame's cues for the selected cameras (the only file access of the fit; the files: see the module).

    cams: the selected cameras; masks_dir, normals_dir, flows_dir: the folders (normals, flows: None, that term
    off); body_verts (T, Vb, 3) and body_faces: the posed body, rasterised as the occluder; views:
    :class:`anidress_core.fit.Views` of ``cams``; num_frames: the last frame read ahead; seq_dir: the sequence
    folder whose images L_anchor reads (None: not read). ``cues(t)`` -> :class:`anidress_core.fit.FrameCues`,
    ``flow(t)`` -> (flow, valid) of t-1 -> t or None; ``close()`` stops the helper thread, which reads the files of
    frame t + 1 while frame t is fitted. Non-finite normals and flow vectors are left out (counted in
    ``bad_values``).
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
