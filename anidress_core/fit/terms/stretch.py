"""L_stretch (ours, not in the paper): the fitted garment keeps its rest edge lengths.

The mean over the template's edges of the squared relative stretch ((|x_a - x_b| - l_ab) / l_ab)^2, l_ab the rest
length (dimensionless): the rig's bones can slide the material along the surface only by stretching the edges
between them, which no image sees on a plain fabric. Weight ``fit/weights/stretch``. Residual sqrt(w / E) r_ab,
Jacobian u^T / l_ab on x_a and -u^T / l_ab on x_b (u the unit edge direction); its Gauss-Newton blocks fill the
(a, a), (b, b), (a, b), (b, a) pairs of the vertex-space pattern (every edge lies on a face).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ... import raster
from ..problem import FrameCues, HessianLayout, Linearisation, Problem, Rendered, System

NAME = "stretch"


class Edges(NamedTuple):
    """L_stretch's edges: vertex ids, rest lengths, and their pairs in the Gauss-Newton pattern."""

    a: Tensor  # (E,) int64
    b: Tensor  # (E,) int64
    rest: Tensor  # (E,) float64 rest length (m)
    pair_ab: Tensor  # (E,) the (a, b) pair of HessianLayout
    pair_ba: Tensor  # (E,) the (b, a) pair


def rest_edges(rest: Tensor, edges: Tensor, edge_faces: Tensor, faces: Tensor, layout: HessianLayout) -> Edges:
    """The :class:`Edges` of the mesh ``rest`` (V, 3) with unique ``edges`` (E, 2), one face of each
    ``edge_faces[:, 0]`` (E,) in ``faces`` (F, 3); edges of zero rest length are left out."""
    a, b = edges[:, 0], edges[:, 1]
    fid = edge_faces[:, 0]
    f = faces[fid]  # (E, 3)
    ka = (f == a[:, None]).long().argmax(1)
    kb = (f == b[:, None]).long().argmax(1)
    ab, ba = layout.face_pair[fid, ka, kb], layout.face_pair[fid, kb, ka]
    length = (rest[a] - rest[b]).norm(dim=-1).double()
    keep = length > 0
    return Edges(a[keep], b[keep], length[keep], ab[keep], ba[keep])


def residual(edges: Edges, verts: Tensor) -> tuple[Tensor, Tensor]:
    """(E,) relative stretch (|x_a - x_b| - l) / l of ``verts`` (V, 3), and (E, 3) the unit edge directions."""
    d = verts[edges.a] - verts[edges.b]
    n = d.norm(dim=-1)
    u = d / n.clamp_min(1e-12)[:, None]
    rest = edges.rest.to(verts.dtype)
    return (n - rest) / rest, u


def setup(pb: Problem, cues: FrameCues, given: None) -> Edges | None:
    """The rig's edges (:func:`rest_edges`), with a weight."""
    rig = pb.rig
    return rest_edges(rig.rest, *rig.edges, rig.faces, rig.layout) if pb.cfg.weights.stretch > 0 else None


def value(pb: Problem, st: Edges, r: Rendered) -> tuple[float, None]:
    """L_stretch at the render ``r``."""
    return float(residual(st, r.verts)[0].pow(2).mean()), None


def gauss_newton(pb: Problem, st: Edges, data: None, lin: Linearisation, out: System) -> bool:
    """Add w/E uu^T / l^2 to the (a, a), (b, b) blocks, its negative to (a, b), (b, a), and
    +-w/E r u / l to gx, in place."""
    verts, e = lin.verts, st
    s, u = residual(e, verts)
    inv = 1.0 / e.rest.to(verts.dtype)
    c = pb.cfg.weights.stretch / s.numel()
    uu = (c * inv.pow(2))[:, None, None] * u[:, :, None] * u[:, None, :]
    lay = pb.rig.layout
    out.blocks.index_add_(0, torch.cat([lay.diag[e.a], lay.diag[e.b], e.pair_ab, e.pair_ba]),
                          torch.cat([uu, uu, -uu, -uu]).to(out.blocks.dtype))
    gs = (c * s * inv)[:, None] * u
    out.gx.index_add_(0, e.a, gs.to(out.gx.dtype))
    out.gx.index_add_(0, e.b, -gs.to(out.gx.dtype))
    return True


def reference(pb: Problem, st: Edges, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_stretch."""
    return residual(st, verts)[0].pow(2).mean()
