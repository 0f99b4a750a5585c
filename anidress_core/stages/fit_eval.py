"""Stage ``fit_eval``: fitted garments measured against the synthetic ground truth.

Writes ``fit_metrics.csv``: per method and frame, vertex RMSE against the ground-truth garment carried onto the
template's vertices, the rig's floor on that frame, Chamfer distance and normal consistency against the
ground-truth mesh, temporal jitter and acceleration error (see :mod:`anidress_core.metrics.mesh`).
"""
from __future__ import annotations

import csv
import functools
import logging
import os
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from ..fit import TERM_NAMES
from ..io import files
from ..io.garment_poses import load_garment_poses
from ..io.rig import read_rig
from ..io.scene import read_scene, scene_cameras

__all__ = ["gt_correspondence", "gt_template_vertices", "run_fit_eval", "FIT_METRIC_COLUMNS"]

log = logging.getLogger("anidress.fit")

FIT_METRIC_COLUMNS = (
    "method", "frame", "vertex_rmse_m", "rig_floor_rmse_m", "chamfer_m", "rig_floor_chamfer_m", "reprojection_px",
    "rig_floor_reprojection_px", "normal_consistency",
    "jitter_m", "gt_jitter_m", "accel_error_m", "loss", *(f"loss_{k}" for k in TERM_NAMES), "iterations", "wall_s",
)


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
                **{f"loss_{k}": float(f.get(f"loss_{k}", np.full(T, np.nan))[t]) for k in TERM_NAMES},
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
