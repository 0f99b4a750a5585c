"""L_prior (ours, not in the paper): a proximal term towards a reference pose.

mean_v |P_v (x_v - x_v(ref))|^2 (metres^2), P_v = I, or with ``fit/prior_tangential`` the projection I - n_v n_v^T
onto the surface's tangent plane at v (only the material's slide along the surface counts; the images place the
surface), n_v the vertex normal of the frame's start mesh (``fit/prior_tangent_planes: start``) or of the reference
(``reference``). The reference (``fit/prior_reference``): ``start``, frame 0 only, its start pose; ``sim``, every
frame, the rig's simulated pose of the observed motion at that frame; ``sim_ensemble``, every frame, the mean of
the simulations at several bending stiffnesses. Weight ``fit/weights/prior`` (0 = off, the paper's loss), times a
factor s_v per vertex: with ``fit/prior_spread_floor`` the ensemble's (:func:`spread_scale`, mean 1), 1 without.
Residual sqrt(w s_v / V) P (x - x_ref); P is symmetric and idempotent, so its Gauss-Newton block on each vertex is
w s_v / V P.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ... import raster
from ...geometry import vertex_normals
from ..problem import FrameCues, Linearisation, Problem, Rendered, System

NAME = "prior"


class Reference(NamedTuple):
    """What the caller gives L_prior for a frame."""

    verts: Tensor  # (V, 3) the reference mesh (frame 0's start, or the simulated pose)
    scale: Tensor | None = None  # (V,) the factor s_v per vertex (:func:`spread_scale`), or None (1)
    planes: Tensor | None = None  # (V, 3) the mesh whose vertex normals give the tangent planes (None: ``verts``)


class Pull(NamedTuple):
    """L_prior's state."""

    verts: Tensor  # (V, 3) float64 the reference mesh
    weight: float  # weights.prior / V
    proj: Tensor | None  # (V, 3, 3) I - n n^T at the tangent planes' vertex normals (tangential), or None
    scale: Tensor | None  # (V,) float64 s_v, or None (1)


def setup(pb: Problem, cues: FrameCues, given: Reference | None) -> Pull | None:
    """On with a weight and a reference ``given``; its tangent planes (``fit/prior_tangential``) are those of the
    area-weighted vertex normals of ``given.planes`` (zero at isolated vertices: their offset counts whole)."""
    V = pb.rig.rest.shape[0]
    if given is None or pb.cfg.weights.prior == 0:
        return None
    ref = given.verts.detach().double()
    proj = None
    if pb.cfg.prior_tangential:
        n = vertex_normals(ref if given.planes is None else given.planes.detach().to(ref), pb.rig.faces)  # (V, 3)
        proj = torch.eye(3, dtype=ref.dtype, device=ref.device) - n[:, :, None] * n[:, None, :]
    scale = None
    if given.scale is not None:
        scale = torch.as_tensor(given.scale, device=ref.device).double()
        if scale.shape != (V,) or not bool(torch.isfinite(scale).all()) or bool((scale < 0).any()):
            raise ValueError(f"L_prior: the factor per vertex must be ({V},), finite and >= 0, got "
                             f"{tuple(scale.shape)}")
    return Pull(ref, pb.cfg.weights.prior / V, proj, scale)


def _offset(st: Pull, verts: Tensor) -> Tensor:
    """(V, 3) P (x - x_ref)."""
    d = verts - st.verts.to(verts.dtype)
    return d if st.proj is None else torch.einsum("vij,vj->vi", st.proj.to(verts.dtype), d)


def _scale(st: Pull, like: Tensor) -> Tensor | float:
    """(V, 1) the per-vertex factor s_v, or 1.0."""
    return 1.0 if st.scale is None else st.scale.to(like.dtype)[:, None]


def value(pb: Problem, st: Pull, r: Rendered) -> tuple[float, None]:
    """L_prior at the render ``r`` (:func:`reference`'s value)."""
    return float(reference(pb, st, r.verts, r.fragments)), None


def gauss_newton(pb: Problem, st: Pull, data: None, lin: Linearisation, out: System) -> bool:
    """Add w s_v / V P to every vertex's diagonal block and w s_v / V P (x - x_ref) to gx, in place."""
    blocks = out.blocks
    V = lin.verts.shape[0]
    P = (torch.eye(3, dtype=blocks.dtype, device=blocks.device).expand(V, 3, 3) if st.proj is None
         else st.proj.to(blocks.dtype))
    s = _scale(st, blocks)
    blocks.index_add_(0, pb.rig.layout.diag, st.weight * (s[:, :, None] if torch.is_tensor(s) else s) * P)
    out.gx.add_(st.weight * s * _offset(st, lin.verts))
    return True


def reference(pb: Problem, st: Pull, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_prior."""
    off = _offset(st, verts)
    return (_scale(st, off) * off ** 2).sum() / verts.shape[0]


def spread_scale(spread: Tensor, floor: float) -> Tensor:
    """(T, V) float64 L_prior's factor per frame and vertex from an ensemble's spread (ours).

    spread: (T, V) the members' RMS distance from their mean (metres; rule simulate_ensemble).
    s_tv = 1 / (sigma_tv^2 + sigma_0^2), scaled to a mean of 1 over each frame's vertices, sigma_0 =
    ``floor`` times the median of sigma over the sequence: where the members agree their mean pulls
    harder, where they disagree less, and each frame's total weight is that of a uniform L_prior
    (studies/fit/README.md section 17). A sequence whose members all agree (median 0) gets 1 everywhere.
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
