"""Settings of the garment fit: one frozen dataclass, field names = the keys of config section ``fit``, the defaults
and allowed values the schema's (workflow/schemas/config.schema.yaml; :meth:`FitConfig.from_config`). Weights are
stored as they are used: ``weights.<term>`` multiplies the unweighted term ``L_<term>``
(:mod:`anidress_core.fit.terms`).
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Mapping

from ..config import default_schema_path, section_defaults
from .variants import VARIANTS, apply_variant

__all__ = ["LossWeights", "VertexSettings", "FitConfig", "STAGE_KEYS"]

#: Keys of config section ``fit`` that the stage (:mod:`anidress_core.stages.fit`) reads, not the fit itself.
STAGE_KEYS = ("views", "cues", "first_frame_init", "ablations", "device", "threads", "eval", "frames")


@dataclass(frozen=True)
class LossWeights:
    """``fit/weights``: the weight of each loss term (:mod:`anidress_core.fit.terms`); 0 = off."""

    silhouette: float
    """L_silhouette, rendered coverage vs garment mask, per garment pixel (the paper's lambda_M = 2.0)."""
    normal: float
    """L_normal, squared unit-normal difference per garment pixel (the paper's lambda_N = 0.1)."""
    flow: float
    """L_flow, squared pixel distance of flow targets per garment pixel (the paper's lambda_of = 3.0)."""
    anchor: float
    """L_anchor, Cauchy loss of the chromaticity against each vertex's reference, per garment pixel (ours)."""
    collision: float
    """L_collision, mean over vertices of the squared clearance shortfall outside the body, m^2 (ours)."""
    prior: float
    """L_prior, mean squared vertex offset from the reference pose (``FitConfig.prior_reference``), m^2 (ours)."""
    stretch: float
    """L_stretch, mean squared relative stretch of the template's edges from their rest lengths (ours)."""


@dataclass(frozen=True)
class VertexSettings:
    """``fit/vertex``: ablation (a), direct vertex fitting with Adam (``method: vertex``)."""

    lr: float
    """Adam learning rate (metres)."""
    max_iters: int
    """Most Adam iterations per frame (first frame: 3x)."""
    patience: int
    """Stop when the best loss improved by less than rel_tol in this many iterations."""


@dataclass(frozen=True)
class FitConfig:
    """Parameters of the garment fit (config section ``fit``; build with :meth:`from_config`: no field has a default
    but the schema's)."""

    loss: str
    """The loss variant these settings are of (:data:`anidress_core.fit.variants.VARIANTS`)."""
    method: str
    """'rig' (bone transforms, Levenberg-Marquardt), 'vertex' (ablation a: Adam on vertices) or 'nearest' (baseline)."""
    weights: LossWeights
    """Weight of each loss term, as used (dimensionless multipliers of the unweighted terms)."""
    max_iters: int
    """Most loss evaluations per frame t > 0 (the LM stops earlier on convergence)."""
    max_iters_first: int
    """Most loss evaluations for frame 0 (starts further from the answer)."""
    rel_tol: float
    """Converged when an accepted step lowers the loss by less than this fraction."""
    step_tol: float
    """Converged when the largest increment is below this (radians, metres)."""
    damping: float
    """Initial LM damping, relative to the largest diagonal entry of J^T J."""
    visibility_depth_tol: float
    """Relative depth tolerance of the vertex visibility test (flow targets, L_anchor)."""
    flow_margin_px: int
    """Flow targets and colours only where the mask (and the flow) is valid this many pixels around."""
    flow_align_iters: int
    """Frames t > 0: Gauss-Newton steps on L_flow alone before the full loss (no rasterisation); 0 = off."""
    crop_margin: int
    """Render a window per view around the mask and the start pose, grown by this many pixels; -1 = whole images."""
    image_blur: float
    """Gaussian blur (pixels, standard deviation) of the images for L_anchor."""
    anchor_scale: float
    """Cauchy scale of L_anchor (chromaticity difference; rgb / (r + g + b), each in [0, 1])."""
    anchor_reference: str
    """L_anchor's references: 'texture' (the garment texture) or 'images' (:mod:`anidress_core.fit.terms.anchor`)."""
    collision_clearance: float
    """L_collision: clearance (metres) the garment keeps from the body skin."""
    collision_radius: float
    """L_collision: only vertices within this distance (metres) of the body at the frame's start get a plane."""
    smooth_passes: int
    """Passes of the temporal filter of the bone transforms (:func:`anidress_core.fit.smooth_transforms`); 0 = off."""
    vertex: VertexSettings
    """Ablation (a): Adam settings."""
    window: int
    """Frames refined jointly after the chain (:mod:`anidress_core.fit.window`); 0 or 1 = off."""
    window_iters: int
    """Most loss evaluations of one window's joint Levenberg-Marquardt (each evaluates all its frames)."""
    prior_reference: str
    """L_prior's reference: ``start``, ``sim`` or ``sim_ensemble`` (:mod:`anidress_core.fit.terms.prior`); ``sim``
    and ``sim_ensemble`` also give frame 0's start."""
    prior_tangential: bool
    """L_prior counts only the offset along the surface (the tangent planes of ``prior_tangent_planes``)."""
    prior_tangent_planes: str
    """Whose vertex normals give the tangent planes: ``start`` (the frame's start mesh) or ``reference``."""
    prior_spread_floor: float | None
    """L_prior's weight per vertex from the ensemble's spread (:func:`.terms.prior.spread_scale`); None = one weight."""

    def __post_init__(self):
        if self.loss not in VARIANTS:
            raise ValueError(f"FitConfig.loss must be one of {sorted(VARIANTS)}, got {self.loss!r}")
        if self.prior_spread_floor is not None and not (self.prior_reference == "sim_ensemble"
                                                        and self.prior_follows_simulation):
            object.__setattr__(self, "prior_spread_floor", None)  # unused: recorded as None, as it ran

    @property
    def prior_follows_simulation(self) -> bool:
        """L_prior pulls every frame towards the simulated pose (``prior_reference`` sim or sim_ensemble, a
        prior weight, method rig; the vertex method keeps L_prior on frame 0 towards its start, nearest is not
        optimised)."""
        return self.prior_reference in ("sim", "sim_ensemble") and self.weights.prior > 0 and self.method == "rig"

    @classmethod
    def from_config(cls, section: Mapping | None = None, loss: str | None = None) -> "FitConfig":
        """The settings of config section ``fit`` (keys left out: the schema's defaults, the pipeline's), as the loss
        variant ``loss`` (default: the section's ``loss``, :mod:`anidress_core.fit.variants`) uses them. No key is
        renamed; the stage-level keys (:data:`STAGE_KEYS`) are ignored; any other unknown key, or a value the schema
        does not allow, is a ValueError."""
        p = section_defaults("fit", dict(section or {}))
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(p) - fields - set(STAGE_KEYS))
        if unknown:
            raise ValueError(f"config section fit: unknown keys {unknown}")
        bad = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}"
               for e in _validator().iter_errors({k: v for k, v in p.items() if k != "frames"})]
        if bad:
            raise ValueError(f"config section fit: {'; '.join(bad)}")
        return apply_variant(_typed(cls, {**{k: v for k, v in p.items() if k in fields}, "loss": "pipeline"}),
                             loss or p["loss"])

    def replace(self, **changes) -> "FitConfig":
        """A copy with fields changed; ``weights`` may be a mapping of the weights to change."""
        w = changes.get("weights")
        if isinstance(w, Mapping):
            changes["weights"] = dataclasses.replace(self.weights, **w)
        v = changes.get("vertex")
        if isinstance(v, Mapping):
            changes["vertex"] = dataclasses.replace(self.vertex, **v)
        return dataclasses.replace(self, **changes)


@functools.lru_cache(maxsize=1)
def _validator():
    """The schema of section ``fit`` (jsonschema)."""
    import jsonschema
    import yaml

    return jsonschema.Draft202012Validator(yaml.safe_load(default_schema_path().read_text())["properties"]["fit"])


def _typed(cls, values: Mapping):
    """``cls`` (a dataclass of this module) from the config's ``values``, each field cast to its type (nested: its
    dataclass)."""
    cast = {"int": int, "float": float, "bool": bool, "str": str,
            "float | None": lambda v: None if v is None else float(v),
            "LossWeights": lambda v: _typed(LossWeights, v), "VertexSettings": lambda v: _typed(VertexSettings, v)}
    return cls(**{f.name: cast[f.type](values[f.name]) for f in dataclasses.fields(cls)})
