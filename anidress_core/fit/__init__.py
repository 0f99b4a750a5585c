"""Garment dynamics fitting by differentiable rendering (AniDress paper §3.2, DESIGN.md §8).

Per frame t the B bone transforms G^t (B, 4, 4) of the garment rig are estimated so that the
skinned mesh ``x = LBS(rest, W, G^t)`` explains the 2D cues of C training views, by
minimising a weighted sum of loss terms over bone increments with Levenberg-Marquardt:

    L = w_silhouette L_silhouette + w_normal L_normal + w_flow L_flow     (paper: 2.0, 0.1, 3.0)
      + w_anchor L_anchor + w_prior L_prior + w_collision L_collision     (ours)
      + w_stretch L_stretch                                              (ours)

The settings are :class:`FitConfig`'s, read from config section ``fit`` (defaults: the schema,
workflow/schemas/config.schema.yaml; each key explained in config/config.yaml). Why each term and
setting is there, as measured: studies/fit/README.md, its Conclusions first.

Modules: :mod:`.config` (:class:`FitConfig`, the config section ``fit``), :mod:`.variants`
(the loss variants: ``pipeline``, ``paper``, their ablations), :mod:`.problem` (rig, views,
cues, render windows), :mod:`.terms` (one module per loss term, one protocol: setup, value,
Gauss-Newton block, autograd reference), :mod:`.objective` (the problem of a frame, the loss and
its Gauss-Newton system), :mod:`.lm`
(Levenberg-Marquardt), :mod:`.jacobians` (bone increments), :mod:`.sequence` (frames and
sequences: the forward chain), :mod:`.window` (windows of chained frames refined jointly, L_flow
coupling their poses), :mod:`.nearest` (the ``nearest`` baseline: simulated poses scored by the
loss), :mod:`.ensemble` (the stiffness ensemble L_prior follows), :mod:`.plan` (the settings
plus the loaded artifacts: one sequence's fit as it will run), :mod:`.images` (image sampling).
"""
from __future__ import annotations

from .config import FitConfig, LossWeights, VertexSettings
from .images import blurred, chromaticity, image_features, sample, sample_blurred
from .jacobians import JACOBIAN_DTYPE, apply_increment, projection_jacobian, skin_jacobian
from .lm import LMResult, levenberg_marquardt
from .plan import FitPlan, plan_fit
from .objective import Evaluation, evaluate, gauss_newton_system, loss_terms, make_problem, total_loss
from .problem import (Crop, FlowTargets, FrameCues, Problem, RigParts, Views, crop_frame, crop_window, cue_notes,
                      occluder_depth, uncrop_fragments)
from .sequence import FrameFit, fit_frame, fit_problem, fit_sequence, flow_align, smooth_transforms
from .terms import TERM_NAMES, TERMS
from .terms.anchor import AnchorRef, texture_anchor, texture_blur_texels, update_anchor
from .terms.collision import Contacts, body_contacts
from .terms.flow import flow_targets
from .terms.prior import Reference as PriorReference
from .variants import PAPER_WEIGHTS, VARIANTS, apply_variant

__all__ = [
    "FitConfig", "LossWeights", "VertexSettings", "FitPlan", "plan_fit", "VARIANTS", "PAPER_WEIGHTS", "apply_variant",
    "RigParts", "Views", "FrameCues", "FlowTargets", "Problem", "make_problem", "Evaluation", "evaluate",
    "gauss_newton_system", "loss_terms", "total_loss", "TERMS", "TERM_NAMES", "LMResult",
    "levenberg_marquardt", "FrameFit", "fit_problem", "fit_frame", "fit_sequence", "cue_notes",
    "flow_align", "smooth_transforms", "flow_targets", "AnchorRef", "PriorReference", "update_anchor",
    "texture_anchor", "texture_blur_texels", "Contacts", "body_contacts", "chromaticity", "image_features",
    "blurred", "sample", "sample_blurred", "occluder_depth", "Crop", "crop_window", "crop_frame",
    "uncrop_fragments", "JACOBIAN_DTYPE", "apply_increment", "skin_jacobian", "projection_jacobian",
]
