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
``fit/prior_information`` in (0, 1] (:func:`information_scale`), with ``fit/prior_spread_floor`` the
ensemble's (:func:`spread_scale`, mean 1), their product, 1 without. Residual sqrt(w s_v / V) P (x - x_ref);
P is symmetric and idempotent, so its Gauss-Newton block on each vertex is w s_v / V P.
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


def information_scale(pb: "Problem", info: Tensor) -> Tensor:
    """(V,) float64 the factor s_v of L_prior's weight where the images already place the material.

    info: (V, 3, 3) the weighted Gauss-Newton blocks that image terms with one vertex per residual
    (L_anchor, L_flow) put on each vertex. Per vertex the information along the directions L_prior
    counts, i_v = tr(P_v info_v) / rank(P_v) (P_v the tangent projector, or I); per bone b its
    skinning-weighted mean i_b = sum_v W_vb i_v / sum_v W_vb; the bone's factor is L_prior's share
    of the information s_b = p / (p + i_b), p = w / V (L_prior's own per vertex and direction), so
    s_b ~ 1 where the images say nothing about where the material is and ~ p / i_b where they do;
    s_v = sum_b W_vb s_b. Terms whose residuals couple vertices (L_silhouette, L_normal) are not
    counted: they place the surface and its orientation, not the material along it.
    """
    V = info.shape[0]
    P = (torch.eye(3, dtype=torch.float64, device=info.device).expand(V, 3, 3) if pb.prior_proj is None
         else pb.prior_proj.double())
    rank = P.diagonal(dim1=-2, dim2=-1).sum(-1).round().clamp_min(1)  # 2 (tangent plane) or 3
    i_v = (P * info.double()).sum((-2, -1)) / rank  # tr(P info) for symmetric P
    W = pb.rig.weights.double()  # (V, B)
    i_b = (W * i_v[:, None]).sum(0) / W.sum(0).clamp_min(1e-12)
    p = float(pb.w_prior)
    s_b = p / (p + i_b.clamp_min(0))
    return (W @ s_b).clamp(0, 1)


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


def member_weights(scores: Tensor, temperature: float, window: int) -> Tensor:
    """(M, T) float64 each ensemble member's weight per frame from how well it explains the images (ours).

    scores: (M, T) each member's image loss per frame (e.g. L_silhouette + L_normal of its rig pose,
    :func:`anidress_core.fit.proposals.score_poses`); lower is better. Summed over the frames within
    ``window`` of t (the sequence's ends repeated), then w_mt = softmax_m(-(s_mt - min_m s_mt) / (temperature
    * std_m s_mt)), std the sample standard deviation; temperature 0: the lowest member alone. Each column
    sums to 1. A frame whose members all score alike (std 0) weighs them equally; non-finite scores raise.
    The images pick the members that match the outline; their weighted mean was closer to the truth than
    the plain mean on 7 of 10 tuning scenes (studies/fit/README.md section 21).
    """
    if scores.ndim != 2 or scores.shape[0] < 1:
        raise ValueError(f"member_weights: scores must be (M >= 1, T), got {tuple(scores.shape)}")
    if not (temperature >= 0 and window >= 0 and int(window) == window):
        raise ValueError(f"member_weights: temperature must be >= 0 and window an integer >= 0, got "
                         f"{temperature}, {window}")
    if not bool(torch.isfinite(scores).all()):
        raise ValueError("member_weights: scores must be finite")
    M, T = scores.shape
    s = scores.double()
    if window > 0:
        idx = (torch.arange(T)[:, None] + torch.arange(-window, window + 1)[None]).clamp(0, T - 1)  # (T, 2w+1)
        s = s[:, idx].sum(-1)
    if temperature == 0:
        best = s.argmin(0)  # (T,)
        return torch.nn.functional.one_hot(best, M).T.double()
    spread = s.std(0) if M > 1 else torch.zeros(T, dtype=s.dtype)  # (T,), with Bessel's correction
    z = (s - s.min(0).values) / (temperature * spread).where(spread > 0, torch.ones_like(spread))
    return torch.softmax(-z.where(spread > 0, torch.zeros_like(z)), 0)


def weighted_members(members: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The members' weighted mean (T, V, 3) and RMS distance from it (T, V) (ours).

    members: (M, T, V, 3) the ensemble's simulations; weights: (M, T), each column summing to 1
    (:func:`member_weights`; 1/M everywhere gives the plain mean and spread of rule simulate_ensemble).
    """
    if members.ndim != 4 or members.shape[-1] != 3 or weights.shape != members.shape[:2]:
        raise ValueError(f"weighted_members: members must be (M, T, V, 3) and weights (M, T), got "
                         f"{tuple(members.shape)}, {tuple(weights.shape)}")
    w = weights.to(members.dtype)
    mean = (w[..., None, None] * members).sum(0)
    spread = (w[..., None] * ((members - mean) ** 2).sum(-1)).sum(0).clamp_min(0).sqrt()
    return mean, spread
