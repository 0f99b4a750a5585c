"""L_collision (ours, not in the paper): the garment keeps a clearance outside the body.

The mean over the garment vertices of max(0, eps - d_v)^2 (metres^2), d_v the vertex's signed
distance to the body along the outward normal of its closest body point, point and normal taken
at the frame's start (:func:`body_contacts`, a point-to-plane linearisation like ICP's);
eps = ``fit/collision_clearance``, planes for vertices within ``fit/collision_radius`` of the
body. Weight ``fit/weights/collision``: a part that has slipped inside a leg is hidden by the body from every cue
(studies/fit/fit_collision.md). Residual sqrt(w / V) max(0, eps - (x - p).n), Jacobian -n^T where active.
"""
from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from ... import raster
from ..problem import FrameCues, Linearisation, Problem, Rendered, System

NAME = "collision"


class Contacts(NamedTuple):
    """L_collision's planes: garment vertices near the body, the closest body point and outward normal."""

    vert: Tensor  # (M,) int64 garment vertex ids
    point: Tensor  # (M, 3) float64 closest body point
    normal: Tensor  # (M, 3) float64 outward unit normal there


def body_contacts(verts: Tensor, body_verts: Tensor, body_faces: Tensor, radius: float) -> Contacts:
    """L_collision's planes for the garment ``verts`` (V, 3) and the posed body mesh (Vb, 3), (Fb, 3):
    every vertex within ``radius`` of the body (inside or outside, by the winding number) with its
    closest body point and the outward normal there (:func:`anidress_core.sim.metrics.body_contacts`)."""
    from ...sim.metrics import body_contacts as closest

    point, normal, found = closest(verts.detach(), body_verts, body_faces, radius)
    vert = found.nonzero(as_tuple=True)[0]
    return Contacts(vert, point[vert], normal[vert])


def residual(contacts: Contacts, verts: Tensor, eps: float) -> Tensor:
    """(M,) max(0, eps - (x - p) . n): how far each contact vertex of ``verts`` (V, 3) is short of
    ``eps`` outside the body."""
    d = ((verts[contacts.vert] - contacts.point.to(verts.dtype)) * contacts.normal.to(verts.dtype)).sum(-1)
    return (eps - d).clamp_min(0)


def setup(pb: Problem, cues: FrameCues, given: Contacts | None) -> Contacts | None:
    """The planes ``given`` (:func:`body_contacts`), when there are some and a weight."""
    return given if pb.cfg.weights.collision > 0 and given is not None and given.vert.numel() else None


def value(pb: Problem, st: Contacts, r: Rendered) -> tuple[float, None]:
    """L_collision at the render ``r``."""
    return float(residual(st, r.verts, pb.cfg.collision_clearance).pow(2).sum()) / r.verts.shape[0], None


def gauss_newton(pb: Problem, st: Contacts, data: None, lin: Linearisation, out: System) -> bool:
    """Add the active planes' blocks w/V n n^T and gradient -w/V r n in place."""
    verts = lin.verts
    r = residual(st, verts, pb.cfg.collision_clearance)
    on = r > 0
    if not bool(on.any()):
        return False
    vv, nn, w = st.vert[on], st.normal[on].to(verts.dtype), pb.cfg.weights.collision / verts.shape[0]
    out.blocks.index_add_(0, pb.rig.layout.diag[vv], w * nn[:, :, None] * nn[:, None, :])
    out.gx.index_add_(0, vv, -w * r[on][:, None] * nn)
    return True


def reference(pb: Problem, st: Contacts, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_collision."""
    return residual(st, verts, pb.cfg.collision_clearance).pow(2).sum() / verts.shape[0]
