"""Stage `undistort`: a captured sequence with lens distortion, undistorted once to pinhole working cameras.

The rasteriser, the cue estimators, the fit, the field and the metrics model pinhole cameras
(:mod:`anidress_core.undistort`). When ``intri.yml`` has non-zero ``dist_<cam>``, this stage
writes the sequence as the pinhole *working* cameras see it, and every later stage reads it
instead of the scene's folder (:func:`anidress_core.io.scene.sequence_source` decides)::

    <out>/images/<cam>/<frame:06d>.png   bilinear; black where the source image does not reach
    <out>/masks/<cam>/<frame:06d>.png    shipped masks, nearest neighbour (0 outside): labels, or a human
                                         parser's label indices (scene.yaml cues/masks/format schp: the
                                         person's file picked, written as plain 8-bit indices)
    <out>/normals/<cam>/<frame:06d>.exr  shipped normal maps of any format (scene.yaml cues/normals), bilinear,
                                         renormalised (0 outside), in the file's own axes
    <out>/flows/<cam>/<frame:06d>.exr    shipped flows of any format (cues/flows): X, Y, valid, the vectors
                                         remapped through the lens (anidress_core.undistort.undistort_flow)
    <out>/gt/masks/<cam>/<frame:06d>.png ground-truth masks, when the sequence has them
    <out>/backgrounds/<cam>.png          recorded background plates (as the images), when present
    <out>/intri.yml, extri.yml           the working cameras: K (the source's), dist 0, H_/W_
    <out>/original_intri.yml             the source intri.yml as it was
    <out>/undistort.json                 the record (cameras, which were distorted, the valid
                                         fraction per camera, frames, what was undistorted)

Cameras: scene.yaml's cameras/train + test (all of intri.yml if it lists none); pinhole
cameras among them are copied unchanged (as PNG). The folder is written into a hidden
temporary sibling and renamed into place at the end: a failure leaves nothing half-written.
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .. import __version__
from ..camera import save_cameras
from ..io import cue_files, files, shipped_cues
from ..io.scene import (IMAGE_EXTS, UNDISTORT_RECORD, distorted_cameras, frame_files, plate_path, read_scene,
                        scene_cameras)
from ..io.scene_info import cue_formats
from ..undistort import (undistort_flow, undistort_image, undistort_labels, undistort_maps, undistort_normals,
                         working_cameras)

log = logging.getLogger("anidress.undistort")

__all__ = ["run_undistort"]


def _frames(d: Path, exts: tuple[str, ...]) -> dict[int, Path]:
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: folder not found")
    return frame_files(d, exts)


def _read_raw(path: Path) -> np.ndarray:
    """An image as stored (uint8 / uint16, BGR order kept: it is written back the same way)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise files.ArtifactError(f"{path}: unreadable or corrupt image")
    return img


