"""L_flow (the paper's L_of): vertices follow the optical flow from the previous frame.

Projections of the vertices of the previous frame's fitted mesh that are visible in a view and
lie inside its garment mask (t-1), moved by the forward flow t-1 -> t sampled there
(:func:`flow_targets`), are the targets of the same vertices' projections now: squared distance
in pixels summed over (view, vertex) targets, divided by the problem's garment pixel count.
Off at frame 0. Weight ``fit/weights/flow`` (paper: lambda_of = 3.0). Each residual is one
vertex's projection: d uv / d x of that vertex.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ... import raster
from ..images import eroded, pixel_ok, sample
from ..problem import FlowTargets, FrameCues, Linearisation, Problem, Rendered, System, Views

NAME = "flow"


@torch.no_grad()
def flow_targets(prev_verts: Tensor, views: Views, prev_fragments: raster.Fragments, flow: Tensor,
                 flow_valid: Tensor | None, prev_mask: Tensor, depth_tol: float = 0.005,
                 margin: int = 1) -> FlowTargets:
    """Flow-loss targets of frame t from the fitted mesh of frame t-1 (paper eq. L_of).

    prev_verts (V, 3) fitted mesh of t-1; prev_fragments: its :func:`raster.occlude`-d
    fragments (visibility of t-1); flow (C, H, W, 2) forward flow t-1 -> t on frame t-1's
    pixel grid, in pixels; flow_valid (C, H, W) bool or None (all valid); prev_mask
    (C, H, W) garment mask of t-1. A vertex gets a target in a view when it is visible
    there (:func:`raster.visible_vertices`), every pixel within ``margin`` pixels of its
    nearest pixel is garment in the mask and valid in the flow (the bilinear support, and
    no flow mixed in from the body or the background across a boundary), and the
    bilinearly sampled flow is finite: ``target = project(prev_verts) + flow(project(prev_verts))``.
    """
    C, H, W = prev_mask.shape
    if flow.shape != (C, H, W, 2):
        raise ValueError(f"flow_targets: flow must be ({C}, {H}, {W}, 2), got {tuple(flow.shape)}")
    K, E = views.K.to(prev_verts.dtype), views.world_to_cam.to(prev_verts.dtype)
    uv, _ = raster.project_vertices(prev_verts, K, E)  # (C, V, 2)
    vis = raster.visible_vertices(prev_verts, K, E, prev_fragments, depth_tol)  # (C, V)
    good = prev_mask.bool() if not prev_mask.is_floating_point() else prev_mask >= 1
    if flow_valid is not None:
        good = good & flow_valid.bool()
    ok = vis & pixel_ok(eroded(good, margin), uv)  # the whole (2 margin + 1)^2 neighbourhood is good
    fs = sample(flow.permute(0, 3, 1, 2), uv)  # (C, V, 2) bilinear flow at the projections
    ok &= torch.isfinite(fs).all(-1)
    c, v = ok.nonzero(as_tuple=True)
    return FlowTargets(c, v, (uv[c, v] + fs[c, v]).double())


def setup(pb: Problem, cues: FrameCues, given: FlowTargets | None) -> FlowTargets | None:
    """The targets ``given`` (:func:`flow_targets`), when there are some and a weight."""
    return None if given is None or pb.cfg.weights.flow == 0 or given.cam.numel() == 0 else given


def value(pb: Problem, st: FlowTargets, r: Rendered) -> tuple[float, None]:
    """L_flow at the render ``r``."""
    d = r.uv[st.cam, st.vert] - st.target
    return float((d * d).sum()) / pb.n_px, None


def gauss_newton(pb: Problem, st: FlowTargets, data: None, lin: Linearisation, out: System) -> bool:
    """Add the flow residuals' diagonal blocks and gradient in place (d uv / d x of one vertex)."""
    w = pb.cfg.weights.flow / pb.n_px
    r = lin.uv[st.cam, st.vert] - st.target  # (N, 2)
    Pf = lin.Puv[st.cam, st.vert]  # (N, 2, 3)
    out.blocks.index_add_(0, pb.rig.layout.diag[st.vert], w * Pf.transpose(1, 2) @ Pf)
    out.gx.index_add_(0, st.vert, w * torch.einsum("nij,ni->nj", Pf, r))
    return True


def reference(pb: Problem, st: FlowTargets, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_flow."""
    K, E = pb.views.K.to(verts.dtype), pb.views.world_to_cam.to(verts.dtype)
    uv, _ = raster.project_vertices(verts, K, E)
    d = uv[st.cam, st.vert] - st.target.to(uv.dtype)
    return (d * d).sum() / pb.n_px
