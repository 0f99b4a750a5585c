"""L_silhouette (the paper's L_M): rendered garment coverage against the garment mask.

Hard rasterisation, antialiased at the silhouette edges (:func:`anidress_core.raster.silhouette`;
the body is an occluder, :func:`anidress_core.raster.occlude`) against the garment mask
(label 2): squared difference summed over all pixels of all views whose mask is known
(:attr:`Target.known`), divided by the problem's garment pixel count. Weight ``fit/weights/silhouette``
(paper: lambda_M = 2.0). Every silhouette crossing depends on its edge's two end points, so its derivative is computed
locally by autograd on the gathered end points and chained per pixel (a pixel can collect the
crossings of several edges).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ... import raster
from ..problem import FrameCues, Linearisation, Problem, Rendered, System

NAME = "silhouette"


class Target(NamedTuple):
    """L_silhouette's state: the frame's masks as its residuals read them."""

    mask: Tensor  # (C, H, W) bool garment pixels (coverage > 1/2), the reference's target
    flat: Tensor  # (C H W,) float64 garment coverage in [0, 1] (0 where unknown), the value's target
    known: Tensor | None
    """(C H W,) float64 1 where the mask is known, 0 where it is not (NaN in a float mask: a pixel left out, or
    a whole view dropped by :func:`anidress_core.fit.problem.cue_notes`); None = all known. The residuals are
    multiplied by it (L_normal and L_anchor read only garment pixels, which are known)."""


class SilhouetteData(NamedTuple):
    inside_xy: Tensor
    outside_xy: Tensor
    cam: Tensor
    edge: Tensor  # (N, 2)
    pixel: Tensor  # (N,) pixel whose coverage the crossing changes
    residual: Tensor  # (C H W,) s - m


def setup(pb: Problem, cues: FrameCues, given: None) -> Target:
    """Always on (its value is reported at any weight)."""
    known = torch.isfinite(cues.mask) if cues.mask.is_floating_point() else None
    known = None if known is None or bool(known.all()) else known.reshape(-1).double()
    return Target(pb.coverage > 0.5, pb.coverage.reshape(-1), known)


def value(pb: Problem, st: Target, r: Rendered) -> tuple[float, SilhouetteData]:
    """Hard coverage + (t - 1/2) where each edge crosses (raster.silhouette), against the mask."""
    uv, z, frags = r.uv, r.z, r.fragments
    hard = (frags.face_id >= 0).reshape(-1).double()
    cr = raster.silhouette_crossings(uv, z, pb.rig.faces, frags, pb.rig.edges)
    V = uv.shape[1]
    uvf = uv.reshape(-1, 2)
    t = raster.crossing_fraction(uvf[cr.cam * V + cr.edge[:, 0]], uvf[cr.cam * V + cr.edge[:, 1]], cr.inside_xy,
                                 cr.outside_xy)
    pix = torch.where(t > 0.5, cr.outside, cr.inside)
    soft = hard.index_add(0, pix, t - 0.5)
    res = soft - st.flat
    if st.known is not None:  # unknown mask pixels: no residual
        res = res * st.known
    return float((res * res).sum()) / pb.n_px, SilhouetteData(cr.inside_xy, cr.outside_xy, cr.cam, cr.edge, pix, res)


def crossing_rows(s: SilhouetteData, uv: Tensor, Puv: Tensor, Jx: Tensor, jdtype) -> Tensor:
    """(N, P) derivative of each crossing's fraction t w.r.t. the parameters: dt/dq by autograd on the
    gathered edge end points, chained through Puv (C, V, 2, 3) and Jx (3V, P), in ``jdtype``."""
    V = uv.shape[1]
    P = Jx.shape[-1]
    uvf = uv.reshape(-1, 2)
    with torch.enable_grad():
        q1 = uvf[s.cam * V + s.edge[:, 0]].detach().requires_grad_()
        q2 = uvf[s.cam * V + s.edge[:, 1]].detach().requires_grad_()
        t = raster.crossing_fraction(q1, q2, s.inside_xy, s.outside_xy)
        g1, g2 = torch.autograd.grad(t.sum(), (q1, q2))
    e0, e1 = s.edge[:, 0], s.edge[:, 1]
    a0 = torch.einsum("ni,nij->nj", g1, Puv[s.cam, e0])  # dt/dx_e0 (N, 3)
    a1 = torch.einsum("ni,nij->nj", g2, Puv[s.cam, e1])
    J3 = Jx.view(V, 3, P)
    return torch.einsum("nj,njp->np", a0.to(jdtype), J3[e0]) + torch.einsum("nj,njp->np", a1.to(jdtype), J3[e1])


def gauss_newton(pb: Problem, st: Target, data: SilhouetteData, lin: Linearisation, out: System) -> bool:
    """Add w/n J^T J to H (P, P) and w/n J^T r to g (P,) in place: each crossing's row
    (:func:`crossing_rows`) summed per pixel. Nothing in vertex space: False."""
    w_sil = pb.cfg.weights.silhouette
    if not (w_sil > 0 and data.pixel.numel()):
        return False
    jdtype = lin.jdtype
    Jt = crossing_rows(data, lin.uv, lin.Puv, lin.Jx, jdtype)
    upix, inv = torch.unique(data.pixel, return_inverse=True)
    Jp = torch.zeros(upix.shape[0], Jt.shape[-1], dtype=jdtype, device=Jt.device).index_add(0, inv, Jt)
    if st.known is not None:
        Jp = Jp * st.known[upix].to(jdtype)[:, None]
    w = w_sil / pb.n_px
    out.H.add_(w * (Jp.t() @ Jp).double())
    out.g.add_(w * (Jp.t() @ data.residual[upix].to(jdtype)).double())
    return False


def reference(pb: Problem, st: Target, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_silhouette of ``verts`` (V, 3) with the visibility of ``fragments`` held fixed."""
    views, rig = pb.views, pb.rig
    K, E = views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype)
    s = raster.silhouette(verts, rig.faces, K, E, fragments, rig.edges)
    r = s - st.mask.to(s.dtype)
    if st.known is not None:
        r = r * st.known.view(r.shape).to(r.dtype)
    return (r ** 2).sum() / pb.n_px