def _write_raw(path: Path, img: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise OSError(f"{path}: OpenCV could not write the image")


def run_undistort(scene_dir: str | os.PathLike, seq: str, out_dir: str | os.PathLike, threads: int = 2,
                  progress: bool = True) -> dict:
    """Undistort sequence ``seq`` of the scene into ``out_dir`` (layout in the module docstring).

    Works for a sequence without distortion too (everything copied, the record says so).
    Returns the record written to ``<out_dir>/undistort.json``.
    """
    t0 = time.perf_counter()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    seq_dir = scene_dir / seq
    info = read_scene(scene_dir)
    cams_cfg = info.get("cameras") or {}
    names = list(cams_cfg.get("train") or []) + list(cams_cfg.get("test") or []) or None
    cams = scene_cameras(scene_dir, seq, names, info)
    names = cams.names
    bad = distorted_cameras(scene_dir, seq, info)
    H, W = cams.height, cams.width
    # 1. the working cameras; the maps are made one camera at a time below (a distorted camera's only)
    work = working_cameras(cams)
    # 2. what to undistort: images of every camera; shipped masks / normals and gt masks where present
    jobs = []  # (kind, cam index, source, target)
    fmts = cue_formats(info, scene_dir)
    kinds = {"images": ".png", "masks": ".png", "normals": ".exr", "flows": ".exr", "gt/masks": ".png"}
    have = {}
    for kind, ext in kinds.items():
        root = seq_dir / kind
        have[kind] = root.is_dir() and kind != "images"
        if kind != "images" and not root.is_dir():
            continue
        for ci, cam in enumerate(names):
            if kind != "images" and not (root / cam).is_dir():
                continue  # shipped cues may cover the training cameras only
            if kind == "images":
                fr = _frames(root / cam, IMAGE_EXTS)
            else:
                fr = shipped_cues.cue_frames(root / cam, kind.split("/")[-1],
                                             "labels" if kind == "gt/masks" else fmts[kind]["format"])
            if kind == "images" and not fr:
                raise FileNotFoundError(f"{root / cam}: no <frame>.png/.jpg images")
            jobs += [(kind, ci, (p, f), Path(kind) / cam / f"{f:06d}{ext}") for f, p in fr.items()]
    n_frames = len({j[3].name for j in jobs if j[0] == "images"})
    plates = [(ci, p) for ci, p in ((ci, plate_path(seq_dir, cam)) for ci, cam in enumerate(names)) if p.is_file()]
    jobs += [("images", ci, (p, None), Path("backgrounds") / f"{names[ci]}.png") for ci, p in plates]
    crops = None
    if have["normals"] and fmts["normals"]["format"] == "icon":
        crops = cue_files.read_crops(seq_dir / "normals" / shipped_cues.CROPS_FILE)
    have["backgrounds"] = bool(plates)
    log.info("undistort %s/%s: %d cameras (%s distorted) x %d frames at %dx%d, masks %s, normals %s, flows %s, "
             "gt masks %s", scene_dir.name, seq, len(names), ", ".join(bad) or "none", n_frames, W, H,
             *(fmts[k]["format"] if have[k] else "no" for k in ("masks", "normals", "flows")),
             "yes" if have["gt/masks"] else "no")
    distorted = {names.index(c) for c in bad if c in names}

    def one(job, tmp: Path, maps) -> None:
        """One file of camera ``cam_i``; ``maps``: that camera's alone (index 0), None for a pinhole camera."""
        kind, cam_i, (src, frame), rel = job
        dst = tmp / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        cam = names[cam_i]
        if kind == "normals":
            n = shipped_cues.read_normals(seq_dir / "normals", cam, frame, fmts["normals"]["format"], (H, W), crops)
            files.write_exr(dst, undistort_normals(n, maps, 0) if cam_i in distorted else n)
            return
        if kind == "flows":
            fl, ok = shipped_cues.read_flow(seq_dir / "flows", cam, frame, fmts["flows"]["format"], (H, W))
            if cam_i in distorted:
                fl, ok = undistort_flow(fl, ok, maps, 0, cams.K[cam_i], cams.dist[cam_i])
            files.write_exr(dst, np.concatenate([np.where(ok[..., None], fl, 0), ok[..., None]], -1).astype(np.float32),
                            ("X", "Y", "valid"))
            return
        if kind == "masks" and fmts["masks"]["format"] == "schp":  # label indices: the person's file, plain layout
            m, _ = cue_files.read_schp_indices(seq_dir / "masks", cam, frame, fmts["masks"]["person"])
            if m.shape != (H, W):
                raise files.ArtifactError(f"{src}: mask is {m.shape[1]}x{m.shape[0]}, the images are {W}x{H}")
            _write_raw(dst, undistort_labels(m, maps, 0) if cam_i in distorted else m)
            return
        if kind in ("masks", "gt/masks"):
            m = files.read_mask(src)
            if m.shape != (H, W):
                raise files.ArtifactError(f"{src}: mask is {m.shape[1]}x{m.shape[0]}, the images are {W}x{H}")
            files.write_mask(dst, undistort_labels(m, maps, 0) if cam_i in distorted else m)
            return
        if cam_i not in distorted and src.suffix.lower() == ".png":
            shutil.copyfile(src, dst)
            return
        img = _read_raw(src)
        if img.shape[:2] != (H, W):
            raise files.ArtifactError(f"{src}: image is {img.shape[1]}x{img.shape[0]}, expected {W}x{H}")
        _write_raw(dst, undistort_image(img, maps, 0) if cam_i in distorted else img)

    with files.atomic_dir(out_dir) as tmp:
        # 3. remap every file, one camera at a time with its maps (OpenCV releases the GIL: threads share the
        #    camera's files)
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=len(jobs), desc=f"undistort {seq}", unit="file")
        valid_fraction = {}
        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            for ci, cam in enumerate(names):
                maps = undistort_maps(cams.K[ci:ci + 1], cams.dist[ci:ci + 1], H, W) if ci in distorted else None
                valid_fraction[cam] = 1.0 if maps is None else round(float(maps.valid[0].mean()), 6)
                for _ in pool.map(lambda job: one(job, tmp, maps), [j for j in jobs if j[1] == ci]):
                    if bar is not None:
                        bar.update()
                del maps
        if bar is not None:
            bar.close()
        # 4. the working cameras, the original intrinsics, the record (last: it marks a complete folder)
        save_cameras(work, tmp / "intri.yml", tmp / "extri.yml")
        shutil.copyfile(seq_dir / "intri.yml", tmp / "original_intri.yml")
        rec = {"scene": scene_dir.name, "sequence": seq, "source": str(seq_dir), "cameras": names,
               "distorted": bad, "image_size": [H, W], "frames": n_frames,
               "working_camera": "pinhole, the source K, zero distortion, the same image size",
               "valid_fraction": valid_fraction,
               "undistorted": ["images"] + [k for k in ("masks", "normals", "flows", "gt/masks", "backgrounds")
                                            if have[k]],
               "formats": {k: ("exr" if k != "masks" else fmts[k]["format"]) for k in ("masks", "normals", "flows")
                           if have[k]},
               "files": len(jobs), "wall_s": round(time.perf_counter() - t0, 3), "code_version": __version__}
        files.write_json(tmp / UNDISTORT_RECORD, rec)
    log.info("undistort %s/%s: %d files -> %s in %.1f s", scene_dir.name, seq, len(jobs), out_dir, rec["wall_s"])
    return rec
