"""The fit's loss over all terms: the problem, values, the Gauss-Newton system, the autograd reference.

    L = sum_k w_k L_k,   k in :data:`anidress_core.fit.terms.TERMS`

:func:`make_problem` builds one frame's :class:`Problem` and every term's state; :func:`evaluate`
rasterises a mesh and evaluates every term (no derivatives), keeping what the Jacobians need;
:func:`gauss_newton_system` builds H = sum_k w_k J_k^T J_k and g = sum_k w_k J_k^T r_k in the bone
increments (so that L(d) ~ L + 2 g.d + d.H d) with exact Jacobians: every residual depends on at most
three vertices (a silhouette crossing on its edge's two end points, a face normal on its face's corners,
a flow target or colour on one vertex), so its derivative w.r.t. those vertices is computed locally
(analytically, or by autograd on the gathered corners), then chained with the projection Jacobian and
dx/d(omega, tau) (linear in the skinning weights). Rasterisation (visibility, which pixels and edges) is
redone at every evaluation and held fixed inside one linearisation (nvdiffrast's split). :func:`loss_terms`
is the same loss through autograd (the terms' references). Each loops over the terms' one protocol
(:mod:`anidress_core.fit.terms`).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .. import raster
from .config import LossWeights
from .jacobians import projection_jacobian, skin_jacobian
from .problem import (Crop, FrameCues, Linearisation, Problem, Rendered, RigParts, System, Views, check_cues,
                      crop_frame, crop_window, occluder_or_inf)
from .terms import TERM_NAMES, TERMS

__all__ = ["SUM_GROUPS", "Evaluation", "make_problem", "windowed_problem", "evaluate", "gauss_newton_system",
           "total_loss", "loss_terms"]

#: The order of the weighted sum: the terms of each group summed left to right, then the groups (the optimiser's
#: float order: Levenberg-Marquardt's acceptance compares these floats, and stored losses depend on it).
SUM_GROUPS = (("silhouette", "normal", "flow"), ("prior", "anchor"), ("collision",), ("stretch",))


class Evaluation(NamedTuple):
    """The loss at one mesh (:func:`evaluate`)."""

    loss: float  # weighted total
    terms: dict  # name -> unweighted value (float), every name of TERMS
    verts: Tensor  # (V, 3)
    fragments: raster.Fragments  # occluded fragments of the render
    uv: Tensor  # (C, V, 2)
    data: dict  # name -> what the term's Gauss-Newton block needs (None: nothing, or the term is off)


def make_problem(rig: RigParts, views: Views, cues: FrameCues, cfg, **given) -> Problem:
    """The :class:`Problem` of one frame: cues checked, the masks' coverage and garment pixel count, the body's
    depth, and every term's state (its ``setup``; off at weight 0 or without its inputs). ``given``: per term
    name what the caller gives it: ``flow`` (:class:`anidress_core.fit.FlowTargets`), ``anchor``
    (:class:`anidress_core.fit.AnchorRef`), ``prior`` (:class:`anidress_core.fit.terms.prior.Reference`),
    ``collision`` (:class:`anidress_core.fit.Contacts`). cfg: :class:`anidress_core.fit.FitConfig`."""
    unknown = sorted(set(given) - set(TERM_NAMES))
    if unknown:
        raise ValueError(f"make_problem: no term {unknown}; the terms are {TERM_NAMES}")
    check_cues(views, cues)
    soft = cues.mask.double() if cues.mask.is_floating_point() else cues.mask.bool().double()
    soft = torch.where(torch.isfinite(soft), soft.clamp(0, 1), torch.zeros_like(soft))
    n_px = float(max(float(soft.sum()), 1.0))  # the paper's sums over pixels / targets, one common scale
    pb = Problem(rig, views, cfg, soft, n_px, occluder_or_inf(cues, views), {})
    return pb._replace(states={t.NAME: t.setup(pb, cues, given.get(t.NAME)) for t in TERMS})


def windowed_problem(rig: RigParts, views: Views, cues: FrameCues, cfg, around: Tensor, flow=None,
                     **given) -> tuple[Problem, Crop | None]:
    """:func:`make_problem` in the render windows that hold the masks and the points ``around`` (N, 3) grown by
    ``cfg.crop_margin`` (:func:`anidress_core.fit.problem.crop_window`; -1: whole images), and the windows."""
    crop = None
    if cfg.crop_margin >= 0:
        crop = crop_window(views, cues.mask, around, cfg.crop_margin)
        views, cues, flow = crop_frame(views, cues, flow, crop)
    return make_problem(rig, views, cues, cfg, flow=flow, **given), crop


def total_loss(weights: LossWeights, terms: dict):
    """sum_k w_k L_k of unweighted ``terms`` (floats or tensors) with the weights as used, in :data:`SUM_GROUPS`."""
    return sum(sum(getattr(weights, k) * terms[k] for k in group) for group in SUM_GROUPS)


def evaluate(pb: Problem, verts: Tensor) -> Evaluation:
    """Rasterise ``verts`` (V, 3) and evaluate the loss (no derivatives); keeps what the Jacobians need."""
    v = pb.views
    K, E = v.K, v.world_to_cam
    uv, z = raster.project_vertices(verts, K, E)
    frags = raster.occlude(raster.rasterize(verts, pb.rig.faces, K, E, v.height, v.width, with_bary=False),
                           pb.occluder)
    r = Rendered(verts, uv, z, frags)
    terms, data = {}, {}
    for term in TERMS:
        st = pb.states[term.NAME]
        terms[term.NAME], data[term.NAME] = (0.0, None) if st is None else term.value(pb, st, r)
    return Evaluation(total_loss(pb.cfg.weights, terms), terms, verts, frags, uv, data)


def gauss_newton_system(pb: Problem, ev: Evaluation, transforms: Tensor, jdtype=torch.float64,
                        skin: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """H (P, P) = sum_k w_k/n J_k^T J_k and g (P,) = sum_k w_k/n J_k^T r_k at ``ev``, P = 6 B.

    transforms: (B, 4, 4) the pose of ``ev``. ``jdtype``: dtype of the (3V, P) Jacobian products
    (float64 for the exactness tests, :data:`anidress_core.fit.jacobians.JACOBIAN_DTYPE` in the
    optimiser). The terms add to H, g directly (silhouette: row by row) or to vertex space (3x3
    blocks of vertex pairs sharing a face, H_x, and g_x, in the order of :data:`TERMS`), then
    H += Jx^T H_x Jx, g += Jx^T g_x once. skin: (V, 3, P) :func:`skin_jacobian` at ``transforms`` in
    ``jdtype``, when the caller has it.
    """
    rig = pb.rig
    verts = ev.verts
    V = verts.shape[0]
    Jx = (skin_jacobian(rig, transforms).to(jdtype) if skin is None else skin).reshape(3 * V, -1)  # (3V, P)
    P = Jx.shape[-1]
    _, Puv = projection_jacobian(verts, pb.views)  # (C, V, 2, 3)
    lay = rig.layout
    f64 = dict(dtype=torch.float64, device=verts.device)
    out = System(torch.zeros(P, P, **f64), torch.zeros(P, **f64),
                 torch.zeros(lay.crow.numel() and lay.perm.numel() // 9, 3, 3, **f64), torch.zeros(V, 3, **f64))
    lin = Linearisation(verts, ev.uv, Puv, Jx, jdtype)
    added = False
    for term in TERMS:
        st = pb.states[term.NAME]
        if st is not None:
            added |= term.gauss_newton(pb, st, ev.data[term.NAME], lin, out)
    H, g = out.H, out.g
    if added:
        Hx = lay.matrix(out.blocks.to(jdtype))
        H += (Jx.t() @ (Hx @ Jx)).double()
        g += (Jx.t() @ out.gx.reshape(-1).to(jdtype)).double()
    return H, g


def loss_terms(pb: Problem, verts: Tensor, fragments: raster.Fragments | None = None) -> tuple[Tensor, dict]:
    """Differentiable (autograd) total loss of a mesh ``verts`` (V, 3) on the problem ``pb`` and its unweighted
    terms: every term's ``reference``, the loss :func:`evaluate` measures (the vertex ablation minimises it;
    the tests check the Gauss-Newton systems with it). ``fragments``: visibility to hold fixed (default:
    rasterise ``verts``)."""
    v = pb.views
    if fragments is None:
        K, E = v.K.to(verts.dtype), v.world_to_cam.to(verts.dtype)
        fragments = raster.occlude(raster.rasterize(verts.detach(), pb.rig.faces, K, E, v.height, v.width,
                                                    with_bary=False), pb.occluder)
    terms = {}
    for term in TERMS:
        st = pb.states[term.NAME]
        terms[term.NAME] = verts.new_zeros(()) if st is None else term.reference(pb, st, verts, fragments)
    return total_loss(pb.cfg.weights, terms), terms
