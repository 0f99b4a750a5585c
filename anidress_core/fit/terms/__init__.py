"""The loss terms of the garment fit, one module each, every one with its value, its
Gauss-Newton block and its autograd reference together (AniDress §3.2 and ours).

    L = w_silhouette L_silhouette + w_normal L_normal + w_flow L_flow        (the paper's, supp.)
      + w_anchor L_anchor + w_prior L_prior + w_collision L_collision
      + w_stretch L_stretch                                                  (ours)

Each module has ``NAME`` (its config key ``fit/weights/<NAME>``), ``value(pb, r)`` ->
(unweighted value, what its Gauss-Newton block needs) at a render ``r`` (:class:`Rendered`),
``gauss_newton(...)`` and ``reference(pb, verts, fragments)`` (a differentiable tensor, for
autograd checks and the vertex ablation). :data:`TERMS` is their order everywhere (values,
the Gauss-Newton accumulation, the stored columns).
"""
from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from ... import raster


class Rendered(NamedTuple):
    """One evaluation's render of the mesh: what every term's value reads."""

    verts: Tensor  # (V, 3)
    uv: Tensor  # (C, V, 2) vertex projections
    z: Tensor  # (C, V) camera depths
    fragments: raster.Fragments  # occluded fragments (visibility)


from . import anchor, collision, flow, normal, prior, silhouette, stretch  # noqa: E402

#: The terms in the order of the Gauss-Newton accumulation (silhouette into H directly; then the
#: vertex-space blocks normal, flow, anchor, prior, collision, stretch).
TERMS = (silhouette, normal, flow, anchor, prior, collision, stretch)

#: Their names (config keys fit/weights/<name>, FrameFit.terms keys, garment_poses.npz loss_<name>).
TERM_NAMES = tuple(t.NAME for t in TERMS)

__all__ = ["Rendered", "TERMS", "TERM_NAMES", "silhouette", "normal", "flow", "anchor", "prior", "collision", "stretch"]
