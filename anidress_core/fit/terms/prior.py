"""L_prior (ours, not in the paper): a proximal term towards a reference pose.

mean_v |P_v (x_v - x_v(ref))|^2 (metres^2), P_v = I, or with ``fit/prior_tangential`` the
projection I - n_v n_v^T onto the reference surface's tangent plane at v (only the material's
slide along the surface counts; the images place the surface). The reference
(``fit/prior_reference``): ``start``, frame 0 only, its start pose (masks and normals cannot
observe a nearly rotationally symmetric garment sliding about the body, and at frame 0 there is
no flow); ``sim``, every frame, the rig's simulated pose of the observed motion at that frame.
Weight ``fit/weights/prior`` (0 = off, the paper's loss). Residual sqrt(w / V) P (x - x_ref);
P is symmetric and idempotent, so its Gauss-Newton block on each vertex is w / V P.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ... import raster

if TYPE_CHECKING:
    from ..problem import Problem

NAME = "prior"


def _offset(pb: "Problem", verts: Tensor) -> Tensor:
    """(V, 3) P (x - x_ref)."""
    d = verts - pb.prior.to(verts.dtype)
    if pb.prior_proj is None:
        return d
    return torch.einsum("vij,vj->vi", pb.prior_proj.to(verts.dtype), d)


def value(pb: "Problem", r) -> tuple[float, None]:
    """L_prior at the render ``r`` (0.0 when off: no reference this frame, or weight 0)."""
    if pb.prior is None:
        return 0.0, None
    return float((_offset(pb, r.verts) ** 2).sum()) / r.verts.shape[0], None


def gauss_newton(pb: "Problem", verts: Tensor, blocks: Tensor, gx: Tensor) -> bool:
    """Add w / V P to every vertex's diagonal block and w / V P (x - x_ref) to gx, in place."""
    if pb.prior is None:
        return False
    V = verts.shape[0]
    P = (torch.eye(3, dtype=blocks.dtype, device=blocks.device).expand(V, 3, 3) if pb.prior_proj is None
         else pb.prior_proj.to(blocks.dtype))
    blocks.index_add_(0, pb.rig.layout.diag, pb.w_prior * P)
    gx += pb.w_prior * _offset(pb, verts)
    return True


def reference(pb: "Problem", verts: Tensor, fragments: raster.Fragments) -> Tensor | None:
    """Differentiable L_prior, or None when off."""
    if pb.prior is None:
        return None
    return (_offset(pb, verts) ** 2).sum() / verts.shape[0]
