"""The stiffness ensemble the fit follows (rule simulate_ensemble; ours, studies/fit/README.md sections 16-17).

The mean of the observed motion simulated at several bending stiffnesses, carried into the rig, is L_prior's
reference and frame 0's start (``fit/prior_reference: sim_ensemble``); the members' spread about it gives
L_prior's weight per vertex (``fit/prior_spread_floor``). Arrays in, arrays out: the stage
(:mod:`anidress_core.stages.fit`) reads the file (:func:`anidress_core.io.sim.read_sim`). Shapes: T frames,
V vertices, B bones.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..rig import fit_transforms
from .terms.prior import spread_scale

__all__ = ["ENSEMBLE_NOTE_MARK", "ensemble_note", "ensemble_transforms", "ensemble_prior_scales"]

#: the words of every :func:`ensemble_note`, by which a fit's header says it read an ensemble file
ENSEMBLE_NOTE_MARK = "simulations (bending stiffness"


def ensemble_note(meta: dict) -> str:
    """What an ensemble file's members are, from its header's ``meta`` (:func:`read_sim`'s): the line the fit
    records as the simulation it followed, and by which benchmarks.bench_fit tells whether a stored fit followed
    the same ensemble."""
    ms = meta.get("members", [])
    k = sorted({m.get("bend_stiffness") for m in ms})
    n = sorted({m.get("settle_frames") for m in ms if m.get("settle_frames") is not None})
    return (f"the mean of {len(ms)} {ENSEMBLE_NOTE_MARK} {k} J"
            + (f", settle frames {n}" if n else "") + ")")


def ensemble_transforms(model, mean, frames: int | None, device) -> Tensor:
    """(frames, B, 4, 4) float64: the rig ``model``'s least-squares bone transforms
    (:func:`anidress_core.rig.fit_transforms`) of the first ``frames`` (None: all) of the ensemble's mean
    ``mean`` (>= frames, V, 3), on ``device``. ValueError when it does not fit the rig or is not finite."""
    V = model.rest.shape[0]
    frames = mean.shape[0] if frames is None else frames
    if mean.ndim != 3 or mean.shape[1:] != (V, 3) or mean.shape[0] < frames:
        raise ValueError(f"frames {tuple(mean.shape)}, the fit needs ({frames}+, {V}, 3) (the rig's template, every "
                         "frame of the sequence)")
    X = torch.as_tensor(mean[:frames], device=device, dtype=torch.float64)
    if not torch.isfinite(X).all():
        raise ValueError("non-finite vertices")
    return fit_transforms(model, X).double()


def ensemble_prior_scales(spread, frames: int, floor: float) -> Tensor:
    """(frames, V) float64 L_prior's factor per frame and vertex (:func:`anidress_core.fit.terms.prior.spread_scale`
    with ``floor``) from the members' spread (>= frames, V) about their mean. ValueError for fewer frames or a
    non-finite or negative spread."""
    if spread.shape[0] < frames:
        raise ValueError(f"spread {tuple(spread.shape)} must hold {frames}+ frames")
    return spread_scale(torch.as_tensor(spread[:frames], dtype=torch.float64), floor)
