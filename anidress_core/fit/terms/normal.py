"""L_normal (the paper's L_N): camera-space normals of the visible faces against the normal maps.

Squared difference of unit vectors (:func:`anidress_core.raster.face_normals_cam`) summed over pixels that are
garment in both the render and the mask (and have a finite normal), divided by the problem's garment pixel count.
Weight ``fit/weights/normal`` (paper: lambda_N = 0.1; the pipeline's: studies/fit/fit_normal_weight.md). A camera
normal is n_cam = s R n (n the world unit normal, R the camera's rotation, s = +-1 turning it towards the camera),
so |n_cam - t|^2 = |n - s R^T t|^2: every pixel's target is taken to world space and the residuals are grouped per
face over all cameras (a face seen by k cameras is one residual, not k); its derivative lives on the face's three
corners.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ... import raster
from ..problem import FrameCues, Linearisation, Problem, Rendered, System

NAME = "normal"


class Targets(NamedTuple):
    """L_normal's state: the frame's normal maps."""

    normals: Tensor  # (C, H, W, 3) float64 camera-space unit normals (0 where none)
    ok: Tensor  # (C, H, W) bool: whole garment pixels (coverage 1) with a normal


class NormalData(NamedTuple):
    face: Tensor  # (U,) faces with normal pixels in some view
    count: Tensor  # (U,) their pixels, all views
    mean_target: Tensor  # (U, 3) mean world-space target (each pixel's s R^T t)


def visible_face_normals(verts: Tensor, faces: Tensor, world_to_cam: Tensor, face: Tensor, cam: Tensor,
                          pair_face: Tensor) -> tuple[Tensor, Tensor]:
    """World-space unit normals (Fu, 3) of the faces ``face`` (Fu,), and for each (camera, face)
    pair -- cameras ``cam`` (U,), ``pair_face`` (U,) indices into ``face`` -- the sign s (U,) that
    turns the normal towards that camera (camera normal = s R n, as :func:`raster.face_normals_cam`)."""
    tri = verts[faces[face]]  # (Fu, 3, 3)
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny ** 0.5)
    E = world_to_cam.to(verts.dtype)
    origin = -torch.einsum("cji,cj->ci", E[:, :3, :3], E[:, :3, 3])  # (C, 3) camera centres
    away = (n[pair_face] * (tri.mean(1)[pair_face] - origin[cam])).sum(-1) > 0
    return n, torch.where(away, -1.0, 1.0).to(verts.dtype)


def normal_corner_jacobian(tri: Tensor) -> tuple[Tensor, Tensor]:
    """World unit normal n = m/|m|, m = (x1 - x0) x (x2 - x0), and d n / d x_k.

    tri (U, 3, 3) corners. Returns n (U, 3) and J (U, 3 [component], 3 [corner], 3 [coordinate]).
    dm/dx0 = [x2 - x1]_x, dm/dx1 = [x0 - x2]_x, dm/dx2 = [x1 - x0]_x;
    d(m/|m|)/dm = (I - n n^T) / |m|.
    """
    x0, x1, x2 = tri.unbind(1)
    m = torch.cross(x1 - x0, x2 - x0, dim=-1)
    ln = m.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    n = m / ln
    A = (torch.eye(3, dtype=tri.dtype, device=tri.device) - n[:, :, None] * n[:, None, :]) / ln[..., None]

    def skew(a):
        x, y, z = a.unbind(-1)
        o = torch.zeros_like(x)
        return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).view(*a.shape[:-1], 3, 3)

    J = torch.stack([A @ skew(x2 - x1), A @ skew(x0 - x2), A @ skew(x1 - x0)], 2)  # (U, 3, 3, 3)
    return n, J


def setup(pb: Problem, cues: FrameCues, given: None) -> Targets | None:
    """On with a weight and normal maps; pixels with a non-finite or zero normal have none."""
    if cues.normals is None or not pb.cfg.weights.normal > 0:
        return None
    n = cues.normals.double()
    ok = torch.isfinite(n).all(-1)
    n = torch.where(ok[..., None], n, torch.zeros_like(n))
    return Targets(n, ok & (n.norm(dim=-1) > 0.5) & (pb.coverage >= 1))


def value(pb: Problem, st: Targets, r: Rendered) -> tuple[float, NormalData]:
    """L_normal at the render ``r``."""
    verts, frags = r.verts, r.fragments
    E = pb.views.world_to_cam
    sel = (frags.face_id >= 0) & st.ok
    c, row, col = sel.nonzero(as_tuple=True)
    f = frags.face_id[c, row, col]
    F = pb.rig.faces.shape[0]
    key, inv, cnt = torch.unique(c * F + f, return_inverse=True, return_counts=True)
    tgt = st.normals[c, row, col]  # (P, 3)
    tsum = torch.zeros(key.shape[0], 3, dtype=tgt.dtype, device=tgt.device).index_add(0, inv, tgt)
    kc, kf = key // F, key % F  # (U,) camera, face of each pair
    face, finv = torch.unique(kf, return_inverse=True)  # (Fu,) faces seen, (U,) pair -> face
    n, s = visible_face_normals(verts, pb.rig.faces, E, face, kc, finv)  # (Fu, 3), (U,)
    Rt = E[kc, :3, :3].to(tgt.dtype)  # (U, 3, 3)
    tw = s[:, None] * torch.einsum("uji,uj->ui", Rt, tsum)  # (U, 3) world-space target sums
    count = torch.zeros(face.shape[0], dtype=tgt.dtype, device=tgt.device).index_add(0, finv, cnt.to(tgt.dtype))
    twf = torch.zeros(face.shape[0], 3, dtype=tgt.dtype, device=tgt.device).index_add(0, finv, tw)
    # sum_p |n_f - t_p|^2 = cnt |n_f|^2 - 2 n_f . sum t + sum |t|^2
    val = float((count * (n * n).sum(-1) - 2 * (n * twf).sum(-1)).sum()) + float((tgt * tgt).sum())
    return val / pb.n_px, NormalData(face, count, twf / count[:, None])


def gauss_newton(pb: Problem, st: Targets, data: NormalData, lin: Linearisation, out: System) -> bool:
    """Add the vertex-space blocks (pairs, 3, 3) and gradient gx (V, 3) in place: per face the
    residual sqrt(count) (n - mean world target) on the face's corners. True if anything was added."""
    w_n = pb.cfg.weights.normal
    if not data.face.numel():
        return False
    fv = pb.rig.faces[data.face]  # (U, 3)
    n, Jn = normal_corner_jacobian(lin.verts[fv])  # (U, 3), (U, 3 comp, 3 corner, 3 coord)
    w = w_n / pb.n_px
    cnt = data.count
    r = n - data.mean_target  # residual sqrt(cnt) r, Jacobian sqrt(cnt) Jn
    # block[k, l] = cnt sum_i Jn[i, k]^T Jn[i, l];  g_k = cnt sum_i Jn[i, k]^T r_i
    blk = torch.einsum("u,uikj,uilm->ukljm", w * cnt, Jn, Jn)  # (U, 3, 3, 3, 3)
    out.blocks.index_add_(0, pb.rig.layout.face_pair[data.face].reshape(-1), blk.reshape(-1, 3, 3))
    gk = torch.einsum("u,uikj,ui->ukj", w * cnt, Jn, r)  # (U, 3 corner, 3)
    out.gx.index_add_(0, fv.reshape(-1), gk.reshape(-1, 3))
    return True


def reference(pb: Problem, st: Targets, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_normal (:func:`raster.render_face_normals`)."""
    E = pb.views.world_to_cam.to(verts.dtype)
    n = raster.render_face_normals(verts, pb.rig.faces, E, fragments)
    sel = (fragments.face_id >= 0) & st.ok
    return ((n - st.normals.to(n.dtype)) ** 2).sum(-1)[sel].sum() / pb.n_px
