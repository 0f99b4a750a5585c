"""Stage `evaluate`: image metrics of the field's renders against the captured images (DESIGN.md §10).

Reads render folders written by :func:`anidress_core.stages.field.run_render` (their
``render.json`` lists frames and cameras) and the sequence's images
``data/<scene>/<seq>/images/<cam>/<frame>.png`` masked (labels > 0) onto the render's
background colour (the field models the subject only, as in the Neural Body protocol), and
``gt/meshes.npz`` for the subject box (else the posed body). The masks, per sequence:

* ``gt/masks`` when the sequence has them (synthetic scenes): ``mask_source`` "gt/masks";
* else the masks the pipeline has (``masks``: {sequence: folder}, the shipped masks or those of
  rule masks, as the field trained on them): ``mask_source`` "pipeline". A captured scene has no
  ground truth: its PSNR / SSIM / LPIPS / DISTS compare with the captured images composited by
  these masks, and its IoU is the agreement of the rendered alpha with them, not an accuracy;
* a camera / frame without either (e.g. test cameras, when rule masks ran on the training cameras
  only, ``cues/cameras: train``): ``mask_source`` "none" and every metric NaN (not scored); a
  pipeline mask without a foreground pixel likewise (``mask_source`` "empty": an estimate that
  failed, e.g. a temporal-median plate of a subject that stays in place, would score an empty
  render as perfect).

Regions: besides the box metrics (``psnr_db`` in the projected subject box, ``ssim`` on its
bounding rectangle), PSNR and SSIM inside the mask's regions (:func:`anidress_core.metrics.image.region_stats`;
SSIM: mean of the per-pixel SSIM map, images mirrored at their borders): subject (labels > 0),
garment (labels == 2), body (labels == 1). A mask whose values are all 0 / 1 / 2 and that has a
garment label or belongs to a scene with a garment (scene.yaml ``garment_template``) carries
the body / garment distinction (``region_masks``: its ``mask_source``); a view where the garment
is hidden then has an empty garment region (NaN). Any other mask (0 / 255, or 0 / 1 in a scene
without a garment) has none: ``region_masks`` "subject only", garment and body NaN.

Writes ``metrics.csv``, one row per (kind, sequence, camera, frame) with columns
``kind, sequence, camera, frame, psnr_db, ssim, iou, lpips, dists, lpips_available,
dists_available, box_source, mask_source, psnr_subject_db, ssim_subject, psnr_garment_db,
ssim_garment, psnr_body_db, ssim_body, region_masks``, and ``metrics_summary.json``: per (kind,
sequence) the mean of every box / IoU / LPIPS / DISTS metric over the scored images, the image
count, the scored count and the mask sources; the region figures ``psnr_<region>_db`` /
``ssim_<region>`` *pooled* over the pixels of the scored images (not means of the per-image
values; see ``region_definition`` in the summary), ``<region>_images`` / ``<region>_empty_images``
(scored images with a non-empty / an empty region), ``subject_only_images`` and ``region_masks``;
``ground_truth`` (whether every scored image had gt/masks), ``sources`` (per sequence the
images and masks folders read) and why LPIPS / DISTS are unavailable when they are (their columns
are then NaN and ``*_available`` is 0 -- never a stand-in).
Renders of library motions have no ground truth and are not evaluated. A sequence whose
cameras have lens distortion is compared in its pinhole working cameras: images and
``gt/masks`` of its undistorted copy (``undistorted``, rule undistort), as the field saw them.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from .. import __version__
from ..io import files
from ..io.scene import image_path, load_body, load_sequence_motion, read_scene, scene_cameras, sequence_source
from ..metrics import image as M

__all__ = ["run_evaluate", "COLUMNS", "read_metrics_csv"]

log = logging.getLogger("anidress.evaluate")

REGIONS = ("subject", "garment", "body")
"""Mask regions scored: labels > 0, == 2, == 1."""
REGION_METRICS = [f"{m}_{r}{u}" for r in REGIONS for m, u in (("psnr", "_db"), ("ssim", ""))]
COLUMNS = ["kind", "sequence", "camera", "frame", "psnr_db", "ssim", "iou", "lpips", "dists", "lpips_available",
           "dists_available", "box_source", "mask_source", *REGION_METRICS, "region_masks"]
SUBJECT_ONLY = "subject only"
"""``region_masks`` of a mask without the body / garment distinction (garment and body NaN)."""
REGION_DEFINITION = (
    "psnr_<region>_db / ssim_<region> of a (kind, sequence): pooled over every pixel of the region in all scored "
    "images (subject: mask labels > 0, garment: == 2, body: == 1; render vs the image composited on the render "
    "background): PSNR = -10 log10(sum of squared error / (3 x pixels)), SSIM = sum of the per-pixel SSIM map "
    "(11x11 Gaussian window, sigma 1.5, centred on the pixel, images mirrored at their borders) / pixels. "
    "Images whose region is empty (<region>_empty_images) or whose mask has no body/garment labels "
    "(subject_only_images) add nothing to it; NaN without a pixel, +inf if every pixel is identical.")
MASK_SOURCES = ("gt/masks", "pipeline", "none", "empty")
"""``mask_source`` of a row: the sequence's ground-truth masks, the pipeline's masks; not scored: no mask, an empty
mask of the pipeline."""


def _subject_points(scene_dir: Path, seq: str, info: dict, frames: Sequence[int],
                    body_dir: str | os.PathLike | None = None) -> tuple[dict, str]:
    """World points of the subject per frame: GT meshes when shipped, else the posed body."""
    gt = scene_dir / seq / "gt" / "meshes.npz"
    if gt.is_file():
        a, _ = files.load_npz(gt, required=("body_vertices",))
        pts = {}
        for f in frames:
            p = [a["body_vertices"][f]]
            if "garment_vertices" in a:
                p.append(a["garment_vertices"][f])
            pts[f] = torch.from_numpy(np.concatenate(p)).float()
        return pts, "gt/meshes.npz"
    body = load_body(scene_dir, info)
    m = load_sequence_motion(scene_dir, seq, info["fps"], body_dir)
    idx = torch.tensor(list(frames))
    v = body.pose(m.poses[idx], m.Rh[idx], m.Th[idx], m.shapes).vertices
    return {f: v[i] for i, f in enumerate(frames)}, "posed body"


def _nan_if_none(x) -> float:
    return float("nan") if x is None else float(x)


def _region_masks(labels: np.ndarray, garment_scene: bool) -> tuple[dict[str, torch.Tensor], bool]:
    """Bool masks (H, W) of the regions of a label mask (H, W) uint8, and whether it has the body /
    garment distinction (values within 0 / 1 / 2, with a 2 or in a scene with a garment); without
    it only the subject."""
    lab = torch.from_numpy(labels)
    values = set(np.unique(labels).tolist())
    labelled = values <= {0, 1, 2} and (2 in values or garment_scene)
    masks = {"subject": lab > 0}
    if labelled:
        masks.update(garment=lab == 2, body=lab == 1)
    return masks, labelled


def run_evaluate(scene_dir: str | os.PathLike, renders: Sequence[tuple[str, str, str | os.PathLike]],
                 out_csv: str | os.PathLike, out_summary: str | os.PathLike, params: dict,
                 lpips=None, dists=None, progress: bool = True,
                 undistorted: Mapping[str, str | os.PathLike] | None = None,
                 masks: Mapping[str, str | os.PathLike] | None = None,
                 bodies: Mapping[str, str | os.PathLike] | None = None) -> dict:
    """Evaluate render folders ``renders``: (kind, sequence, folder) each.

    undistorted: {sequence: folder of rule undistort} for sequences whose cameras have lens
    distortion (:func:`anidress_core.io.scene.sequence_source`).
    masks: {sequence: folder ``<cam>/<frame:06d>.png``} of the pipeline's masks, used for a sequence
    without ``gt/masks`` (in the working cameras: for a distorted sequence, masks of its undistorted
    images). A sequence with neither is evaluated on no image (every row NaN, mask_source "none").
    bodies: {sequence: body poses refined by rule refine_body}, posed for the scoring box of a sequence
    without ``gt/meshes.npz`` (as the renders posed them).

    params: the ``metrics`` config section (``box_pad_m``). lpips / dists: loaded
    models or :class:`anidress_core.metrics.image.Unavailable` (or None: not requested).
    """
    t0 = time.perf_counter()
    scene_dir = Path(scene_dir)
    info = read_scene(scene_dir)
    pad = float(params.get("box_pad_m", 0.05))
    lp_ok, ds_ok = bool(lpips), bool(dists)
    notes = {"lpips": "available" if lp_ok else getattr(lpips, "reason", "not requested"),
             "dists": "available" if ds_ok else getattr(dists, "reason", "not requested")}
    garment_scene = bool(info.get("garment_template"))
    rows, sources = [], {}
    for kind, seq, folder in renders:
        folder = Path(folder)
        rj = files.read_json(folder / "render.json")
        frames, cams_names = rj["frames"], rj["cameras"]
        src = sequence_source(scene_dir, seq, (undistorted or {}).get(seq), info)
        cams = scene_cameras(scene_dir, seq, cams_names, info, seq_dir=src)
        bg = torch.tensor(rj.get("background", [0.0, 0.0, 0.0]), dtype=torch.float32)
        pts, box_source = _subject_points(scene_dir, seq, info, frames, (bodies or {}).get(seq))
        mask_dir, mask_source = src / "gt" / "masks", "gt/masks"
        if not mask_dir.is_dir():
            pipe = (masks or {}).get(seq)
            mask_dir, mask_source = (Path(pipe), "pipeline") if pipe is not None else (None, "none")
        sources[seq] = {"images": str(src / "images"), "masks": None if mask_dir is None else str(mask_dir),
                        "mask_source": mask_source}
        todo = [(f, ci) for f in frames for ci in range(len(cams_names))]
        it = todo
        if progress:
            from tqdm import tqdm
            it = tqdm(todo, desc=f"evaluate {kind} {seq}", unit="img")
        for f, ci in it:
            cam = cams_names[ci]
            pred = torch.from_numpy(files.read_image(folder / "rgb" / cam / f"{f:06d}.png"))
            alpha_u16 = _read_u16(folder / "alpha" / cam / f"{f:06d}.png")
            alpha = torch.from_numpy(alpha_u16.astype(np.float32) / 65535.0)
            img = torch.from_numpy(files.read_image(image_path(src, cam, f)))
            if img.shape != pred.shape:
                raise files.ArtifactError(f"{folder / 'rgb' / cam / f'{f:06d}.png'}: size {tuple(pred.shape)} differs "
                                          f"from the image {tuple(img.shape)} ({src / 'images' / cam})")
            mask_path = None if mask_dir is None else mask_dir / cam / f"{f:06d}.png"
            unscored = None
            if mask_path is None or (mask_source == "pipeline" and not mask_path.is_file()):
                unscored = "none"  # no mask for this image (the captured background is not the render's)
            else:
                labels = files.read_mask(mask_path)
                if labels.shape != tuple(pred.shape[:2]):
                    raise files.ArtifactError(f"{mask_path}: mask size {labels.shape} differs from the render "
                                              f"{tuple(pred.shape[:2])} ({folder / 'rgb' / cam / f'{f:06d}.png'})")
                mask = torch.from_numpy(labels > 0)
                if mask_source == "pipeline" and not bool(mask.any()):
                    unscored = "empty"  # a failed estimate, not a subject out of view
            if unscored:
                rows.append({"kind": kind, "sequence": seq, "camera": cam, "frame": int(f),
                             **{k: float("nan") for k in ("psnr_db", "ssim", "iou", "lpips", "dists")},
                             "lpips_available": int(lp_ok), "dists_available": int(ds_ok), "box_source": box_source,
                             "mask_source": unscored, **{k: float("nan") for k in REGION_METRICS},
                             "region_masks": unscored, "_regions": {}})
                continue
            gt = torch.where(mask[..., None], img, bg)
            H, W = mask.shape
            box = M.subject_box_mask(pts[f], cams.K[ci], cams.world_to_cam[ci], H, W, pad)
            y0, y1, x0, x1 = M.box_rect(box)
            crop_p, crop_g = pred[y0:y1, x0:x1], gt[y0:y1, x0:x1]
            row = {"kind": kind, "sequence": seq, "camera": cam, "frame": int(f),
                   "psnr_db": M.psnr(pred, gt, box), "ssim": M.ssim(crop_p, crop_g), "iou": M.iou(alpha, mask),
                   "lpips": float("nan"), "dists": float("nan"), "lpips_available": int(lp_ok),
                   "dists_available": int(ds_ok), "box_source": box_source, "mask_source": mask_source}
            regions, labelled = _region_masks(labels, garment_scene)
            row["_regions"] = M.region_stats(pred, gt, regions)
            for reg in REGIONS:
                score = M.region_score(row["_regions"].get(reg, M.RegionStats()))
                row[f"psnr_{reg}_db"], row[f"ssim_{reg}"] = score.psnr_db, score.ssim
            row["region_masks"] = mask_source if labelled else SUBJECT_ONLY
            if (lp_ok or ds_ok) and y1 > y0 and x1 > x0:
                a = crop_p.permute(2, 0, 1)[None]
                b = crop_g.permute(2, 0, 1)[None]
                with torch.no_grad():
                    if lp_ok:
                        row["lpips"] = float(lpips(a, b)[0])
                    if ds_ok:
                        row["dists"] = float(dists(a, b)[0])
            rows.append(row)
    # metrics.csv (atomic)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in COLUMNS})
    files.write_text(out_csv, buf.getvalue())
    # summary
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["kind"], r["sequence"]), []).append(r)
    scored = [r for r in rows if r["mask_source"] in ("gt/masks", "pipeline")]
    summary = {"metrics": [], "lpips": notes["lpips"], "dists": notes["dists"], "box_pad_m": pad,
               "ground_truth": bool(scored) and all(r["mask_source"] == "gt/masks" for r in scored),
               "sources": sources, "region_definition": REGION_DEFINITION, "code_version": __version__,
               "wall_s": time.perf_counter() - t0}
    for (kind, seq), rs in groups.items():
        ent = {"kind": kind, "sequence": seq, "images": len(rs),
               "scored": sum(r["mask_source"] in ("gt/masks", "pipeline") for r in rs),
               "mask_sources": sorted({r["mask_source"] for r in rs})}
        for k in ("psnr_db", "ssim", "iou", "lpips", "dists"):
            vals = [r[k] for r in rs if not math.isnan(r[k]) and not math.isinf(r[k])]
            ent[k] = float(np.mean(vals)) if vals else float("nan")
        # region figures pooled over the pixels of the scored images (empty regions add nothing)
        got = [r["_regions"] for r in rs if r["mask_source"] in ("gt/masks", "pipeline")]
        for reg in REGIONS:
            st = [g[reg] for g in got if reg in g]
            ent[f"psnr_{reg}_db"], ent[f"ssim_{reg}"] = M.region_score(sum(st, M.RegionStats()))
            ent[f"{reg}_images"] = sum(s.pixels > 0 for s in st)
            ent[f"{reg}_empty_images"] = sum(s.pixels == 0 for s in st)
        ent["subject_only_images"] = sum(r["region_masks"] == SUBJECT_ONLY for r in rs)
        ent["region_masks"] = sorted({r["region_masks"] for r in rs if r["mask_source"] in ("gt/masks", "pipeline")})
        summary["metrics"].append(ent)
        log.info("%s %s: %d images (%d scored; masks: %s), PSNR %.2f dB (box; subject %.2f, garment %.2f, body %.2f), "
                 "SSIM %.4f, IoU %.4f, LPIPS %s, DISTS %s", kind, seq, len(rs), ent["scored"],
                 ", ".join(ent["mask_sources"]), ent["psnr_db"], ent["psnr_subject_db"], ent["psnr_garment_db"],
                 ent["psnr_body_db"], ent["ssim"], ent["iou"], f"{ent['lpips']:.4f}" if lp_ok else "unavailable",
                 f"{ent['dists']:.4f}" if ds_ok else "unavailable")
    files.write_text(out_summary, json.dumps(summary, indent=1))
    return summary


def _read_u16(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None or m.ndim != 2:
        raise files.ArtifactError(f"{path}: not a single-channel 16-bit alpha PNG")
    return m


def read_metrics_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a ``metrics.csv`` with numbers parsed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    out = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            for k in ("psnr_db", "ssim", "iou", "lpips", "dists", *REGION_METRICS):
                if k in r:  # region columns: absent from older files
                    r[k] = float(r[k])
            for k in ("frame", "lpips_available", "dists_available"):
                r[k] = int(r[k])
            out.append(r)
    return out
