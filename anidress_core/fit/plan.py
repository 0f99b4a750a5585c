"""One sequence's fit as it will run: the settings plus what the loaded artifacts give them (one immutable plan).

:func:`plan_fit` decides, from :class:`FitConfig` and the stage-level ``first_frame_init``, frame 0's start, the
simulation L_prior follows and its weight per vertex, and the settings as used (L_normal off without normal maps).
The artifacts come as loaders, called only where the settings need them, so that a fit reads no file it does not
use (:mod:`anidress_core.stages.fit` reads the files and names them in errors). Shapes: T frames, V vertices,
B bones.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

from torch import Tensor

from .config import FitConfig
from .terms.anchor import AnchorRef

__all__ = ["FitPlan", "plan_fit"]

#: a loader of a simulation the fit may follow: () -> (transforms (>= T, B, 4, 4), a line saying what it is)
Followed = Callable[[], tuple[Tensor, str]]


class FitPlan(NamedTuple):
    """What :func:`anidress_core.fit.fit_sequence` runs on."""

    cfg: FitConfig
    """The settings as used (weights.normal 0 without normal maps)."""
    init: Tensor
    """(B, 4, 4) frame 0's start."""
    start_note: str
    """Where frame 0's start comes from (the header's ``first_frame_start``)."""
    sim_transforms: Tensor | None
    """(T, B, 4, 4) L_prior's reference per frame where it follows the simulation, else None."""
    prior_scales: Tensor | None
    """(T, V) L_prior's weight per frame and vertex from the ensemble's spread, else None."""
    followed_note: str | None
    """The simulation L_prior follows and its weighting (the header's ``followed_simulation``), else None."""
    anchor_init: AnchorRef | None
    """L_anchor's references from frame 0 on (the garment texture), else None (from the images as seen)."""
    anchor_note: str | None
    """Where L_anchor's references come from (the header's ``anchor_reference``); None: L_anchor off."""


def plan_fit(cfg: FitConfig, first_frame_init: str, ensemble: Followed, rig_sim: Followed | None,
             body_start: Callable[[], Tensor], spread: Callable[[], Tensor], starts: Tensor | None = None,
             normals: bool = True, rig_name: str = "the rig",
             texture: Callable[[Tensor], tuple[AnchorRef, str]] | None = None) -> FitPlan:
    """The plan of one sequence's fit.

    first_frame_init: ``auto`` (the followed simulation's frame 0 where there is one, else the body-skinned
    template), ``sim`` (the followed simulation's, an error without one) or ``body``. The followed simulation is
    the stiffness ensemble's mean (``ensemble``) with ``prior_reference: sim_ensemble`` where L_prior follows it or
    frame 0 starts from it, else the rig's simulation of the observed motion (``rig_sim``; None: the rig has
    none). body_start: () -> (B, 4, 4) the template skinned by the body at frame 0, in the rig; spread: () ->
    (T, V) :func:`anidress_core.fit.ensemble.ensemble_prior_scales` at ``cfg.prior_spread_floor`` (called only
    where it is set). starts: (T, B, 4, 4) an oracle start for every frame (frame 0's start is ``starts[0]``).
    normals: whether normal maps exist (else L_normal's weight is 0). ValueError, naming ``rig_name``, where the
    settings need a simulation the rig does not have. texture: (B, 4, 4) frame 0's start -> L_anchor's references
    from the garment texture and a line saying what they are (:func:`anidress_core.fit.texture_anchor`), called with
    ``anchor_reference: texture`` and L_anchor on.
    """
    followed, note = None, None
    if cfg.prior_reference == "sim_ensemble" and (cfg.prior_follows_simulation or first_frame_init in ("auto", "sim")):
        followed, note = ensemble()
    elif rig_sim is not None:
        followed, note = rig_sim()
    if starts is not None:
        init, start_note = starts[0], "every frame from the given starts (an oracle)"
    elif first_frame_init in ("auto", "sim") and followed is not None:
        init, start_note = followed[0], f"{note}, frame 0"
    elif first_frame_init == "sim":
        raise ValueError(f"{rig_name}: first_frame_init is 'sim' but it has no simulation of the observed motion")
    else:
        init, start_note = body_start(), "template skinned by the body at frame 0, rig transforms fitted to it"
    sim_transforms, scales = None, None
    if cfg.prior_follows_simulation:
        if followed is None:
            raise ValueError(f"{rig_name}: fit/prior_reference 'sim' needs its simulation of the observed motion "
                             "(rule motions simulates every captured sequence; or set fit/prior_reference: start, "
                             "the variant pipeline_no_sim_prior)")
        sim_transforms = followed
        if cfg.prior_spread_floor is not None:  # set only where L_prior follows the ensemble (FitConfig)
            scales = spread()
            note += f"; L_prior's weight per vertex from the members' spread (prior_spread_floor " \
                    f"{cfg.prior_spread_floor:g})"
    if not normals:
        cfg = cfg.replace(weights={"normal": 0.0})
    anchor_init, anchor_note = None, None
    if cfg.weights.anchor > 0:
        anchor_note = "images (each vertex's chromaticity where first seen)"
        if cfg.anchor_reference == "texture":
            if texture is None:
                raise ValueError("fit/anchor_reference is 'texture' but no garment texture was given")
            anchor_init, anchor_note = texture(init)
    return FitPlan(cfg, init, start_note, sim_transforms, scales, note if sim_transforms is not None else None,
                   anchor_init, anchor_note)
