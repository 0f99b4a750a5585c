"""The loss variants of the garment fit, in one place (config ``fit/loss``, ``fit/ablations``, rules ``fit`` and
``fit_ablation``, the CLI): ``pipeline`` (config section ``fit`` as written) and its leave-one-out ablations, the
``nearest`` baseline (:mod:`anidress_core.fit.nearest`), and ``paper``, the paper's loss L = 2.0 L_silhouette +
0.1 L_normal + 3.0 L_flow (L_M, L_N, L_of in AniDress, supplementary) with its ablations of Fig. 9: (a) direct
vertex fitting, (b) no normal and no flow losses, (c) no flow loss. Each variant's description says what it changes.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

__all__ = ["PAPER_WEIGHTS", "Variant", "VARIANTS", "apply_variant"]

#: The paper's weights (lambda_M, lambda_N, lambda_of) = (2.0, 0.1, 3.0), none of ours (``fit/weights``).
PAPER_WEIGHTS = {"silhouette": 2.0, "normal": 0.1, "flow": 3.0, "anchor": 0.0, "collision": 0.0, "prior": 0.0,
                 "stretch": 0.0}


class Variant(NamedTuple):
    description: str
    apply: Callable  # FitConfig -> FitConfig (:meth:`anidress_core.fit.FitConfig.replace`; config imports this module)


def _without(term: str) -> Callable:
    return lambda c: c.replace(weights={term: 0.0})


def _paper(c):
    return c.replace(weights=PAPER_WEIGHTS, smooth_passes=0, window=0, method="rig")


VARIANTS: dict[str, Variant] = {
    "pipeline": Variant("the pipeline's loss (config section fit as written)", lambda c: c),
    **{f"pipeline_no_{k}": Variant(f"the pipeline's loss without L_{k}", _without(k))
       for k in ("normal", "flow", "anchor", "collision", "stretch")},
    "pipeline_no_prior": Variant("the pipeline's loss without L_prior (frame 0)", _without("prior")),
    "pipeline_no_smooth": Variant("the pipeline's loss without the temporal filter of the bone transforms",
                                  lambda c: c.replace(smooth_passes=0)),
    "pipeline_no_window": Variant("the pipeline without the joint refinement of windows of frames (fit/window 0): the "
                                  "chain alone, L_flow's targets carried from the previous result",
                                  lambda c: c.replace(window=0)),
    "pipeline_no_sim_prior": Variant("the pipeline with L_prior on frame 0 only, towards its start, whole offset, "
                                     "weight 10 (fit/prior_reference start; the pipeline before L_prior followed the "
                                     "simulation)",
                                     lambda c: c.replace(prior_reference="start", prior_tangential=False,
                                                         weights={"prior": 10.0})),
    "pipeline_uniform_prior": Variant("the pipeline with one L_prior weight for every vertex, not weighted by the "
                                      "stiffness ensemble's spread (fit/prior_spread_floor null)",
                                      lambda c: c.replace(prior_spread_floor=None)),
    "pipeline_texture_anchor": Variant("the pipeline's loss with L_anchor's references from the garment texture at "
                                       "the template's UVs, not the images (a capture has no such texture)",
                                       lambda c: c.replace(anchor_reference="texture")),
    "nearest": Variant("baseline, no fitting: per frame the simulated pose (nearest simulated frames by body pose and "
                       "velocity, the simulation of the observed motion at t +- offsets) with the lowest pipeline loss "
                       "on the frame's cues", lambda c: c.replace(method="nearest", smooth_passes=0, window=0)),
    "paper": Variant("the paper's loss: 2.0 L_silhouette + 0.1 L_normal + 3.0 L_flow, rig, no temporal filter, "
                     "no window refinement", _paper),
    "paper_vertex": Variant("paper (a): direct vertex fitting without the rig (Adam on vertex positions), "
                            "the paper's loss", lambda c: _paper(c).replace(method="vertex")),
    "paper_no_normal_flow": Variant("paper (b): no normal and no flow losses (silhouettes only)",
                                    lambda c: _paper(c).replace(weights={"normal": 0.0, "flow": 0.0})),
    "paper_no_flow": Variant("paper (c): no flow loss (silhouettes and normals)",
                             lambda c: _paper(c).replace(weights={"flow": 0.0})),
}


def apply_variant(cfg, name: str):
    """The settings of variant ``name`` derived from the pipeline's ``cfg``; ``loss`` records the name."""
    if name not in VARIANTS:
        raise ValueError(f"unknown fit loss variant {name!r}; choose from {sorted(VARIANTS)}")
    return VARIANTS[name].apply(cfg).replace(loss=name)
