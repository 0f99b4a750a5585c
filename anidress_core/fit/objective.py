"""The fit's loss over all terms: values, the Gauss-Newton system, the autograd reference.

    L = sum_k w_k L_k,   k in silhouette, normal, flow, anchor, prior, collision (:mod:`.terms`)

:func:`evaluate` rasterises a mesh and evaluates every term (no derivatives), keeping what the
Jacobians need; :func:`gauss_newton_system` builds H = sum_k w_k J_k^T J_k and
g = sum_k w_k J_k^T r_k in the bone increments (so that L(d) ~ L + 2 g.d + d.H d) with exact
Jacobians: every residual depends on at most three vertices (a silhouette crossing on its
edge's two end points, a face normal on its face's corners, a flow target or colour on one
vertex), so its derivative w.r.t. those vertices is computed locally (analytically, or by
autograd on the gathered corners), then chained with the projection Jacobian and
dx/d(omega, tau) (linear in the skinning weights). Rasterisation (visibility, which pixels and
edges) is redone at every evaluation and held fixed inside one linearisation (nvdiffrast's
split). :func:`loss_terms` is the same loss through autograd (the terms' references).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .. import raster
from .config import FitConfig, LossWeights
from .jacobians import projection_jacobian, skin_jacobian
from .problem import FlowTargets, FrameCues, Problem, RigParts, Views, make_problem
from .terms import TERMS, Rendered, anchor, collision, flow, normal, prior, silhouette, stretch

__all__ = ["Evaluation", "evaluate", "gauss_newton_system", "total_loss", "loss_terms"]


class Evaluation(NamedTuple):
    """The loss at one mesh (:func:`evaluate`)."""

    loss: float  # weighted total
    terms: dict  # name -> unweighted value (float), every name of TERMS
    verts: Tensor  # (V, 3)
    fragments: raster.Fragments  # occluded fragments of the render
    uv: Tensor  # (C, V, 2)
    data: dict  # name -> what the term's Gauss-Newton block needs (None: nothing)


def total_loss(weights: LossWeights, terms: dict):
    """sum_k w_k L_k of unweighted ``terms`` (floats) with the weights as used."""
    # this grouping (three partial sums) is the optimiser's: LM acceptance compares these floats
    loss = weights.silhouette * terms["silhouette"] + weights.normal * terms["normal"] + weights.flow * terms["flow"]
    loss += weights.prior * terms["prior"] + weights.anchor * terms["anchor"]
    loss += weights.collision * terms["collision"]
    loss += weights.stretch * terms["stretch"]
    return loss


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
        terms[term.NAME], data[term.NAME] = term.value(pb, r)
    return Evaluation(total_loss(pb.cfg.weights, terms), terms, verts, frags, uv, data)


def gauss_newton_system(pb: Problem, ev: Evaluation, transforms: Tensor, jdtype=torch.float64,
                        skin: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """H (P, P) = sum_k w_k/n J_k^T J_k and g (P,) = sum_k w_k/n J_k^T r_k at ``ev``, P = 6 B.

    transforms: (B, 4, 4) the pose of ``ev``. ``jdtype``: dtype of the (3V, P) Jacobian products
    (float64 for the exactness tests, :data:`anidress_core.fit.jacobians.JACOBIAN_DTYPE` in the
    optimiser). Silhouette residuals are chained to the parameters row by row (into H, g
    directly); the others are accumulated in vertex space (3x3 blocks of vertex pairs sharing
    a face, H_x, and g_x, in the order normal, flow, anchor, prior, collision), then
    H += Jx^T H_x Jx, g += Jx^T g_x once. skin: (V, 3, P) :func:`skin_jacobian` at ``transforms`` in
    ``jdtype``, when the caller has it.
    """
    rig = pb.rig
    verts = ev.verts
    V = verts.shape[0]
    Jx = (skin_jacobian(rig, transforms).to(jdtype) if skin is None else skin).reshape(3 * V, -1)  # (3V, P)
    P = Jx.shape[-1]
    _, Puv = projection_jacobian(verts, pb.views)  # (C, V, 2, 3)
    H = torch.zeros(P, P, dtype=torch.float64, device=verts.device)
    g = torch.zeros(P, dtype=torch.float64, device=verts.device)
    lay = rig.layout
    blocks = torch.zeros(lay.crow.numel() and lay.perm.numel() // 9, 3, 3, dtype=torch.float64, device=verts.device)
    gx = torch.zeros(V, 3, dtype=torch.float64, device=verts.device)
    # 1. silhouette, straight into H and g
    silhouette.gauss_newton(pb, ev.data["silhouette"], ev.uv, Puv, Jx, H, g, jdtype)
    # 2.-6. vertex-space terms (this order: the accumulation order of the blocks)
    added = [normal.gauss_newton(pb, ev.data["normal"], verts, Puv, blocks, gx),
             flow.gauss_newton(pb, ev.uv, Puv, blocks, gx),
             anchor.gauss_newton(pb, ev.data["anchor"], Puv, blocks, gx),
             prior.gauss_newton(pb, verts, blocks, gx),
             collision.gauss_newton(pb, verts, blocks, gx),
             stretch.gauss_newton(pb, verts, blocks, gx)]
    if any(added):
        Hx = lay.matrix(blocks.to(jdtype))
        H += (Jx.t() @ (Hx @ Jx)).double()
        g += (Jx.t() @ gx.reshape(-1).to(jdtype)).double()
    return H, g


def loss_terms(rig: RigParts, views: Views, cues: FrameCues, verts: Tensor, flow_targets: FlowTargets | None,
               cfg: FitConfig, fragments: raster.Fragments | None = None, prior_verts: Tensor | None = None,
               anchor_ref: "anchor.AnchorRef | None" = None,
               contacts: "collision.Contacts | None" = None, prior_scale: Tensor | None = None,
               tangent_mesh: Tensor | None = None) -> tuple[Tensor, dict]:
    """Differentiable (autograd) total loss of a mesh ``verts`` (V, 3) and its unweighted terms.

    The same loss :func:`anidress_core.fit.fit_frame` minimises, built from every term's
    ``reference`` (:func:`raster.silhouette`, :func:`raster.render_face_normals`,
    :func:`raster.project_vertices`), for the vertex ablation and to check the Gauss-Newton
    systems. ``fragments``: visibility to hold fixed (default: rasterise ``verts``); ``tangent_mesh``:
    :func:`anidress_core.fit.make_problem`'s (L_prior's tangent planes).
    """
    pb = make_problem(rig, views, cues, flow_targets, cfg, prior_verts, anchor_ref, contacts, prior_scale,
                      tangent_mesh)
    K, E = views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype)
    if fragments is None:
        fragments = raster.occlude(raster.rasterize(verts.detach(), rig.faces, K, E, views.height, views.width,
                                                    with_bary=False),
                                   pb.occluder)
    terms = {}
    for term in TERMS:
        val = term.reference(pb, verts, fragments)
        terms[term.NAME] = val if val is not None else terms["silhouette"].new_zeros(())
    w = cfg.weights
    total = w.silhouette * terms["silhouette"] + w.normal * terms["normal"] + w.flow * terms["flow"]
    total = total + w.prior * terms["prior"] + w.anchor * terms["anchor"]  # (the vertex ablation's grouping)
    total = total + w.collision * terms["collision"]
    total = total + w.stretch * terms["stretch"]
    return total, terms
