"""Geometry errors of fitted meshes against ground truth (DESIGN.md §10).

All distances in metres. Meshes are (V, 3) vertices with (F, 3) triangles; sequences
are (T, V, 3). Functions take torch tensors (CPU or GPU; nearest-neighbour queries run
on the CPU with a k-d tree) and return tensors or floats.

* :func:`vertex_rmse`: per-frame root mean squared vertex distance, for meshes in
  correspondence (same topology, or the prediction's vertices carried onto the ground
  truth, see :func:`barycentric_transfer`).
* :func:`surface_samples` + :func:`chamfer_normal`: symmetric Chamfer distance (mean of
  the point-to-nearest-point distances, both directions averaged, *not* squared) and
  normal consistency (mean |cos| between a sample's face normal and its nearest
  neighbour's, both directions averaged; 1 = perfectly aligned; absolute value because
  a garment is a two-sided sheet, as in Occupancy Networks' definition) between dense
  area-uniform surface samples.
* :func:`temporal_jitter`: mean norm of the second difference of vertex positions per
  frame (``|x[t+1] - 2 x[t] + x[t-1]|``, metres per frame^2), and
  :func:`acceleration_error`: the same of the difference prediction - ground truth (the
  jitter a fit adds on top of the true motion).
* :func:`reprojection_error`: per-frame mean pixel distance between the projections of
  corresponding vertices in a set of cameras (what the images could show of a vertex
  error; occlusion is not modelled: every vertex in front of a camera counts).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..camera import Cameras, project

__all__ = [
    "vertex_rmse",
    "SurfaceSamples",
    "surface_samples",
    "ChamferNormal",
    "chamfer_normal",
    "temporal_jitter",
    "acceleration_error",
    "barycentric_transfer",
    "reprojection_error",
]


def _check_seq(name: str, x: Tensor) -> Tensor:
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"{name}: expected (T, V, 3) or (V, 3), got {tuple(x.shape)}")
    return x


def vertex_rmse(pred: Tensor, gt: Tensor) -> Tensor:
    """Per-frame RMSE (T,): sqrt(mean_v |pred[t, v] - gt[t, v]|^2). pred, gt: (T, V, 3) or (V, 3)."""
    pred, gt = _check_seq("vertex_rmse", pred), _check_seq("vertex_rmse", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"vertex_rmse: shapes differ, {tuple(pred.shape)} vs {tuple(gt.shape)}")
    return ((pred - gt) ** 2).sum(-1).mean(-1).sqrt()


def temporal_jitter(verts: Tensor) -> Tensor:
    """(T - 2,) mean over vertices of |x[t+1] - 2 x[t] + x[t-1]| for t = 1..T-2. verts (T, V, 3)."""
    verts = _check_seq("temporal_jitter", verts)
    if verts.shape[0] < 3:
        return verts.new_zeros(0)
    acc = verts[2:] - 2 * verts[1:-1] + verts[:-2]
    return acc.norm(dim=-1).mean(-1)


def acceleration_error(pred: Tensor, gt: Tensor) -> Tensor:
    """(T - 2,) mean over vertices of the norm of the second difference of pred - gt."""
    pred, gt = _check_seq("acceleration_error", pred), _check_seq("acceleration_error", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"acceleration_error: shapes differ, {tuple(pred.shape)} vs {tuple(gt.shape)}")
    return temporal_jitter(pred - gt)


def barycentric_transfer(verts: Tensor, faces: Tensor, face: Tensor, bary: Tensor) -> Tensor:
    """Points given by (face (N,), barycentrics (N, 3)) on a mesh sequence verts (T, V, 3) or (V, 3).

    Returns (T, N, 3) (or (N, 3)): ``sum_k bary[n, k] verts[..., faces[face[n], k]]``.
    """
    tri = verts[..., faces[face], :]  # (..., N, 3, 3)
    return (bary.to(verts.dtype)[..., :, None] * tri).sum(-2)


class SurfaceSamples(NamedTuple):
    points: Tensor  # (N, 3)
    normals: Tensor  # (N, 3) unit face normals


def surface_samples(verts: Tensor, faces: Tensor, num: int, generator: torch.Generator | None = None) -> SurfaceSamples:
    """``num`` points uniformly distributed over the surface area, with their face normals.

    Faces are drawn with probability proportional to area, points uniformly inside them
    (square-root barycentric sampling). Degenerate faces are never drawn.
    """
    if verts.ndim != 2 or verts.shape[-1] != 3 or faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"surface_samples: verts (V, 3), faces (F, 3) expected, got "
                         f"{tuple(verts.shape)}, {tuple(faces.shape)}")
    tri = verts[faces.long()]  # (F, 3, 3)
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    area = n.norm(dim=-1)
    if not bool(torch.isfinite(area).all()):
        raise ValueError("surface_samples: vertices contain NaN or inf")
    if float(area.sum()) <= 0:
        raise ValueError("surface_samples: the mesh has zero area")
    f = torch.multinomial(area.cpu().double(), num, replacement=True, generator=generator).to(verts.device)
    r = torch.rand(num, 2, generator=generator, dtype=torch.float64).to(verts.device, verts.dtype)
    s = r[:, 0].sqrt()
    b = torch.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], -1)
    pts = (b[:, :, None] * tri[f]).sum(1)
    return SurfaceSamples(pts, n[f] / area[f, None])


class ChamferNormal(NamedTuple):
    chamfer: float  # metres, symmetric mean nearest-neighbour distance
    normal_consistency: float  # mean |cos| in [0, 1]
    a_to_b: float  # mean distance from samples of a to b
    b_to_a: float


def chamfer_normal(a: SurfaceSamples, b: SurfaceSamples) -> ChamferNormal:
    """Symmetric Chamfer distance and normal consistency between two sample sets (see module doc)."""
    from scipy.spatial import cKDTree

    pa, pb = a.points.detach().cpu().double().numpy(), b.points.detach().cpu().double().numpy()
    na, nb = a.normals.detach().cpu().double().numpy(), b.normals.detach().cpu().double().numpy()
    if not (np.isfinite(pa).all() and np.isfinite(pb).all()):
        raise ValueError("chamfer_normal: samples contain NaN or inf")
    if len(pa) == 0 or len(pb) == 0:
        raise ValueError("chamfer_normal: empty sample set")
    dab, iab = cKDTree(pb).query(pa)
    dba, iba = cKDTree(pa).query(pb)
    cab = np.abs((na * nb[iab]).sum(-1)).mean()
    cba = np.abs((nb * na[iba]).sum(-1)).mean()
    return ChamferNormal(float(0.5 * (dab.mean() + dba.mean())), float(0.5 * (cab + cba)), float(dab.mean()),
                         float(dba.mean()))


def reprojection_error(pred: Tensor, gt: Tensor, cams: Cameras) -> Tensor:
    """Mean 2D distance (pixels) per frame between projected corresponding vertices.

    pred, gt (T, V, 3) or (V, 3) in correspondence; cams: C cameras (lens distortion applied).
    A (frame, camera, vertex) counts when both points are in front of the camera.
    Returns (T,); NaN for a frame where no pair counts.
    """
    pred, gt = _check_seq("reprojection_error", pred), _check_seq("reprojection_error", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"reprojection_error: shapes differ, {tuple(pred.shape)} vs {tuple(gt.shape)}")
    cams = cams.to(device=pred.device, dtype=pred.dtype)
    out = []
    for t in range(pred.shape[0]):  # a loop over frames; each frame is one batched projection
        a, b = project(pred[t], cams), project(gt[t], cams)
        ok = (a.depth > 0) & (b.depth > 0)  # (C, V)
        d = (a.uv - b.uv).norm(dim=-1)  # (C, V)
        n = ok.sum()
        out.append(torch.where(ok, d, torch.zeros_like(d)).sum() / n if n > 0 else d.new_tensor(float("nan")))
    return torch.stack(out)
