"""Garment dynamics fitting by differentiable rendering (AniDress paper §3.2, DESIGN.md §8).

Per frame t the B bone transforms G^t (B, 4, 4) of the garment rig are estimated so that the
skinned mesh ``x = LBS(rest, W, G^t)`` explains the 2D cues of C training views, by
minimising a weighted sum of loss terms over bone increments with Levenberg-Marquardt:

    L = w_silhouette L_silhouette + w_normal L_normal + w_flow L_flow     (paper: 2.0, 0.1, 3.0)
      + w_anchor L_anchor + w_prior L_prior + w_collision L_collision     (ours)
      + w_stretch L_stretch                                              (ours)

The settings are :class:`FitConfig`'s (config section ``fit``, the schema's defaults); why each term and setting
is there, as measured: studies/fit/README.md. :func:`plan_fit` turns them and the loaded artifacts into one
:class:`FitPlan`, which :func:`fit_sequence` runs. Modules: :mod:`.config`, :mod:`.variants` (the loss variants),
:mod:`.plan`, :mod:`.sequence` (frames and sequences), :mod:`.window` (windows of frames refined jointly),
:mod:`.problem` (rig, views, cues, render windows), :mod:`.objective` (the loss and its Gauss-Newton system over
:mod:`.terms`, one module per term), :mod:`.lm`, :mod:`.jacobians`, :mod:`.images`, :mod:`.nearest` (the
``nearest`` baseline), :mod:`.ensemble` (the stiffness ensemble L_prior follows).
"""
from __future__ import annotations

from .config import FitConfig, LossWeights
from .images import blurred, chromaticity, image_features, sample, sample_blurred
from .jacobians import apply_increment, projection_jacobian, skin_jacobian
from .lm import levenberg_marquardt
from .objective import evaluate, gauss_newton_system, loss_terms, make_problem, total_loss
from .plan import FitPlan, plan_fit
from .problem import FlowTargets, FrameCues, RigParts, Views, crop_frame, crop_window, uncrop_fragments
from .sequence import FrameFit, fit_frame, fit_sequence, smooth_transforms
from .terms import TERM_NAMES, TERMS
from .terms.anchor import AnchorRef, texture_anchor, texture_blur_texels, update_anchor
from .terms.collision import body_contacts
from .terms.flow import flow_targets
from .variants import PAPER_WEIGHTS, VARIANTS, apply_variant

__all__ = [
    "FitConfig", "LossWeights", "FitPlan", "plan_fit", "VARIANTS", "PAPER_WEIGHTS", "apply_variant", "RigParts",
    "Views", "FrameCues", "FlowTargets", "make_problem", "evaluate", "gauss_newton_system", "loss_terms", "total_loss",
    "TERMS", "TERM_NAMES", "levenberg_marquardt", "FrameFit", "fit_frame", "fit_sequence", "smooth_transforms",
    "flow_targets", "AnchorRef", "update_anchor", "texture_anchor", "texture_blur_texels", "body_contacts",
    "chromaticity", "image_features", "blurred", "sample", "sample_blurred", "crop_window", "crop_frame",
    "uncrop_fragments", "apply_increment", "skin_jacobian", "projection_jacobian",
]
