"""One sequence's fit as it will run: the settings plus what the loaded artifacts give them (:class:`FitPlan`).

:func:`plan_fit` takes the artifacts as loaders, called only where the settings need them, so that a fit reads no
file it does not use (:mod:`anidress_core.stages.fit` reads the files and names them in errors). Shapes: T frames,
V vertices, B bones.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

from torch import Tensor

from ..geometry import lbs
from .config import FitConfig
from .nearest import Candidates, SimDatabase, body_features, frame_candidates
from .problem import RigParts, Views
from .terms.anchor import AnchorRef, texture_anchor, texture_blur_texels

__all__ = ["FitPlan", "plan_fit"]

#: a loader of a simulation the fit may follow: () -> (transforms (>= T, B, 4, 4), a line saying what it is)
Followed = Callable[[], tuple[Tensor, str]]


class FitPlan(NamedTuple):
    """What :func:`anidress_core.fit.fit_sequence` runs: :func:`plan_fit`'s, or built directly from arrays."""

    cfg: FitConfig
    """The settings as used (weights.normal 0 without normal maps)."""
    rig: RigParts
    views: Views
    frames: int
    """T, the frames fitted."""
    init: Tensor
    """(B, 4, 4) frame 0's start."""
    starts: Tensor | None = None
    """(>= T, B, 4, 4) a start for every frame instead of the previous result (an oracle for benchmarks)."""
    sim_transforms: Tensor | None = None
    """(>= T, B, 4, 4) L_prior's reference per frame where it follows the simulation, else None."""
    prior_scales: Tensor | None = None
    """(>= T, V) L_prior's weight per frame and vertex from the ensemble's spread, else None (1)."""
    anchor_init: AnchorRef | None = None
    """L_anchor's references from frame 0 on (the garment texture), else None (from the images as seen)."""
    candidates_of: Callable[[int], Candidates] | None = None
    """Method ``nearest``: frame t -> its candidate poses (:func:`anidress_core.fit.nearest.frame_candidates`)."""
    notes: dict | None = None
    """What each choice came from, by the header's key (``first_frame_start``, ``followed_simulation``,
    ``anchor_reference``, ``simulation_database``, ``starts``, ``transforms_note``)."""


def transforms_note(cfg: FitConfig) -> str:
    """What the stored bone transforms are."""
    if cfg.method == "vertex":
        return "vertex ablation: rig transforms fitted to the fitted vertices"
    return "fitted bone transforms" + (f", then smooth_transforms ({cfg.smooth_passes} passes); the per-frame losses "
                                       "are those of the fit before it" if cfg.smooth_passes else "")


def plan_fit(cfg: FitConfig, rig: RigParts, views: Views, frames: int, first_frame_init: str = "auto", *,
             body_start: Callable[[], Tensor], ensemble: Followed, rig_sim: Followed | None,
             spread: Callable[[], Tensor], texture: Callable[[], tuple[Tensor, Tensor, str]] | None = None,
             database: Callable[[], tuple[SimDatabase, Tensor, float]] | None = None, own: str | None = None,
             starts: Tensor | None = None, normals: bool = True, rig_name: str = "the rig") -> FitPlan:
    """The plan of the fit of ``frames`` frames of ``rig`` in ``views``: each choice of :class:`FitPlan` with a note
    for the fit's header.

    first_frame_init: ``auto`` (the followed simulation's frame 0 where there is one, else the body-skinned
    template), ``sim`` (the followed simulation's, an error without one) or ``body``. The followed simulation is
    the stiffness ensemble's mean with ``prior_reference: sim_ensemble`` where L_prior follows it or frame 0 starts
    from it, else the rig's simulation of the observed motion. The loaders:

    * body_start: () -> (1, V, 3) the template skinned by the body at frame 0;
    * ensemble, rig_sim: the ensemble's mean, the rig's simulation (None: the rig has none);
    * spread: () -> (T, V) :func:`anidress_core.fit.ensemble.ensemble_prior_scales` at ``cfg.prior_spread_floor``;
    * texture: () -> the template's face UVs (F, 3, 2), the garment texture (Ht, Wt, 3) and a line naming it
      (``anchor_reference: texture``: :func:`anidress_core.fit.texture_anchor`, blurred to the images' footprint
      at frame 0's start);
    * database: () -> the simulation database, the observed body's joint transforms (T, J, 4, 4) and frame rate
      (method ``nearest``; own: the database's simulation of the observed motion).

    starts: (T, B, 4, 4) an oracle start for every frame. normals: whether normal maps exist (else L_normal's
    weight is 0). ValueError, naming ``rig_name``, where the settings need a simulation the rig does not have.
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
        init = rig.closest_pose(body_start())[0]
        start_note = "template skinned by the body at frame 0, rig transforms fitted to it"
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
            face_uv, tex, name = texture()
            blur = texture_blur_texels(rig.rest, rig.faces, face_uv, tuple(tex.shape[:2]),
                                       lbs(rig.rest, rig.weights, init), views, cfg.image_blur)
            anchor_init = texture_anchor(rig.faces, face_uv, tex, blur, num_vertices=rig.rest.shape[0])
            anchor_note = f"{name}, blurred by {blur:.2f} texels (one image pixel + the images' blur)"
    candidates_of, db_note = None, None
    if cfg.method == "nearest":
        if database is None:
            raise ValueError("the method 'nearest' needs the simulation database")
        db, joints, fps = database()
        query = body_features(joints, fps)
        db_note = f"{db.transforms.shape[0]} simulated frames of {list(db.names)}"

        def candidates_of(t: int) -> Candidates:
            c = frame_candidates(db, query, t, own=own)
            return c._replace(transforms=c.transforms.to(rig.rest.device))

    notes = {"first_frame_start": start_note, "anchor_reference": anchor_note, "simulation_database": db_note,
             "followed_simulation": note if sim_transforms is not None else None,
             "starts": None if starts is None else "given per frame (oracle)", "transforms_note": transforms_note(cfg)}
    return FitPlan(cfg, rig, views, frames, init, starts, sim_transforms, scales, anchor_init, candidates_of, notes)
