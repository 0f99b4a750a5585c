"""The loss terms of the garment fit, one module each, with one protocol (AniDress §3.2 and ours).

Every module has ``NAME`` (its config key ``fit/weights/<NAME>``) and four functions:

* ``setup(pb, cues, given) -> state | None``: the term's state for one frame from the problem's common
  part ``pb`` (:class:`anidress_core.fit.problem.Problem`), the frame's :class:`FrameCues` and what the
  caller gives it (``given``: flow :class:`FlowTargets`, anchor :class:`anchor.AnchorRef`, prior
  :class:`prior.Reference`, collision :class:`collision.Contacts`; the others None). None: the term is
  off this frame (weight 0, or no input); its value is then 0 and it adds nothing.
* ``value(pb, state, r) -> (value, data)``: the unweighted value at a render ``r``
  (:class:`anidress_core.fit.problem.Rendered`), and what its Gauss-Newton block needs.
* ``gauss_newton(pb, state, data, lin, out) -> bool``: adds its weighted J^T J and J^T r at the
  linearisation ``lin`` (:class:`anidress_core.fit.problem.Linearisation`) to ``out``
  (:class:`anidress_core.fit.problem.System`) in place: into H, g directly, or into the vertex-space blocks
  (True when it added some).
* ``reference(pb, state, verts, fragments) -> Tensor``: the same value, differentiable, visibility held
  fixed (autograd checks, the vertex ablation).

:data:`TERMS` is their order everywhere (values, the Gauss-Newton accumulation, the stored columns).
"""
from __future__ import annotations

from . import anchor, collision, flow, normal, prior, silhouette, stretch

#: The terms in the order of the Gauss-Newton accumulation (silhouette into H directly; then the
#: vertex-space blocks normal, flow, anchor, prior, collision, stretch).
TERMS = (silhouette, normal, flow, anchor, prior, collision, stretch)

#: Their names (config keys fit/weights/<name>, FrameFit.terms keys, garment_poses.npz loss_<name>).
TERM_NAMES = tuple(t.NAME for t in TERMS)

__all__ = ["TERMS", "TERM_NAMES", "silhouette", "normal", "flow", "anchor", "prior", "collision", "stretch"]
