"""The subject as the field sees it: the unified pose and the posed surfaces per variant.

Variants (AniDress §4, "w/o G"):

* ``full``: K = 24 body joints (+) B garment bones. Garment poses come from the fitting
  stage (captured sequences) or from the rig's simulated sequences (library motions);
  the posed garment is the rig's LBS of its rest mesh with those poses.
* ``body_only``: K = 24. The garment region is skinned by the body only (the garment
  template's body skinning weights), like a body-driven avatar (HumanNeRF).

A tight-clothed scene has no garment: K = 24 in either variant.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry import lbs
from .sampler import SurfacePart
from .weights import body_bone_priors, combine_priors, grid_points, vertex_priors

__all__ = ["VARIANTS", "BodyRest", "GarmentRest", "canonical_setup", "unified_pose", "posed_parts"]

VARIANTS = ("full", "body_only")


@dataclass
class BodyRest:
    """The body in the canonical frame."""

    verts: Tensor
    """(Vb, 3) rest vertices."""
    faces: Tensor
    """(Fb, 3) int64."""
    weights: Tensor
    """(Vb, 24) skinning weights."""
    joints: Tensor
    """(24, 3) rest joints."""


@dataclass
class GarmentRest:
    """The garment template in the canonical frame with its two sets of weights."""

    verts: Tensor
    """(Vg, 3) rest vertices (the rig's rest = the template)."""
    faces: Tensor
    """(Fg, 3) int64."""
    rig_weights: Tensor | None
    """(Vg, B) rig (virtual bone) weights; None without a rig."""
    body_weights: Tensor
    """(Vg, 24) nearest-body-surface skinning weights of the template."""


def _check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")


def canonical_setup(body: BodyRest, garment: GarmentRest | None, variant: str, res: int = 32,
                    garment_sigma_m: float = 0.04, pad_m: float = 0.1, ellipsoid_scale: float = 1.5
                    ) -> tuple[Tensor, Tensor]:
    """Canonical box (2, 3) and prior volume (K + 1, res, res, res) of a variant."""
    _check_variant(variant)
    pts = body.verts if garment is None else torch.cat([body.verts, garment.verts])
    box = torch.stack([pts.min(0).values - pad_m, pts.max(0).values + pad_m]).float()
    g = grid_points(box, (res, res, res)).reshape(-1, 3)
    prior_body = body_bone_priors(body.verts.float(), body.weights.float(), body.joints.float(), g,
                                  scale=ellipsoid_scale)
    if garment is None:
        prior = combine_priors(prior_body)
    elif variant == "full":
        if garment.rig_weights is None:
            raise ValueError("canonical_setup: variant 'full' needs the garment rig weights")
        prox, wg = vertex_priors(garment.verts.float(), garment.rig_weights.float(), g, garment_sigma_m)
        prior = combine_priors(prior_body, prox, garment_weights=wg)
    else:
        prox, wb = vertex_priors(garment.verts.float(), garment.body_weights.float(), g, garment_sigma_m)
        prior = combine_priors(prior_body, prox, garment_body_weights=wb)
    return box, prior.reshape(-1, res, res, res)


def unified_pose(body_transforms: Tensor, bone_transforms: Tensor | None, variant: str) -> Tensor:
    """S: (T, 24, 4, 4) body (+) (T, B, 4, 4) garment bones -> (T, K, 4, 4)."""
    _check_variant(variant)
    if variant == "body_only" or bone_transforms is None:
        return body_transforms
    if bone_transforms.shape[0] != body_transforms.shape[0]:
        raise ValueError(f"unified_pose: {body_transforms.shape[0]} body frames but {bone_transforms.shape[0]} "
                         "garment pose frames")
    return torch.cat([body_transforms, bone_transforms.to(body_transforms.dtype)], 1)


def posed_parts(body: BodyRest, body_verts: Tensor, garment: GarmentRest | None, variant: str,
                body_transforms: Tensor, bone_transforms: Tensor | None, dilate_m: float,
                body_only_garment_dilate_m: float) -> list[SurfacePart]:
    """Posed surfaces (with weights over the K joints) for the occupancy grid.

    body_verts (T, Vb, 3) posed body. ``full``: garment = rig LBS with the bone
    transforms, margin ``dilate_m``. ``body_only``: garment = template skinned by the
    body (its true place is unknown to this variant), margin
    ``body_only_garment_dilate_m``.
    """
    _check_variant(variant)
    B = 0 if (garment is None or variant == "body_only" or bone_transforms is None) else bone_transforms.shape[1]
    Vb = body.verts.shape[0]
    wb = torch.cat([body.weights, body.weights.new_zeros(Vb, B)], 1)
    parts = [SurfacePart(body_verts, body.faces, wb, dilate_m)]
    if garment is None:
        return parts
    if B:
        gv = lbs(garment.verts.float(), garment.rig_weights.float(), bone_transforms.float())
        wg = torch.cat([garment.rig_weights.new_zeros(garment.verts.shape[0], 24), garment.rig_weights], 1)
        parts.append(SurfacePart(gv, garment.faces, wg, dilate_m))
    else:
        gv = lbs(garment.verts.float(), garment.body_weights.float(), body_transforms.float())
        parts.append(SurfacePart(gv, garment.faces, garment.body_weights, body_only_garment_dilate_m))
    return parts
