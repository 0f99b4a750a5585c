"""L_prior (ours, not in the paper): frame 0 only, a proximal term towards the start pose.

mean_v |x_v - x_v(start)|^2 (metres^2). Masks and normals cannot observe a nearly rotationally
symmetric garment sliding about the body, and at frame 0 there is no flow; this keeps frame 0
near its start. Weight ``fit/weights/prior`` (0 = off, the paper's loss). Residual
sqrt(w / V) (x - x_start), identity Jacobian on each vertex.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ... import raster

if TYPE_CHECKING:
    from ..problem import Problem

NAME = "prior"


def value(pb: "Problem", r) -> tuple[float, None]:
    """L_prior at the render ``r`` (0.0 when off: frames t > 0 or weight 0)."""
    if pb.prior is None:
        return 0.0, None
    verts = r.verts
    return float(((verts - pb.prior) ** 2).sum()) / verts.shape[0], None


def gauss_newton(pb: "Problem", verts: Tensor, blocks: Tensor, gx: Tensor) -> bool:
    """Add w / V I to every vertex's diagonal block and w / V (x - x_start) to gx, in place."""
    if pb.prior is None:
        return False
    V = verts.shape[0]
    blocks.index_add_(0, pb.rig.layout.diag, pb.w_prior * torch.eye(3, dtype=blocks.dtype, device=blocks.device).expand(V, 3, 3))
    gx += pb.w_prior * (verts - pb.prior)
    return True


def reference(pb: "Problem", verts: Tensor, fragments: raster.Fragments) -> Tensor | None:
    """Differentiable L_prior, or None when off."""
    if pb.prior is None:
        return None
    return ((verts - pb.prior.to(verts.dtype)) ** 2).sum() / verts.shape[0]
