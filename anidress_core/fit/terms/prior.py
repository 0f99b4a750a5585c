"""L_prior (ours, not in the paper): a proximal term towards a reference pose.

mean_v |P_v (x_v - x_v(ref))|^2 (metres^2), P_v = I, or with ``fit/prior_tangential`` the
projection I - n_v n_v^T onto the surface's tangent plane at v (only the material's slide along the
surface counts; the images place the surface), n_v the vertex normal of the frame's start mesh
(``fit/prior_tangent_planes: start``) or of the reference (``reference``). The reference
(``fit/prior_reference``): ``start``, frame 0 only, its start pose (masks and normals cannot
observe a nearly rotationally symmetric garment sliding about the body, and at frame 0 there is
no flow); ``sim``, every frame, the rig's simulated pose of the observed motion at that frame;
``sim_ensemble``, every frame, the mean of the simulations at several bending stiffnesses.
Weight ``fit/weights/prior`` (0 = off, the paper's loss), times a factor s_v per vertex: with
``fit/prior_spread_floor`` the ensemble's (:func:`spread_scale`, mean 1), 1 without. Residual
sqrt(w s_v / V) P (x - x_ref); P is symmetric and idempotent, so its Gauss-Newton block on each vertex
is w s_v / V P.
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


def _scale(pb: "Problem", like: Tensor) -> Tensor | float:
    """(V, 1) the per-vertex factor s_v, or 1.0."""
    return 1.0 if pb.prior_scale is None else pb.prior_scale.to(like.dtype)[:, None]


def value(pb: "Problem", r) -> tuple[float, None]:
    """L_prior at the render ``r`` (0.0 when off: no reference this frame, or weight 0)."""
    if pb.prior is None:
        return 0.0, None
    off = _offset(pb, r.verts)
    return float((_scale(pb, off) * off ** 2).sum()) / r.verts.shape[0], None


def gauss_newton(pb: "Problem", verts: Tensor, blocks: Tensor, gx: Tensor) -> bool:
    """Add w s_v / V P to every vertex's diagonal block and w s_v / V P (x - x_ref) to gx, in place."""
    if pb.prior is None:
        return False
    V = verts.shape[0]
    P = (torch.eye(3, dtype=blocks.dtype, device=blocks.device).expand(V, 3, 3) if pb.prior_proj is None
         else pb.prior_proj.to(blocks.dtype))
    s = _scale(pb, blocks)
    blocks.index_add_(0, pb.rig.layout.diag, pb.w_prior * (s[:, :, None] if torch.is_tensor(s) else s) * P)
    gx += pb.w_prior * s * _offset(pb, verts)
    return True


def reference(pb: "Problem", verts: Tensor, fragments: raster.Fragments) -> Tensor | None:
    """Differentiable L_prior, or None when off."""
    if pb.prior is None:
        return None
    off = _offset(pb, verts)
    return (_scale(pb, off) * off ** 2).sum() / verts.shape[0]


def spread_scale(spread: Tensor, floor: float) -> Tensor:
    """(T, V) float64 L_prior's factor per frame and vertex from an ensemble's spread (ours).

    spread: (T, V) the members' RMS distance from their mean (metres; rule simulate_ensemble).
    s_tv = 1 / (sigma_tv^2 + sigma_0^2), scaled to a mean of 1 over each frame's vertices, sigma_0 =
    ``floor`` times the median of sigma over the sequence: where the members agree their mean pulls
    harder, where they disagree less, and each frame's total weight is that of a uniform L_prior (the
    spread predicts the mean's error: Spearman 0.48-0.77 per tuning scene, studies/fit/README.md
    section 17). A sequence whose members all agree (median 0) gets 1 everywhere.
    """
    if spread.ndim != 2:
        raise ValueError(f"spread_scale: spread must be (T, V), got {tuple(spread.shape)}")
    if not floor > 0:
        raise ValueError(f"spread_scale: floor must be > 0, got {floor}")
    if not bool(torch.isfinite(spread).all()) or bool((spread < 0).any()):
        raise ValueError("spread_scale: spread must be finite and >= 0")
    s2 = spread.double() ** 2
    s0 = floor * float(s2.sqrt().median())
    if s0 <= 0:
        return torch.ones_like(s2)
    s = 1.0 / (s2 + s0 ** 2)
    return s / s.mean(1, keepdim=True)
