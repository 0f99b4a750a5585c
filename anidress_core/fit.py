"""Garment dynamics fitting by differentiable rendering (AniDress paper §3.2, DESIGN.md §8).

Per frame t the B bone transforms G^t (B, 4, 4) of the garment rig (rest (V, 3),
weights (V, B), :mod:`anidress_core.rig`) are estimated so that the skinned mesh
``x = LBS(rest, W, G^t)`` explains the 2D cues of C training views:

    L_fit = w_M L_M + w_N L_N + w_of L_of,   (w_M, w_N, w_of) = (2.0, 0.1, 3.0)  [paper, supp.]

* L_M, silhouette: rendered garment coverage (hard rasterisation, antialiased at the
  silhouette edges, :func:`anidress_core.raster.silhouette`; the body is an occluder,
  :func:`anidress_core.raster.occlude`) against the garment mask (label 2): squared
  difference summed over all pixels of all views.
* L_N, normals: camera-space normals of the visible faces
  (:func:`anidress_core.raster.face_normals_cam`) against the normal maps: squared
  difference of unit vectors summed over pixels that are garment in both the render and
  the mask (and have a finite normal).
* L_of, optical flow: projections of the vertices of the previous frame's fitted mesh
  that are visible in a view and lie inside its garment mask (t-1), moved by the forward
  flow t-1 -> t sampled there, are the targets of the same vertices' projections now:
  squared distance in pixels summed over (view, vertex) targets. Off at frame 0.
* L_ph, multi-view photo-consistency (not in the paper; ``w_photo``, 0 = off): every vertex
  seen by two or more views (visible, its pixel inside the eroded garment mask) should have
  the same colour in all of them; residual = its colour in a view (slightly blurred image,
  bilinear) minus its mean over those views, robust Cauchy loss. A shape cue in the spirit of
  multi-view stereo: it places textured surface points in depth, where the masks see only
  the outline and the normals only the orientation, and it is absolute at every frame (L_of
  chains frames). It cannot see a garment sliding along its own surface (the same surface
  with other vertex labels); that stays L_of's job. Measured in benchmarks/fit.md (variant
  ``photo``): the surface (Chamfer) improves in every case measured, the vertex RMSE only on
  the scene it was tuned on, so the default is the paper's loss.
* L_an, temporal chromaticity anchor (not in the paper; ``w_anchor``, 0 = off): every vertex
  keeps the chromaticity rgb / (r + g + b) it had in the first frame it was seen (mean over
  the views that saw it then, inside the eroded garment mask); at later frames each
  (view, visible vertex) pays a robust Cauchy loss of its chromaticity there (blurred image,
  bilinear) against that reference. Chromaticity does not change with Lambertian shading
  under white light, which the colour itself does as the garment turns; a reference that
  follows the material point is what L_of's chained targets lack (benchmarks/fit_drift.md),
  so L_an is what holds a vertex on its material point over many frames -- it sees sliding.
  The reference is only as good as the fit of the frame it comes from (a start error stays),
  unless the references come from the garment's texture at the template's UVs
  (:func:`texture_anchor`; the stage's ``anchor_reference: texture``): then L_an sees where
  each material point is from frame 0 on, which masks, normals and flow cannot (on the
  skirt's floral print the frame-0 tangential error falls from 18 to 6 mm; on a repeating,
  nearly one-hue plaid they discriminate less, and the fit is worse than with first-seen
  references unless the normal term is weighted up too: the stage's
  ``weights/normal_texture_anchor``, benchmarks/fit_normal_weight.md).
* L_col, body collision (not in the paper; ``w_collision``, 0 = off): the mean over the
  garment vertices of max(0, eps - d_v)^2, d_v the vertex's signed distance to the body along
  the outward normal of its closest body point, point and normal taken at the frame's start
  (:func:`body_contacts`, a point-to-plane linearisation like ICP's). The rig's bones at the
  hem are seen in few views, and a part that has slipped inside a leg is hidden by the body
  from every cue; without this the fit leaves tens of vertices per frame up to 6 cm inside
  the body (benchmarks/fit_collision.md).

As in the paper every term is a sum (over views and pixels or targets); all of them are
divided by one common constant, the number of garment pixels in the masks, so that their
ratios are the paper's whatever the image size and number of views
(``normalisation='paper'``; ``'per_term'`` makes each term a mean of its own residuals).
Optional, off by default: a proximal term towards the start pose at frame 0
(``w_prior_first``), because masks and normals cannot observe a nearly rotationally
symmetric garment sliding about the body.

Optimisation. The unknowns are increments (omega_b, tau_b) of every bone: a rotation
by the axis-angle omega_b about the bone's current centre (the rig's rest centroid
carried by G_b) followed by a translation tau_b, composed onto G_b after each step
(a local exponential chart, so no parameterisation singularity is ever reached; the
accumulated rotations are stored as matrices). The loss is a sum of squared residuals,
minimised by Levenberg-Marquardt (Marquardt's diagonal scaling, Nielsen's damping
update) with exact Gauss-Newton Jacobians: every residual depends on at most three
vertices (a silhouette crossing on its edge's two end points, a face normal on its
face's corners, a flow target on one vertex), so its derivative w.r.t. those vertices
is computed locally (analytically, or by autograd on the gathered corners), then
chained with the projection Jacobian and dx/d(omega, tau) (linear in the skinning
weights). Rasterisation (visibility, which pixels and edges) is redone at every
evaluation and held fixed inside one linearisation (nvdiffrast's split). A frame stops
when an accepted step lowers the loss by less than ``rel_tol`` (relative), when the
step is below ``step_tol``, or after ``max_iters`` evaluations. Frames t > 0 start from
frame t-1's pose moved by a few Gauss-Newton steps on L_of alone (``flow_align_iters``,
vertex projections only, no rasterisation), which keeps fast motion inside the
one-pixel reach of the silhouette gradients. The renders are cut to a window per view
around the mask and the start pose (``crop_margin``), the body occluder rasterised there.

Ablation (a) of the paper, direct vertex fitting without the rig, optimises the V x 3
vertex positions with Adam on the same loss through autograd (Gauss-Newton on 3V
unknowns is not practical); ablations (b) no normal + no flow and (c) no flow are the
rig fit with those weights set to 0. See :data:`ABLATIONS`.

Shapes: T frames, V vertices, F faces, B bones, C cameras, H, W image size, N residuals.
Float64 for poses and geometry, float32 for the Jacobians; CPU or CUDA (whatever device
the inputs are on).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Callable, NamedTuple

import torch
import torch.nn.functional as Fnn
from torch import Tensor

from . import raster
from .geometry import axis_angle_to_matrix, lbs, nearest_rotation

__all__ = [
    "FitConfig",
    "ABLATIONS",
    "config_for",
    "RigParts",
    "Views",
    "FrameCues",
    "FlowTargets",
    "photo_features",
    "chromaticity",
    "AnchorRef",
    "update_anchor",
    "texture_anchor",
    "texture_blur_texels",
    "FrameFit",
    "contour_length",
    "flow_targets",
    "occluder_depth",
    "fit_frame",
    "downsample",
    "crop_window",
    "crop_frame",
    "fit_sequence",
    "loss_terms",
    "apply_increment",
    "skin_jacobian",
    "projection_jacobian",
]

#: Weight of L_ph in the ``photo`` variant when the configuration leaves it off (measured in
#: benchmarks/fit.md; tuned on the skirt walk: 300 / 1000 / 3000 gave 32.0 / 28.4 / 27.9 mm).
PHOTO_WEIGHT = 1000.0

#: Weight of L_an in the ``anchor`` variant when the configuration leaves it off (benchmarks/fit.md;
#: tuned on skirt/walk with ground-truth cues: 1e3 / 1e4 / 1e5 / 3e5 / 1e6 gave 18.3 / 14.4 / 13.5 /
#: 13.5 / 15.0 mm against 19.6 without it).
ANCHOR_WEIGHT = 1.0e5

#: Weight of L_col in the ``collision`` variant when the configuration leaves it off
#: (benchmarks/fit_collision.md, 1e6: on the skirt walk with texture references 15.94 mm against
#: 16.40 without it, and < 1 vertex per frame more than 2 mm inside the body; 1e5, not in that
#: file, gave 15.97 mm).
COLLISION_WEIGHT = 1.0e6

#: Ablations of the paper (Fig. 9) and our variants: name -> what changes with respect to the full method.
ABLATIONS = {
    "vertex": "(a) direct vertex fitting without the rig (Adam on vertex positions)",
    "no_normal_flow": "(b) no normal and no flow losses (silhouettes only)",
    "no_flow": "(c) no flow loss (silhouettes and normals)",
    "photo": "(ours, a variant) the full loss + multi-view photo-consistency L_ph (weight fit/weights/photo, "
             "else PHOTO_WEIGHT)",
    "anchor": "(ours, a variant) the full loss + the temporal chromaticity anchor L_an (weight fit/weights/anchor, "
              "else ANCHOR_WEIGHT)",
    "anchor_smooth": "(ours, a variant) as anchor, then the poses filtered over time (fit/smooth_passes, else 1 pass)",
    "anchor_texture": "(ours, a variant) as anchor_smooth, with L_an's references from the garment's texture at the "
                      "template's UVs instead of from the first frame each vertex is seen (texture_anchor)",
    "collision": "(ours, a variant) as anchor_texture, + the body-collision term L_col (weight "
                 "fit/weights/collision, else COLLISION_WEIGHT)",
}


@dataclass(frozen=True)
class FitConfig:
    """Parameters of the garment fit (config section ``fit``)."""

    w_mask: float = 2.0
    """lambda_M, weight of the silhouette loss (paper: 2.0)."""
    w_normal: float = 0.1
    """lambda_N, weight of the normal loss (paper: 0.1); 0 switches it off."""
    w_flow: float = 3.0
    """lambda_of, weight of the optical-flow loss (paper: 3.0); 0 switches it off."""
    method: str = "rig"
    """'rig' (bone transforms, Levenberg-Marquardt) or 'vertex' (ablation a, Adam on vertices)."""
    max_iters: int = 20
    """Most loss evaluations per frame t > 0 (the LM stops earlier on convergence)."""
    max_iters_first: int = 60
    """Most loss evaluations for the first frame (starts further from the answer)."""
    levels: tuple = (1,)
    """Resolution pyramid of frames t > 0: image reduction factors, coarse to fine, ending with 1
    (see :func:`downsample`; each level gets up to ``max_iters`` evaluations)."""
    levels_first: tuple = (1,)
    """Resolution pyramid of the first frame (each level up to ``max_iters_first`` evaluations)."""
    rel_tol: float = 1e-3
    """Converged when an accepted step lowers the loss by less than this fraction."""
    step_tol: float = 1e-5
    """Converged when the largest increment is below this (radians, metres)."""
    damping: float = 1e-4
    """Initial LM damping, relative to the largest diagonal entry of J^T J."""
    vis_depth_tol: float = 0.005
    """Relative depth tolerance of the vertex visibility test (flow targets)."""
    vertex_lr: float = 1e-3
    """Adam learning rate (metres) of the vertex ablation."""
    vertex_max_iters: int = 60
    """Most Adam iterations per frame of the vertex ablation (first frame: 3x)."""
    vertex_patience: int = 10
    """Vertex ablation: stop when the best loss improved by less than rel_tol in this many iterations."""
    w_prior_first: float = 0.0
    """First frame only: weight of a proximal term w * mean_v |x_v - x_v(start)|^2 (metres^2)
    towards the start pose. Silhouettes and normals do not observe sliding of a nearly
    rotationally symmetric garment about the body; without flow (frame 0) nothing else
    does. 0 = off (the paper's loss)."""
    flow_margin_px: int = 1
    """Flow targets only where the mask and the flow are valid this many pixels around (see
    :func:`flow_targets`)."""
    flow_align_iters: int = 3
    """Frames t > 0: Gauss-Newton steps on L_of alone before the full loss (cheap, no
    rasterisation); 0 = off."""
    crop_margin: int = 12
    """Render only a window per view around the mask and the start pose, grown by this many
    pixels (the same loss while the garment stays inside; faster); -1 = whole images."""
    w_photo: float = 0.0
    """Weight of L_ph, multi-view photo-consistency (not in the paper; 0 = off): the colour of
    every vertex seen by two or more views, in each of them, against its mean over them (robust
    Cauchy loss); places textured surface points in depth at every frame (module docstring)."""
    photo_blur: float = 0.5
    """Gaussian blur (pixels, standard deviation) of the images for L_ph and L_an."""
    photo_scale: float = 0.05
    """Cauchy scale of L_ph (colour difference, RGB in [0, 1]): rho(r) = s^2 log(1 + |r|^2 / s^2)."""
    w_anchor: float = 0.0
    """Weight of L_an, the temporal chromaticity anchor (not in the paper; 0 = off): each
    vertex's chromaticity against the one it had when first seen (module docstring)."""
    anchor_scale: float = 0.05
    """Cauchy scale of L_an (chromaticity difference; rgb / (r + g + b), each in [0, 1])."""
    w_collision: float = 0.0
    """Weight of L_col, the body-collision term (not in the paper; 0 = off): mean over the garment
    vertices of max(0, collision_eps - d_v)^2 (metres^2), d_v the vertex's signed distance to the
    body along the outward normal of its closest body point, that point and normal taken once per
    frame at the start pose (a point-to-plane linearisation; needs ``FrameCues.occluder_mesh``).
    A garment part hidden inside a leg is seen by no mask, normal or flow; this pushes it out."""
    collision_eps: float = 0.003
    """L_col: clearance (metres) the garment keeps from the body skin."""
    collision_radius: float = 0.05
    """L_col: only vertices within this distance (metres) of the body at the frame's start get a plane."""
    smooth_passes: int = 0
    """After the whole sequence is fitted: passes of the temporal filter (1, 2, 1) / 4 over the bone
    transforms (:func:`smooth_transforms`; not in the paper; 0 = off). Offline, like the rest of
    the fit; the per-frame loss terms stay those of the unfiltered fit."""
    normalisation: str = "paper"
    """'paper': each term is the paper's sum (over pixels, flow targets), all divided by one
    common constant, the number of garment pixels of the masks; 'per_term': each term is a
    mean (mask: per contour pixel pair, normals: per mask pixel, flow: per target)."""

    def __post_init__(self):
        if self.normalisation not in ("paper", "per_term"):
            raise ValueError(f"FitConfig.normalisation must be 'paper' or 'per_term', got {self.normalisation!r}")
        if self.method not in ("rig", "vertex"):
            raise ValueError(f"FitConfig.method must be 'rig' or 'vertex', got {self.method!r}")
        for k in ("w_mask", "w_normal", "w_flow", "w_photo", "w_anchor", "w_collision"):
            v = getattr(self, k)
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"FitConfig.{k} must be finite and >= 0, got {v}")
        if not (self.photo_blur >= 0 and self.photo_scale > 0 and self.anchor_scale > 0):
            raise ValueError(f"FitConfig: photo_blur must be >= 0, photo_scale and anchor_scale > 0, got "
                             f"{self.photo_blur}, {self.photo_scale}, {self.anchor_scale}")
        if not (self.collision_eps >= 0 and self.collision_radius > 0):
            raise ValueError(f"FitConfig: collision_eps must be >= 0 and collision_radius > 0, got "
                             f"{self.collision_eps}, {self.collision_radius}")
        if int(self.smooth_passes) != self.smooth_passes or self.smooth_passes < 0:
            raise ValueError(f"FitConfig.smooth_passes must be an integer >= 0, got {self.smooth_passes}")
        if self.max_iters < 1 or self.max_iters_first < 1 or self.vertex_max_iters < 1:
            raise ValueError("FitConfig: iteration limits must be >= 1")
        for k in ("levels", "levels_first"):
            lv = tuple(getattr(self, k))
            if not lv or lv[-1] != 1 or any(int(x) != x or x < 1 for x in lv):
                raise ValueError(f"FitConfig.{k} must be reduction factors >= 1 ending with 1, got {lv}")
            object.__setattr__(self, k, tuple(int(x) for x in lv))


def config_for(base: FitConfig, ablation: str | None) -> FitConfig:
    """The configuration of an ablation (:data:`ABLATIONS`) derived from the full method's."""
    if ablation in (None, "", "full"):
        return base
    if ablation == "vertex":
        return replace(base, method="vertex", w_photo=0.0, w_anchor=0.0, w_collision=0.0, smooth_passes=0)
    if ablation == "no_normal_flow":
        return replace(base, w_normal=0.0, w_flow=0.0, w_photo=0.0, w_anchor=0.0, w_collision=0.0, smooth_passes=0)
    if ablation == "no_flow":
        return replace(base, w_flow=0.0, w_photo=0.0, w_anchor=0.0, w_collision=0.0, smooth_passes=0)
    if ablation == "photo":
        return replace(base, w_photo=base.w_photo if base.w_photo > 0 else PHOTO_WEIGHT)
    if ablation == "anchor":
        return replace(base, w_anchor=base.w_anchor if base.w_anchor > 0 else ANCHOR_WEIGHT)
    if ablation in ("anchor_smooth", "anchor_texture"):  # texture: the references' source is the caller's
        return replace(base, w_anchor=base.w_anchor if base.w_anchor > 0 else ANCHOR_WEIGHT,
                       smooth_passes=max(int(base.smooth_passes), 1))
    if ablation == "collision":
        return replace(config_for(base, "anchor_texture"),
                       w_collision=base.w_collision if base.w_collision > 0 else COLLISION_WEIGHT)
    raise ValueError(f"unknown ablation {ablation!r}; choose from {sorted(ABLATIONS)}")


class RigParts(NamedTuple):
    """The garment rig as the fit uses it (float64, one device); build with :meth:`make`."""

    rest: Tensor  # (V, 3) rest vertices (body canonical frame)
    weights: Tensor  # (V, B) convex skinning weights
    centres: Tensor  # (B, 3) rest-pose bone centres
    faces: Tensor  # (F, 3) int64
    edges: tuple  # raster.mesh_edges(faces): (E, 2) vertex ids, (E, 2) faces either side
    layout: "_HessianLayout"  # sparsity pattern of the vertex-space Gauss-Newton matrix

    @staticmethod
    def make(rest: Tensor, weights: Tensor, centres: Tensor, faces: Tensor) -> "RigParts":
        rest = torch.as_tensor(rest).double()
        dev = rest.device
        weights = torch.as_tensor(weights, device=dev).double()
        centres = torch.as_tensor(centres, device=dev).double()
        faces = torch.as_tensor(faces, device=dev).long()
        V = rest.shape[0]
        if rest.shape != (V, 3) or weights.ndim != 2 or weights.shape[0] != V or centres.shape != (weights.shape[1], 3):
            raise ValueError(f"RigParts: rest (V, 3), weights (V, B), centres (B, 3) expected, got "
                             f"{tuple(rest.shape)}, {tuple(weights.shape)}, {tuple(centres.shape)}")
        if faces.ndim != 2 or faces.shape[1] != 3 or (faces.numel() and (faces.min() < 0 or faces.max() >= V)):
            raise ValueError(f"RigParts: faces must be (F, 3) indices into {V} vertices")
        if not (bool(torch.isfinite(rest).all()) and bool(torch.isfinite(weights).all())
                and bool(torch.isfinite(centres).all())):
            raise ValueError("RigParts: rest, weights or centres contain NaN or inf")
        return RigParts(rest, weights, centres, faces, raster.mesh_edges(faces), _HessianLayout.make(faces, V))


class _HessianLayout(NamedTuple):
    """Block pattern of sum_residuals J_x^T J_x for residuals living on one face or vertex.

    Vertex pairs (a, b) that share a face (and every (v, v)), sorted by a * V + b; each
    pair is a 3x3 block. ``face_pair`` (F, 3, 3) is the pair of (faces[f, k], faces[f, l]),
    ``diag`` (V,) the pair (v, v); ``perm``, ``crow``, ``col`` turn the (pairs, 3, 3)
    buffer into a (3V, 3V) CSR matrix.
    """

    num_vertices: int
    face_pair: Tensor
    diag: Tensor
    perm: Tensor
    crow: Tensor
    col: Tensor

    @staticmethod
    def make(faces: Tensor, V: int) -> "_HessianLayout":
        dev = faces.device
        fa = faces[:, :, None].expand(-1, 3, 3)
        fb = faces[:, None, :].expand(-1, 3, 3)
        ar = torch.arange(V, device=dev)
        codes = torch.unique(torch.cat([(fa * V + fb).reshape(-1), ar * V + ar]))  # sorted
        face_pair = torch.searchsorted(codes, fa * V + fb)
        diag = torch.searchsorted(codes, ar * V + ar)
        a, b = codes // V, codes % V
        i = torch.arange(3, device=dev)
        rows = (3 * a[:, None, None] + i[None, :, None]).expand(-1, 3, 3).reshape(-1)
        cols = (3 * b[:, None, None] + i[None, None, :]).expand(-1, 3, 3).reshape(-1)
        perm = torch.argsort(rows * (3 * V) + cols)
        crow = torch.zeros(3 * V + 1, dtype=torch.int64, device=dev)
        crow[1:] = torch.cumsum(torch.bincount(rows, minlength=3 * V), 0)
        return _HessianLayout(V, face_pair, diag, perm, crow, cols[perm])

    def matrix(self, blocks: Tensor) -> Tensor:
        """(pairs, 3, 3) blocks -> (3V, 3V) sparse CSR."""
        n = 3 * self.num_vertices
        with warnings.catch_warnings():  # "sparse CSR support is in beta"
            warnings.simplefilter("ignore")
            return torch.sparse_csr_tensor(self.crow, self.col, blocks.reshape(-1)[self.perm], (n, n))


class Views(NamedTuple):
    """C undistorted pinhole views (see :mod:`anidress_core.raster` for the conventions)."""

    K: Tensor  # (C, 3, 3)
    world_to_cam: Tensor  # (C, 4, 4)
    height: int
    width: int

    @staticmethod
    def from_cameras(cams) -> "Views":
        """From :class:`anidress_core.camera.Cameras`; distortion is not modelled, so it must be 0."""
        if bool((cams.dist.abs() > 1e-9).any()):
            raise ValueError(f"fit: cameras {cams.names} have lens distortion, which the rasteriser does not "
                             "model; undistort the images and cues first")
        # Rotations read from float32 files are orthonormal to ~1e-7 only; the normal term
        # uses R^T = R^-1 (per-face grouping in world space), so they are projected onto SO(3).
        E = cams.world_to_cam.double().clone()
        R = nearest_rotation(E[:, :3, :3])
        off = (R - E[:, :3, :3]).abs().amax((-2, -1))
        if bool((off > 1e-4).any()):
            bad = [n for n, o in zip(cams.names, off.tolist()) if o > 1e-4]
            raise ValueError(f"fit: cameras {bad} have a world_to_cam rotation that is not a rotation "
                             f"(off by up to {float(off.max()):.2g})")
        E[:, :3, :3] = R
        return Views(cams.K.double(), E, cams.height, cams.width)


class FrameCues(NamedTuple):
    """The 2D observations of one frame in C views (pixels on the image grid)."""

    mask: Tensor  # (C, H, W) bool garment pixels (label 2), or float garment coverage in [0, 1]
    normals: Tensor | None  # (C, H, W, 3) camera-space unit normals; non-finite / zero = none
    occluder: Tensor | None  # (C, H, W) camera z of the body (+inf where none), see occluder_depth
    occluder_mesh: tuple | None = None
    """(verts (Vb, 3), faces (Fb, 3)) of the occluder (the posed body), rasterised by
    :func:`fit_frame` in its render windows when ``occluder`` is None (cheaper)."""
    image: Tensor | None = None
    """(C, H, W, 3) colour images in [0, 1] for L_ph (``FitConfig.w_photo``), or None (L_ph off)."""


class FlowTargets(NamedTuple):
    """Where the flow says visible vertices of the previous fitted mesh went (N targets)."""

    cam: Tensor  # (N,) int64
    vert: Tensor  # (N,) int64
    target: Tensor  # (N, 2) float64 pixel positions in frame t


@dataclass
class FrameFit:
    """Result of :func:`fit_frame`."""

    transforms: Tensor
    """(B, 4, 4) bone transforms rest -> world (for the vertex method: the start's, unchanged)."""
    verts: Tensor
    """(V, 3) fitted mesh."""
    terms: dict
    """Unweighted loss terms at the result: mask, normal, flow (float; 0 for an unused term)."""
    loss: float
    """Weighted total at the result."""
    iterations: int
    """Loss evaluations spent (LM: accepted + rejected steps; vertex: Adam steps)."""
    converged: bool
    """Stopped by a tolerance rather than by the iteration limit."""
    curve: list = field(default_factory=list)
    """Weighted total loss after each accepted step (index 0: the start)."""
    fragments: raster.Fragments | None = None
    """Occluded fragments of the result (for the next frame's flow targets)."""


# --------------------------------------------------------------------------------------
# cues and small geometric helpers
# --------------------------------------------------------------------------------------


def contour_length(mask: Tensor) -> Tensor:
    """(C,) number of horizontally or vertically adjacent pixel pairs with different labels in mask (C, H, W)."""
    m = mask.bool()
    return (m[:, :, 1:] != m[:, :, :-1]).sum((1, 2)) + (m[:, 1:, :] != m[:, :-1, :]).sum((1, 2))


def occluder_depth(verts: Tensor, faces: Tensor, views: Views) -> Tensor:
    """(C, H, W) camera z of an occluding mesh (the posed body), +inf where it is absent."""
    return raster.rasterize(verts, faces, views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype),
                            views.height, views.width, with_bary=False).depth


def _sanitize_normals(normals: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
    """(normals with NaN/inf replaced by 0, valid (C, H, W) bool) or (None, None)."""
    if normals is None:
        return None, None
    n = normals.double()
    ok = torch.isfinite(n).all(-1)
    n = torch.where(ok[..., None], n, torch.zeros_like(n))
    ok &= n.norm(dim=-1) > 0.5
    return n, ok


@torch.no_grad()
def flow_targets(prev_verts: Tensor, views: Views, prev_fragments: raster.Fragments, flow: Tensor,
                 flow_valid: Tensor | None, prev_mask: Tensor, depth_tol: float = 0.005,
                 margin: int = 1) -> FlowTargets:
    """Flow-loss targets of frame t from the fitted mesh of frame t-1 (paper eq. L_of).

    prev_verts (V, 3) fitted mesh of t-1; prev_fragments: its :func:`raster.occlude`-d
    fragments (visibility of t-1); flow (C, H, W, 2) forward flow t-1 -> t on frame t-1's
    pixel grid, in pixels; flow_valid (C, H, W) bool or None (all valid); prev_mask
    (C, H, W) garment mask of t-1. A vertex gets a target in a view when it is visible
    there (:func:`raster.visible_vertices`), every pixel within ``margin`` pixels of its
    nearest pixel is garment in the mask and valid in the flow (the bilinear support, and
    no flow mixed in from the body or the background across a boundary), and the
    bilinearly sampled flow is finite: ``target = project(prev_verts) + flow(project(prev_verts))``.
    """
    C, H, W = prev_mask.shape
    if flow.shape != (C, H, W, 2):
        raise ValueError(f"flow_targets: flow must be ({C}, {H}, {W}, 2), got {tuple(flow.shape)}")
    K, E = views.K.to(prev_verts.dtype), views.world_to_cam.to(prev_verts.dtype)
    uv, _ = raster.project_vertices(prev_verts, K, E)  # (C, V, 2)
    vis = raster.visible_vertices(prev_verts, K, E, prev_fragments, depth_tol)  # (C, V)
    good = prev_mask.bool() if not prev_mask.is_floating_point() else prev_mask >= 1
    if flow_valid is not None:
        good = good & flow_valid.bool()
    ok = vis & _pixel_ok(_eroded(good, margin), uv)  # the whole (2 margin + 1)^2 neighbourhood is good
    fs = _sample(flow.permute(0, 3, 1, 2), uv)  # (C, V, 2) bilinear flow at the projections
    ok &= torch.isfinite(fs).all(-1)
    c, v = ok.nonzero(as_tuple=True)
    return FlowTargets(c, v, (uv[c, v] + fs[c, v]).double())


def _gaussian_taps(blur: float, device=None) -> tuple[int, Tensor]:
    """Radius r = ceil(3 blur) (at least 1) and the normalised float64 taps (2r + 1,) of a
    Gaussian of ``blur`` pixels; ``blur`` 0: (0, [1])."""
    if blur <= 0:
        return 0, torch.ones(1, dtype=torch.float64, device=device)
    r = max(1, int(math.ceil(3 * blur)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64, device=device) / blur) ** 2)
    return r, k / k.sum()


def _blurred(image: Tensor, blur: float) -> Tensor:
    """(C, ch, H, W) float64: the image (C, H, W, ch) (non-finite values as 0) blurred by a
    separable Gaussian of ``blur`` pixels (replicated border); ``blur`` 0: unchanged."""
    x = image.permute(0, 3, 1, 2).double()
    x = torch.where(torch.isfinite(x), x, torch.zeros_like(x))
    if blur <= 0:
        return x
    C, ch, H, W = x.shape
    r, k = _gaussian_taps(blur, x.device)
    k = k.view(1, 1, -1)
    y = x.reshape(C * ch, 1, H, W)
    y = Fnn.conv2d(Fnn.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    y = Fnn.conv2d(Fnn.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return y.view(C, ch, H, W)


def photo_features(image: Tensor, blur: float) -> Tensor:
    """(C, 9, H, W): the image (C, H, W, 3) blurred by a Gaussian of ``blur`` pixels (channels
    0-2) and its derivatives along x (3-5) and y (6-8), central differences (one-sided at the
    border). L_ph samples these bilinearly at vertex projections; the
    derivative channels are its Gauss-Newton Jacobian (smoother than the bilinear
    interpolant's own piecewise-constant derivative)."""
    x = _blurred(image, blur)
    H, W = x.shape[-2:]
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    if W > 1:
        gx[..., 1:-1] = 0.5 * (x[..., 2:] - x[..., :-2])
        gx[..., 0], gx[..., -1] = x[..., 1] - x[..., 0], x[..., -1] - x[..., -2]
    if H > 1:
        gy[..., 1:-1, :] = 0.5 * (x[..., 2:, :] - x[..., :-2, :])
        gy[..., 0, :], gy[..., -1, :] = x[..., 1, :] - x[..., 0, :], x[..., -1, :] - x[..., -2, :]
    return torch.cat([x, gx, gy], 1)


def _sample(feat: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples (C, V, ch) of feat (C, ch, H, W) at pixel positions uv (C, V, 2)
    (pixel centres at integer coordinates; outside: the border value)."""
    H, W = feat.shape[-2:]
    grid = torch.stack([2 * uv[..., 0] / max(W - 1, 1) - 1, 2 * uv[..., 1] / max(H - 1, 1) - 1], -1)
    grid = torch.where(torch.isfinite(grid), grid, torch.full_like(grid, -2.0))
    out = Fnn.grid_sample(feat.to(uv.dtype), grid[:, None], mode="bilinear", padding_mode="border",
                          align_corners=True)
    return out[:, :, 0].permute(0, 2, 1)


def _sample_blurred(image: Tensor, cam: Tensor, uv: Tensor, blur: float) -> Tensor:
    """``_sample(_blurred(image, blur), uv)`` at N points only: (N, ch) for image (C, H, W, ch),
    cam (N,) and pixel positions uv (N, 2), without filtering whole images.

    The bilinear sample of the Gaussian-blurred image is one separable stencil on the
    (2r + 2)^2 pixels around the point (r = ceil(3 blur)): per axis the weights
    (1 - f) g[o] + f g[o - 1], o = -r .. r + 1, with the replicated border of both
    filters (indices clamped) and the sample position clamped to the image like
    ``grid_sample``'s border padding."""
    C, H, W, ch = image.shape
    dt = torch.float64
    r, g = _gaussian_taps(blur, uv.device)
    off = torch.arange(-r, r + 2, device=uv.device)  # (S,) S = 2r + 2

    def axis(x, size):  # -> (N, S) pixel indices and weights along one axis
        x = torch.where(torch.isfinite(x), x.to(dt), torch.zeros_like(x, dtype=dt)).clamp(0, max(size - 1, 0))
        x0 = torch.floor(x)
        f = (x - x0)[:, None]
        gpad = torch.cat([g.new_zeros(1), g, g.new_zeros(1)])  # g[o] at gpad[o + r + 1]
        w = (1 - f) * gpad[off + r + 1][None] + f * gpad[off + r][None]
        return (x0.long()[:, None] + off[None]).clamp(0, size - 1), w

    cols, wc = axis(uv[:, 0], W)
    rows, wr = axis(uv[:, 1], H)
    pix = image[cam[:, None, None], rows[:, :, None], cols[:, None, :]].to(dt)  # (N, S, S, ch)
    pix = torch.where(torch.isfinite(pix), pix, torch.zeros_like(pix))
    return torch.einsum("nabc,na,nb->nc", pix, wr, wc)


def _eroded(mask: Tensor, margin: int) -> Tensor:
    """(C, H, W) bool: pixels whose whole (2 margin + 1)^2 neighbourhood is garment (mask >= 1 if soft)."""
    good = mask.bool() if not mask.is_floating_point() else mask >= 1
    if margin <= 0:
        return good
    return -Fnn.max_pool2d(-good[:, None].double(), 2 * margin + 1, stride=1, padding=margin)[:, 0] > 0.5


def _pixel_ok(region: Tensor, uv: Tensor) -> Tensor:
    """(C, V) bool: the pixel nearest to uv (C, V, 2) lies in the image and in region (C, H, W)."""
    C, H, W = region.shape
    finite = torch.isfinite(uv).all(-1)
    col = torch.where(finite, uv[..., 0], torch.full_like(uv[..., 0], -1.0)).round()
    row = torch.where(finite, uv[..., 1], torch.full_like(uv[..., 1], -1.0)).round()
    inside = finite & (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1)
    cam = torch.arange(C, device=uv.device)[:, None].expand_as(col)
    return inside & region[cam, row.clamp(0, H - 1).long(), col.clamp(0, W - 1).long()]


#: Added to r + g + b before dividing (colours in [0, 1]): dark pixels have a chromaticity near 0
#: instead of an unstable ratio.
CHROMA_EPS = 0.05


def chromaticity(image: Tensor) -> Tensor:
    """(..., 3) -> (..., 3): rgb / (r + g + b + CHROMA_EPS), unchanged by a Lambertian shading factor
    (white light) on pixels well above black."""
    image = image.double()
    return image / (image.sum(-1, keepdim=True) + CHROMA_EPS)


class Contacts(NamedTuple):
    """L_col's planes: garment vertices near the body, the closest body point and outward normal."""

    vert: Tensor  # (M,) int64 garment vertex ids
    point: Tensor  # (M, 3) float64 closest body point
    normal: Tensor  # (M, 3) float64 outward unit normal there


def body_contacts(verts: Tensor, body_verts: Tensor, body_faces: Tensor, radius: float) -> Contacts:
    """L_col's planes for the garment ``verts`` (V, 3) and the posed body mesh (Vb, 3), (Fb, 3):
    every vertex within ``radius`` of the body (inside or outside, by the winding number) with its
    closest body point and the outward normal there (:func:`anidress_core.sim.metrics.body_contacts`)."""
    from .sim.metrics import body_contacts as closest

    point, normal, found = closest(verts.detach(), body_verts, body_faces, radius)
    vert = found.nonzero(as_tuple=True)[0]
    return Contacts(vert, point[vert], normal[vert])


def _collision_residual(contacts: Contacts, verts: Tensor, eps: float) -> Tensor:
    """(M,) max(0, eps - (x - p) . n): how far each contact vertex is short of ``eps`` outside the body."""
    d = ((verts[contacts.vert] - contacts.point.to(verts.dtype)) * contacts.normal.to(verts.dtype)).sum(-1)
    return (eps - d).clamp_min(0)


class AnchorRef(NamedTuple):
    """L_an's references: each vertex's chromaticity in the first frame it was seen."""

    chroma: Tensor  # (V, 3)
    seen: Tensor  # (V,) bool: has a reference


def update_anchor(ref: AnchorRef | None, verts: Tensor, views: Views, fragments: raster.Fragments, image: Tensor,
                  mask: Tensor, cfg: FitConfig) -> AnchorRef:
    """Give the vertices without a reference one from this frame: the mean chromaticity
    (blurred image (C, H, W, 3), bilinear) over the views in which the vertex of ``verts`` (V, 3) is
    visible (``fragments``, whole images) and lies inside the eroded garment ``mask`` (C, H, W).
    Vertices that already have a reference keep it; vertices seen nowhere stay without one.
    Only the new references' pixels are read (:func:`_sample_blurred`)."""
    K, E = views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype)
    uv, _ = raster.project_vertices(verts.detach(), K, E)
    soft = mask.double() if mask.is_floating_point() else mask.bool().double()
    vis = raster.visible_vertices(verts.detach(), K, E, fragments, cfg.vis_depth_tol)
    vis &= _pixel_ok(_eroded(torch.where(torch.isfinite(soft), soft, torch.zeros_like(soft)), cfg.flow_margin_px), uv)
    seen_now = vis.any(0)
    new = seen_now if ref is None else seen_now & ~ref.seen
    if ref is not None and not bool(new.any()):
        return ref
    c, v = (vis & new[None]).nonzero(as_tuple=True)
    V = verts.shape[0]
    total = torch.zeros(V, 3, dtype=torch.float64, device=uv.device).index_add_(
        0, v, _sample_blurred(chromaticity(image), c, uv[c, v], cfg.photo_blur))
    mean = total / torch.zeros(V, dtype=torch.float64, device=uv.device).index_add_(
        0, v, torch.ones_like(v, dtype=torch.float64)).clamp_min(1)[:, None]
    if ref is None:
        return AnchorRef(torch.where(seen_now[:, None], mean, torch.zeros_like(mean)), seen_now)
    return AnchorRef(torch.where(new[:, None], mean, ref.chroma.to(mean.dtype)), ref.seen | new)


def texture_anchor(faces: Tensor, face_uv: Tensor, texture: Tensor, blur_texels: float,
                   num_vertices: int | None = None) -> AnchorRef:
    """L_an's references from a textured template instead of from the first frame a vertex is seen.

    faces (F, 3), face_uv (F, 3, 2) the template's UVs (OBJ convention, :func:`raster.sample_texture`);
    a vertex on a UV seam takes the UV of its first face. texture (Ht, Wt, 3) colours in [0, 1].
    Each vertex's reference is the chromaticity of the texture blurred by a Gaussian of
    ``blur_texels`` texels (what one image pixel, blurred like the images, covers:
    :func:`texture_blur_texels`), at its UV. Every vertex gets one (``seen`` all True), so L_an
    holds each vertex on its own material point from frame 0 on: the material placement that
    no mask, normal or flow observes (benchmarks/fit_frame0.md) is then seen in the images.
    num_vertices: V (default: the largest index in ``faces`` + 1); every vertex must be in a face.
    """
    V = num_vertices if num_vertices is not None else (int(faces.max()) + 1 if faces.numel() else 0)
    if face_uv.shape != (*faces.shape, 2) or texture.ndim != 3 or texture.shape[-1] != 3:
        raise ValueError(f"texture_anchor: faces (F, 3), face_uv (F, 3, 2) and texture (Ht, Wt, 3) expected, got "
                         f"{tuple(faces.shape)}, {tuple(face_uv.shape)}, {tuple(texture.shape)}")
    first = torch.full((V,), faces.numel(), dtype=torch.int64, device=faces.device)
    if faces.numel() and int(faces.max()) >= V:
        raise ValueError(f"texture_anchor: faces index vertex {int(faces.max())} of {V}")
    first.scatter_reduce_(0, faces.reshape(-1), torch.arange(faces.numel(), device=faces.device), "amin")
    if bool((first == faces.numel()).any()):
        raise ValueError("texture_anchor: some vertices are in no face")
    uv = face_uv.reshape(-1, 2)[first].double()  # (V, 2)
    chroma = _blurred(chromaticity(texture.double())[None], blur_texels)[0].permute(1, 2, 0)  # (Ht, Wt, 3)
    ref = raster.sample_texture(chroma, uv)
    return AnchorRef(ref, torch.ones(V, dtype=torch.bool, device=ref.device))


def texture_blur_texels(rest: Tensor, faces: Tensor, face_uv: Tensor, texture_hw: tuple[int, int], verts: Tensor,
                        views: Views, image_blur: float) -> float:
    """The Gaussian (in texels) that makes the texture look like the images at ``verts``:
    sqrt(1/12 + image_blur^2) pixels (a pixel's box, then the images' blur) times the median
    metres per pixel of the vertices ``verts`` (V, 3) in the views (camera z / focal), times
    the template's texels per metre (square root of UV area in texels over rest area, rest
    (V, 3), faces (F, 3), face_uv (F, 3, 2))."""
    def area(p):  # (F, 3, k) -> (F,)
        a, b = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        if p.shape[-1] == 2:
            return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).abs()
        return 0.5 * torch.cross(a, b, dim=-1).norm(dim=-1)

    Ht, Wt = texture_hw
    uv_area = float(area(face_uv.double() * torch.tensor([Wt, Ht], dtype=torch.float64, device=face_uv.device)).sum())
    rest_area = float(area(rest.double()[faces]).sum())
    if not (uv_area > 0 and rest_area > 0):
        raise ValueError("texture_blur_texels: the template has zero UV or surface area")
    _, z = raster.project_vertices(verts.double(), views.K.double(), views.world_to_cam.double())  # (C, V)
    m_per_px = (z / views.K[:, 0, 0, None].double())
    m_per_px = float(m_per_px[torch.isfinite(m_per_px) & (z > 0)].median())
    return math.sqrt(1.0 / 12.0 + image_blur ** 2) * m_per_px * math.sqrt(uv_area / rest_area)


def apply_increment(transforms: Tensor, centres: Tensor, delta: Tensor) -> Tensor:
    """Compose per-bone increments onto transforms.

    transforms (B, 4, 4) rest -> world; centres (B, 3) rest bone centres; delta (B, 6)
    = (omega, tau): rotate by axis-angle omega about the bone's current world centre
    c_w = R c + t, then translate by tau. ``x' = exp(omega) (R r + t - c_w) + c_w + tau``.
    """
    R, t = transforms[:, :3, :3], transforms[:, :3, 3]
    cw = torch.einsum("bij,bj->bi", R, centres) + t
    Q = axis_angle_to_matrix(delta[:, :3])
    out = transforms.clone()
    out[:, :3, :3] = Q @ R
    out[:, :3, 3] = torch.einsum("bij,bj->bi", Q, t - cw) + cw + delta[:, 3:]
    return out


def skin_jacobian(rig: RigParts, transforms: Tensor) -> Tensor:
    """dx/d(delta) at delta = 0: (V, 3, B * 6), columns (bone, [omega, tau]).

    x_v = sum_b W_vb (R_b r_v + t_b); d x_v / d omega_b = -W_vb [a_vb]_x with
    a_vb = R_b (r_v - c_b) (the vertex relative to the bone centre); d x_v / d tau_b = W_vb I.
    Written straight into the (V, 3, B, 6) layout (no stacked skew matrices, no permuted copy).
    """
    R = transforms[:, :3, :3]
    W = rig.weights
    V, B = W.shape
    a = torch.einsum("vj,bij->vbi", rig.rest, R) - torch.einsum("bij,bj->bi", R, rig.centres)[None]  # (V, B, 3)
    x, y, z = (W[..., None] * a).unbind(-1)
    J = torch.zeros(V, 3, B, 6, dtype=a.dtype, device=a.device)
    J[:, 0, :, 1], J[:, 0, :, 2] = z, -y  # -W [a]_x, rows of [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    J[:, 1, :, 0], J[:, 1, :, 2] = -z, x
    J[:, 2, :, 0], J[:, 2, :, 1] = y, -x
    for i in range(3):
        J[:, i, :, 3 + i] = W
    return J.view(V, 3, B * 6)


def projection_jacobian(verts: Tensor, views: Views) -> tuple[Tensor, Tensor]:
    """uv (C, V, 2) and d uv / d x (C, V, 2, 3) of the pinhole projection of world points verts (V, 3)."""
    E = views.world_to_cam.to(verts.dtype)
    K = views.K.to(verts.dtype)
    Xc = torch.einsum("cij,vj->cvi", E[:, :3, :3], verts) + E[:, None, :3, 3]  # (C, V, 3)
    X, Y, Z = Xc.unbind(-1)
    iz = 1.0 / Z
    fx, s, cx = K[:, 0, 0, None], K[:, 0, 1, None], K[:, 0, 2, None]
    fy, cy = K[:, 1, 1, None], K[:, 1, 2, None]
    u = (fx * X + s * Y) * iz + cx
    v = fy * Y * iz + cy
    o = torch.zeros_like(X)
    du = torch.stack([fx * iz + o, s * iz + o, -(fx * X + s * Y) * iz * iz], -1)
    dv = torch.stack([o, fy * iz + o, -fy * Y * iz * iz], -1)
    D = torch.stack([du, dv], -2)  # (C, V, 2, 3) d uv / d X_cam
    return torch.stack([u, v], -1), D @ E[:, None, :3, :3]


# --------------------------------------------------------------------------------------
# loss evaluation (values, fragments) and Gauss-Newton systems
# --------------------------------------------------------------------------------------


class _Problem(NamedTuple):
    """Everything fixed during one frame's optimisation."""

    rig: RigParts
    views: Views
    mask: Tensor  # (C, H, W) bool
    mask_flat: Tensor  # (C H W,) float64
    n_mask: float  # contour length normaliser
    normals: Tensor | None  # (C, H, W, 3) float64 or None
    normal_ok: Tensor | None  # (C, H, W) bool
    n_normal: float
    occluder: Tensor  # (C, H, W)
    flow: FlowTargets | None
    n_flow: float
    cfg: FitConfig
    prior: Tensor | None = None  # (V, 3) start mesh of the first frame (proximal term), or None
    w_prior: float = 0.0  # its weight per vertex: w_prior_first / V
    photo: Tensor | None = None  # (C, 9, H, W) photo_features of the images, or None (L_ph off)
    photo_region: Tensor | None = None  # (C, H, W) bool: eroded garment mask (where colours count)
    n_photo: float = 1.0
    anchor_feat: Tensor | None = None  # (C, 9, H, W) photo_features of the chromaticity, or None (L_an off)
    anchor: AnchorRef | None = None
    contacts: "Contacts | None" = None  # L_col's planes, or None (L_col off)


class _Eval(NamedTuple):
    loss: float
    terms: dict
    verts: Tensor
    fragments: raster.Fragments
    uv: Tensor  # (C, V, 2)
    sil: "_SilData"
    nrm: "_NormalData | None"
    pho: "_PhotoData | None" = None
    anc: "_PhotoData | None" = None


class _SilData(NamedTuple):
    inside_xy: Tensor
    outside_xy: Tensor
    cam: Tensor
    edge: Tensor  # (N, 2)
    pixel: Tensor  # (N,) pixel whose coverage the crossing changes
    residual: Tensor  # (C H W,) s - m


class _PhotoData(NamedTuple):
    cam: Tensor  # (N,)
    vert: Tensor  # (N,)
    residual: Tensor  # (N, 3) colour - reference
    grad: Tensor  # (N, 3, 2) d colour / d uv
    weight: Tensor  # (N,) Cauchy IRLS weight 1 / (1 + |r|^2 / s^2)


class _NormalData(NamedTuple):
    face: Tensor  # (U,) faces with normal pixels in some view
    count: Tensor  # (U,) their pixels, all views
    mean_target: Tensor  # (U, 3) mean world-space target (each pixel's s R^T t)


def _occluder_or_inf(cues: FrameCues, views: Views) -> Tensor:
    """(C, H, W) float64 occluder depth of the cues (rasterised from occluder_mesh if needed; +inf: none)."""
    if cues.occluder is not None:
        occ = cues.occluder.double()
        return torch.where(torch.isnan(occ), torch.full_like(occ, float("inf")), occ)
    if cues.occluder_mesh is not None:
        v, f = cues.occluder_mesh
        return occluder_depth(v.double(), f, views).double()
    return torch.full(cues.mask.shape, float("inf"), dtype=torch.float64, device=cues.mask.device)


def _check_cues(views: Views, cues: FrameCues) -> None:
    C, H, W = views.K.shape[0], views.height, views.width
    if cues.mask.shape != (C, H, W):
        raise ValueError(f"fit: mask must be ({C}, {H}, {W}), got {tuple(cues.mask.shape)}")
    if cues.occluder is not None and cues.occluder.shape != (C, H, W):
        raise ValueError(f"fit: occluder depth must be ({C}, {H}, {W}), got {tuple(cues.occluder.shape)}")
    if cues.normals is not None and cues.normals.shape != (C, H, W, 3):
        raise ValueError(f"fit: normals must be ({C}, {H}, {W}, 3), got {tuple(cues.normals.shape)}")


def _make_problem(rig: RigParts, views: Views, cues: FrameCues, flow: FlowTargets | None, cfg: FitConfig,
                  prior: Tensor | None = None, anchor: AnchorRef | None = None,
                  contacts: Contacts | None = None) -> _Problem:
    _check_cues(views, cues)
    soft = cues.mask.double() if cues.mask.is_floating_point() else cues.mask.bool().double()
    soft = torch.where(torch.isfinite(soft), soft.clamp(0, 1), torch.zeros_like(soft))
    mask = soft > 0.5
    normals, nok = _sanitize_normals(cues.normals if cfg.w_normal > 0 else None)
    if nok is not None:
        nok = nok & (soft >= 1)
    occ = _occluder_or_inf(cues, views)
    if flow is not None and (cfg.w_flow == 0 or flow.cam.numel() == 0):
        flow = None
    photo = region = None
    if cfg.w_photo > 0 and cues.image is not None:
        photo = photo_features(cues.image, cfg.photo_blur)
    anchor_feat = None
    if cfg.w_anchor > 0 and cues.image is not None and anchor is not None and bool(anchor.seen.any()):
        anchor_feat = photo_features(chromaticity(cues.image), cfg.photo_blur)
    else:
        anchor = None
    if photo is not None or anchor_feat is not None:
        region = _eroded(soft, cfg.flow_margin_px)
    if cfg.normalisation == "paper":  # the paper's sums over pixels / targets, one common scale
        n_px = float(max(float(soft.sum()), 1.0))
        n_mask = n_normal = n_flow = n_photo = n_px
    else:  # every term a mean: per contour pixel, per normal pixel, per flow target, per vertex
        n_mask = float(max(int(contour_length(mask).sum()), 1))
        n_normal = float(max(int(nok.sum()), 1)) if nok is not None else 1.0
        n_flow = float(max(flow.cam.numel(), 1)) if flow is not None else 1.0
        n_photo = float(rig.rest.shape[0])
    return _Problem(
        rig=rig, views=views, mask=mask, mask_flat=soft.reshape(-1), n_mask=n_mask,
        normals=normals, normal_ok=nok, n_normal=n_normal,
        occluder=occ, flow=flow, n_flow=n_flow, cfg=cfg,
        prior=None if prior is None or cfg.w_prior_first == 0 else prior.detach().double(),
        w_prior=cfg.w_prior_first / rig.rest.shape[0],
        photo=photo, photo_region=region, n_photo=n_photo, anchor_feat=anchor_feat, anchor=anchor,
        contacts=contacts if cfg.w_collision > 0 and contacts is not None and contacts.vert.numel() else None,
    )


class Crop(NamedTuple):
    """Per-camera windows (x0, y0) (C,) int64 of a common size height x width."""

    x0: Tensor
    y0: Tensor
    height: int
    width: int


def crop_window(views: Views, mask: Tensor, verts: Tensor, margin: int) -> Crop:
    """The smallest common window size holding, in every view, the mask's garment pixels
    and the projection of ``verts`` (V, 3), grown by ``margin`` pixels, clamped to the image."""
    C, H, W = mask.shape
    uv, z = raster.project_vertices(verts.detach(), views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype))
    ok = torch.isfinite(uv).all(-1) & (z > 0)
    big = torch.tensor(1e9, dtype=uv.dtype, device=uv.device)
    lo = torch.where(ok[..., None], uv, big).amin(1).floor()  # (C, 2)
    hi = torch.where(ok[..., None], uv, -big).amax(1).ceil()
    m = mask.bool() if not mask.is_floating_point() else mask > 0
    rows, cols = m.any(2), m.any(1)  # (C, H), (C, W)
    ar_h = torch.arange(H, device=mask.device, dtype=uv.dtype)
    ar_w = torch.arange(W, device=mask.device, dtype=uv.dtype)
    lo_x = torch.minimum(lo[:, 0], torch.where(cols, ar_w, big).amin(1))
    hi_x = torch.maximum(hi[:, 0], torch.where(cols, ar_w, -big).amax(1))
    lo_y = torch.minimum(lo[:, 1], torch.where(rows, ar_h, big).amin(1))
    hi_y = torch.maximum(hi[:, 1], torch.where(rows, ar_h, -big).amax(1))
    lo_x, lo_y = (lo_x - margin).clamp(0, W - 1), (lo_y - margin).clamp(0, H - 1)
    hi_x, hi_y = (hi_x + margin).clamp(0, W - 1), (hi_y + margin).clamp(0, H - 1)
    empty = hi_x < lo_x
    lo_x, hi_x = torch.where(empty, torch.zeros_like(lo_x), lo_x), torch.where(empty, torch.zeros_like(hi_x), hi_x)
    empty = hi_y < lo_y
    lo_y, hi_y = torch.where(empty, torch.zeros_like(lo_y), lo_y), torch.where(empty, torch.zeros_like(hi_y), hi_y)
    cw = int((hi_x - lo_x).max()) + 1
    ch = int((hi_y - lo_y).max()) + 1
    x0 = lo_x.long().clamp(max=W - cw)
    y0 = lo_y.long().clamp(max=H - ch)
    return Crop(x0, y0, ch, cw)


def crop_frame(views: Views, cues: FrameCues, flow: FlowTargets | None, c: Crop
               ) -> tuple[Views, FrameCues, FlowTargets | None]:
    """The frame seen through the windows ``c``: principal points shifted, cue maps cut out."""
    C = cues.mask.shape[0]
    K = views.K.clone()
    K[:, 0, 2] -= c.x0.to(K.dtype)
    K[:, 1, 2] -= c.y0.to(K.dtype)
    dev = cues.mask.device
    rr = c.y0[:, None] + torch.arange(c.height, device=dev)[None]  # (C, h)
    cc = c.x0[:, None] + torch.arange(c.width, device=dev)[None]  # (C, w)
    ci = torch.arange(C, device=dev)[:, None, None]

    def cut(x):
        return None if x is None else x[ci, rr[:, :, None], cc[:, None, :]]

    fl = None
    if flow is not None:
        off = torch.stack([c.x0, c.y0], -1).to(flow.target.dtype)[flow.cam]
        fl = FlowTargets(flow.cam, flow.vert, flow.target - off)
    return (Views(K, views.world_to_cam, c.height, c.width),
            FrameCues(cut(cues.mask), cut(cues.normals), cut(cues.occluder), cues.occluder_mesh, cut(cues.image)), fl)


def uncrop_fragments(frags: raster.Fragments, c: Crop, height: int, width: int,
                     occluder: Tensor) -> raster.Fragments:
    """Paste windowed fragments back into full (C, H, W) images (outside: occluder depth, face -1)."""
    C = frags.face_id.shape[0]
    dev = frags.face_id.device
    fid = torch.full((C, height, width), -1, dtype=frags.face_id.dtype, device=dev)
    depth = occluder.to(frags.depth.dtype).clone()
    rr = c.y0[:, None] + torch.arange(c.height, device=dev)[None]
    cc = c.x0[:, None] + torch.arange(c.width, device=dev)[None]
    ci = torch.arange(C, device=dev)[:, None, None]
    fid[ci, rr[:, :, None], cc[:, None, :]] = frags.face_id
    depth[ci, rr[:, :, None], cc[:, None, :]] = frags.depth
    return raster.Fragments(fid, None, depth)  # type: ignore[arg-type]


def downsample(views: Views, cues: FrameCues, flow: FlowTargets | None, factor: int
               ) -> tuple[Views, FrameCues, FlowTargets | None]:
    """The same frame at 1/factor resolution: coarse pixel = factor x factor block of fine pixels.

    Cameras: ``u_coarse = (u - (factor - 1) / 2) / factor`` (pixel centres stay at integer
    coordinates), H // factor x W // factor (a remainder row/column is dropped). Masks
    become soft (the garment fraction of each block, i.e. supersampled area coverage,
    which the antialiased silhouette matches to sub-pixel accuracy); normals are the
    normalised block mean where the whole block is garment with valid normals (else
    none); the occluder depth is the block minimum; flow targets are mapped like pixels.
    A wider basin for the silhouette loss (an edge is seen ``factor`` fine pixels away).
    """
    f = int(factor)
    if f == 1:
        return views, cues, flow
    C, H, W = cues.mask.shape
    Hc, Wc = H // f, W // f
    if Hc < 1 or Wc < 1:
        raise ValueError(f"downsample: {H}x{W} images cannot be reduced by {f}")
    K = views.K.clone()
    K[:, :2, :] = K[:, :2, :] / f
    K[:, 0, 2] = (views.K[:, 0, 2] - (f - 1) / 2) / f
    K[:, 1, 2] = (views.K[:, 1, 2] - (f - 1) / 2) / f
    crop = lambda x: x[:, : Hc * f, : Wc * f]  # noqa: E731
    pool = lambda x: Fnn.avg_pool2d(x, f)  # noqa: E731  (N, ch, H, W)
    soft = cues.mask.double() if cues.mask.is_floating_point() else cues.mask.bool().double()
    m = pool(crop(soft)[:, None])[:, 0]
    normals = None
    if cues.normals is not None:
        n, ok = _sanitize_normals(crop(cues.normals))
        ok = ok & (crop(soft) >= 1)
        okf = ok.double()
        ns = pool((n * okf[..., None]).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        full = pool(okf[:, None])[:, 0] >= 1
        ns = ns / ns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        normals = torch.where(full[..., None], ns, torch.zeros_like(ns))
    occ = -Fnn.max_pool2d(-crop(_occluder_or_inf(cues, views))[:, None], f)[:, 0]
    image = None
    if cues.image is not None:
        image = pool(crop(cues.image.double()).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
    fl = None
    if flow is not None:
        fl = FlowTargets(flow.cam, flow.vert, (flow.target - (f - 1) / 2) / f)
    return Views(K, views.world_to_cam, Hc, Wc), FrameCues(m, normals, occ, None, image), fl


def _evaluate(pb: _Problem, verts: Tensor) -> _Eval:
    """Rasterise ``verts`` and evaluate the loss (no derivatives); keeps what the Jacobians need."""
    v = pb.views
    K, E = v.K, v.world_to_cam
    uv, z = raster.project_vertices(verts, K, E)
    frags = raster.occlude(raster.rasterize(verts, pb.rig.faces, K, E, v.height, v.width, with_bary=False),
                           pb.occluder)
    cfg = pb.cfg
    terms = {"mask": 0.0, "normal": 0.0, "flow": 0.0, "prior": 0.0, "collision": 0.0}
    # 1. silhouette (raster.silhouette): hard coverage + (t - 1/2) where each edge crosses
    hard = (frags.face_id >= 0).reshape(-1).double()
    cr = raster.silhouette_crossings(uv, z, pb.rig.faces, frags, pb.rig.edges)
    V = uv.shape[1]
    uvf = uv.reshape(-1, 2)
    t = raster.crossing_fraction(uvf[cr.cam * V + cr.edge[:, 0]], uvf[cr.cam * V + cr.edge[:, 1]], cr.inside_xy,
                                 cr.outside_xy)
    pix = torch.where(t > 0.5, cr.outside, cr.inside)
    soft = hard.index_add(0, pix, t - 0.5)
    res = soft - pb.mask_flat
    terms["mask"] = float((res * res).sum()) / pb.n_mask
    sil = _SilData(cr.inside_xy, cr.outside_xy, cr.cam, cr.edge, pix, res)
    # 2. normals of the visible faces. A camera normal is n_cam = s R n (n the world unit normal,
    #    R the camera's rotation, s = +-1 turning it towards the camera), so |n_cam - t|^2 =
    #    |n - s R^T t|^2: every pixel's target is taken to world space and the residuals are
    #    grouped per face over all cameras (a face seen by k cameras is one residual, not k).
    nrm = None
    if pb.normals is not None:
        sel = (frags.face_id >= 0) & pb.normal_ok
        c, r, col = sel.nonzero(as_tuple=True)
        f = frags.face_id[c, r, col]
        F = pb.rig.faces.shape[0]
        key, inv, cnt = torch.unique(c * F + f, return_inverse=True, return_counts=True)
        tgt = pb.normals[c, r, col]  # (P, 3)
        tsum = torch.zeros(key.shape[0], 3, dtype=tgt.dtype, device=tgt.device).index_add(0, inv, tgt)
        kc, kf = key // F, key % F  # (U,) camera, face of each pair
        face, finv = torch.unique(kf, return_inverse=True)  # (Fu,) faces seen, (U,) pair -> face
        n, s = _visible_face_normals(verts, pb.rig.faces, E, face, kc, finv)  # (Fu, 3), (U,)
        Rt = E[kc, :3, :3].to(tgt.dtype)  # (U, 3, 3)
        tw = s[:, None] * torch.einsum("uji,uj->ui", Rt, tsum)  # (U, 3) world-space target sums
        count = torch.zeros(face.shape[0], dtype=tgt.dtype, device=tgt.device).index_add(0, finv, cnt.to(tgt.dtype))
        twf = torch.zeros(face.shape[0], 3, dtype=tgt.dtype, device=tgt.device).index_add(0, finv, tw)
        nrm = _NormalData(face, count, twf / count[:, None])
        # sum_p |n_f - t_p|^2 = cnt |n_f|^2 - 2 n_f . sum t + sum |t|^2
        val = float((count * (n * n).sum(-1) - 2 * (n * twf).sum(-1)).sum()) + float((tgt * tgt).sum())
        terms["normal"] = val / pb.n_normal
    # 3. flow targets
    if pb.flow is not None:
        d = uv[pb.flow.cam, pb.flow.vert] - pb.flow.target
        terms["flow"] = float((d * d).sum()) / pb.n_flow
    # 4. first frame: proximal term towards the start (see FitConfig.w_prior_first)
    if pb.prior is not None:
        terms["prior"] = float(((verts - pb.prior) ** 2).sum()) / verts.shape[0]
    # 5. multi-view photo-consistency: colours of the vertices seen twice or more against their mean
    pho = anc = vis_col = None
    terms["photo"] = terms["anchor"] = 0.0
    if pb.photo is not None or pb.anchor_feat is not None:  # vertices whose colour counts
        vis_col = raster.visible_vertices(verts, K, E, frags, cfg.vis_depth_tol) & _pixel_ok(pb.photo_region, uv)
    if pb.photo is not None:
        smp = _sample(pb.photo, uv)  # (C, V, 9)
        vis, ref = _photo_reference(vis_col, smp[..., :3])
        c, vv = vis.nonzero(as_tuple=True)
        value, pho = _cauchy_colour(c, vv, smp[c, vv], ref, cfg.photo_scale)
        terms["photo"] = value / pb.n_photo
    # 6. temporal chromaticity anchor: each visible vertex's chromaticity against its reference
    if pb.anchor_feat is not None:
        c, vv = (vis_col & pb.anchor.seen[None]).nonzero(as_tuple=True)
        value, anc = _cauchy_colour(c, vv, _sample(pb.anchor_feat, uv)[c, vv], pb.anchor.chroma, cfg.anchor_scale)
        terms["anchor"] = value / pb.n_photo
    loss = cfg.w_mask * terms["mask"] + cfg.w_normal * terms["normal"] + cfg.w_flow * terms["flow"]
    # 7. body collision: vertices short of the clearance outside the body (planes fixed per frame)
    if pb.contacts is not None:
        terms["collision"] = float(_collision_residual(pb.contacts, verts, cfg.collision_eps).pow(2).sum()) / V
    loss += cfg.w_prior_first * terms["prior"] + cfg.w_photo * terms["photo"] + cfg.w_anchor * terms["anchor"]
    loss += cfg.w_collision * terms["collision"]
    return _Eval(loss, terms, verts, frags, uv, sil, nrm, pho, anc)


def _cauchy_colour(cam: Tensor, vert: Tensor, samples: Tensor, reference: Tensor, scale: float
                   ) -> tuple[float, _PhotoData]:
    """L_ph's and L_an's common form: samples (N, 9) of photo_features at the (cam, vert) pairs
    (N,) against each vertex's reference (V, 3); the Cauchy loss sum s^2 log(1 + |r|^2 / s^2) and
    what the Gauss-Newton blocks need (residuals, colour gradients, IRLS weights)."""
    r = samples[:, :3] - reference.to(samples.dtype)[vert]
    s2 = scale ** 2
    e = (r * r).sum(-1)
    return (float((s2 * torch.log1p(e / s2)).sum()),
            _PhotoData(cam, vert, r, torch.stack([samples[:, 3:6], samples[:, 6:9]], -1), 1.0 / (1.0 + e / s2)))


def _photo_reference(vis: Tensor, colours: Tensor) -> tuple[Tensor, Tensor]:
    """The (camera, vertex) pairs with an L_ph residual (C, V) bool -- the vertices seen (vis
    (C, V)) by two or more views -- and each vertex's reference colour (V, 3): the mean of its
    colours (C, V, 3) over those views. For the squared loss the mean's own derivative drops out
    of the gradient (the residuals of a vertex sum to 0), so the Gauss-Newton step holds it fixed;
    with the Cauchy weights (unequal per view) that is an approximation, checked only by the
    LM's acceptance test (the exact-gradient test runs in the quadratic regime)."""
    w = vis.to(colours.dtype)[..., None]
    n = w.sum(0)  # (V, 1)
    return vis & (n[:, 0] >= 2)[None], (colours * w).sum(0) / n.clamp_min(1)


def _visible_face_normals(verts: Tensor, faces: Tensor, world_to_cam: Tensor, face: Tensor, cam: Tensor,
                          pair_face: Tensor) -> tuple[Tensor, Tensor]:
    """World-space unit normals (Fu, 3) of the faces ``face`` (Fu,), and for each (camera, face)
    pair -- cameras ``cam`` (U,), ``pair_face`` (U,) indices into ``face`` -- the sign s (U,) that
    turns the normal towards that camera (camera normal = s R n, as :func:`raster.face_normals_cam`)."""
    tri = verts[faces[face]]  # (Fu, 3, 3)
    n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny ** 0.5)
    E = world_to_cam.to(verts.dtype)
    origin = -torch.einsum("cji,cj->ci", E[:, :3, :3], E[:, :3, 3])  # (C, 3) camera centres
    away = (n[pair_face] * (tri.mean(1)[pair_face] - origin[cam])).sum(-1) > 0
    return n, torch.where(away, -1.0, 1.0).to(verts.dtype)


def _normal_corner_jacobian(tri: Tensor) -> tuple[Tensor, Tensor]:
    """World unit normal n = m/|m|, m = (x1 - x0) x (x2 - x0), and d n / d x_k.

    tri (U, 3, 3) corners. Returns n (U, 3) and J (U, 3 [component], 3 [corner], 3 [coordinate]).
    dm/dx0 = [x2 - x1]_x, dm/dx1 = [x0 - x2]_x, dm/dx2 = [x1 - x0]_x;
    d(m/|m|)/dm = (I - n n^T) / |m|.
    """
    x0, x1, x2 = tri.unbind(1)
    m = torch.cross(x1 - x0, x2 - x0, dim=-1)
    ln = m.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    n = m / ln
    A = (torch.eye(3, dtype=tri.dtype, device=tri.device) - n[:, :, None] * n[:, None, :]) / ln[..., None]

    def skew(a):
        x, y, z = a.unbind(-1)
        o = torch.zeros_like(x)
        return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).view(*a.shape[:-1], 3, 3)

    J = torch.stack([A @ skew(x2 - x1), A @ skew(x0 - x2), A @ skew(x1 - x0)], 2)  # (U, 3, 3, 3)
    return n, J


#: dtype of the large Jacobian products in the Levenberg-Marquardt steps: float32 is ~20 %
#: faster per Gauss-Newton system than float64 at ~2e-7 relative error in H and g (skirt, 8
#: views), far below what the step needs; residuals, poses and H, g themselves stay float64.
JACOBIAN_DTYPE = torch.float32


def _gauss_newton(pb: _Problem, ev: _Eval, transforms: Tensor, jdtype=torch.float64) -> tuple[Tensor, Tensor]:
    """H = sum_k w_k/n_k J_k^T J_k and g = sum_k w_k/n_k J_k^T r_k (so that L(d) ~ L + 2 g.d + d.H d).

    ``jdtype``: dtype of the (3V, P) Jacobian products (float64 for the exactness tests,
    :data:`JACOBIAN_DTYPE` in the optimiser).

    J_k = (d r_k / d x) (d x / d delta). Normal and flow residuals are accumulated in
    vertex space first (3x3 blocks of vertex pairs sharing a face, H_x, and g_x), then
    H += Jx^T H_x Jx, g += Jx^T g_x; silhouette residuals (a pixel can collect the
    crossings of several edges) are chained to the parameters row by row.
    """
    cfg = pb.cfg
    rig = pb.rig
    verts = ev.verts
    V = verts.shape[0]
    Jx = skin_jacobian(rig, transforms).to(jdtype).reshape(3 * V, -1)  # (3V, P)
    P = Jx.shape[-1]
    _, Puv = projection_jacobian(verts, pb.views)  # (C, V, 2, 3)
    H = torch.zeros(P, P, dtype=torch.float64, device=verts.device)
    g = torch.zeros(P, dtype=torch.float64, device=verts.device)
    lay = rig.layout
    blocks = torch.zeros(lay.crow.numel() and lay.perm.numel() // 9, 3, 3, dtype=torch.float64, device=verts.device)
    gx = torch.zeros(V, 3, dtype=torch.float64, device=verts.device)
    any_vertex_term = False

    # 1. silhouette: dt/dq by autograd on the gathered edge end points, then chain per pixel
    s = ev.sil
    if cfg.w_mask > 0 and s.pixel.numel():
        uvf = ev.uv.reshape(-1, 2)
        with torch.enable_grad():
            q1 = uvf[s.cam * V + s.edge[:, 0]].detach().requires_grad_()
            q2 = uvf[s.cam * V + s.edge[:, 1]].detach().requires_grad_()
            t = raster.crossing_fraction(q1, q2, s.inside_xy, s.outside_xy)
            g1, g2 = torch.autograd.grad(t.sum(), (q1, q2))
        e0, e1 = s.edge[:, 0], s.edge[:, 1]
        a0 = torch.einsum("ni,nij->nj", g1, Puv[s.cam, e0])  # dt/dx_e0 (N, 3)
        a1 = torch.einsum("ni,nij->nj", g2, Puv[s.cam, e1])
        J3 = Jx.view(V, 3, P)
        Jt = torch.einsum("nj,njp->np", a0.to(jdtype), J3[e0]) + torch.einsum("nj,njp->np", a1.to(jdtype), J3[e1])
        upix, inv = torch.unique(s.pixel, return_inverse=True)
        Jp = torch.zeros(upix.shape[0], P, dtype=jdtype, device=verts.device).index_add(0, inv, Jt)
        w = cfg.w_mask / pb.n_mask
        H += w * (Jp.t() @ Jp).double()
        g += w * (Jp.t() @ s.residual[upix].to(jdtype)).double()
    # 2. normals: per face residual sqrt(count) (n - mean world target), on the face's corners
    if ev.nrm is not None and cfg.w_normal > 0 and ev.nrm.face.numel():
        nd = ev.nrm
        fv = rig.faces[nd.face]  # (U, 3)
        n, Jn = _normal_corner_jacobian(verts[fv])  # (U, 3), (U, 3 comp, 3 corner, 3 coord)
        w = cfg.w_normal / pb.n_normal
        cnt = nd.count
        r = n - nd.mean_target  # residual sqrt(cnt) r, Jacobian sqrt(cnt) Jn
        # block[k, l] = cnt sum_i Jn[i, k]^T Jn[i, l];  g_k = cnt sum_i Jn[i, k]^T r_i
        blk = torch.einsum("u,uikj,uilm->ukljm", w * cnt, Jn, Jn)  # (U, 3, 3, 3, 3)
        blocks.index_add_(0, lay.face_pair[nd.face].reshape(-1), blk.reshape(-1, 3, 3))
        gk = torch.einsum("u,uikj,ui->ukj", w * cnt, Jn, r)  # (U, 3 corner, 3)
        gx.index_add_(0, fv.reshape(-1), gk.reshape(-1, 3))
        any_vertex_term = True
    # 3. flow: d uv / d x of one vertex
    if pb.flow is not None and cfg.w_flow > 0:
        fl = pb.flow
        w = cfg.w_flow / pb.n_flow
        r = ev.uv[fl.cam, fl.vert] - fl.target  # (N, 2)
        Pf = Puv[fl.cam, fl.vert]  # (N, 2, 3)
        blocks.index_add_(0, lay.diag[fl.vert], w * Pf.transpose(1, 2) @ Pf)
        gx.index_add_(0, fl.vert, w * torch.einsum("nij,ni->nj", Pf, r))
        any_vertex_term = True
    # 4. photo-consistency and 5. chromaticity anchor (IRLS): residual sqrt(weight) (colour - reference),
    # d colour / d x = dI/duv duv/dx (the anchor's reference is fixed: exact)
    for cd, wt in ((ev.pho, cfg.w_photo), (ev.anc, cfg.w_anchor)):
        if cd is not None and wt > 0 and cd.cam.numel():
            Jr = cd.grad @ Puv[cd.cam, cd.vert]  # (N, 3, 3)
            w = (wt / pb.n_photo) * cd.weight
            blocks.index_add_(0, lay.diag[cd.vert], w[:, None, None] * Jr.transpose(1, 2) @ Jr)
            gx.index_add_(0, cd.vert, w[:, None] * torch.einsum("nij,ni->nj", Jr, cd.residual))
            any_vertex_term = True
    # 6. proximal term: residual sqrt(w / V) (x - x_start), identity Jacobian on each vertex
    if pb.prior is not None:
        blocks.index_add_(0, lay.diag, pb.w_prior * torch.eye(3, dtype=blocks.dtype, device=blocks.device).expand(V, 3, 3))
        gx += pb.w_prior * (verts - pb.prior)
        any_vertex_term = True
    # 7. body collision: residual sqrt(w / V) max(0, eps - (x - p).n), Jacobian -n^T where active
    if pb.contacts is not None:
        ct = pb.contacts
        r = _collision_residual(ct, verts, cfg.collision_eps)
        on = r > 0
        if bool(on.any()):
            vv, nn, w = ct.vert[on], ct.normal[on].to(verts.dtype), cfg.w_collision / V
            blocks.index_add_(0, lay.diag[vv], w * nn[:, :, None] * nn[:, None, :])
            gx.index_add_(0, vv, -w * r[on][:, None] * nn)
            any_vertex_term = True
    if any_vertex_term:
        Hx = lay.matrix(blocks.to(jdtype))
        H += (Jx.t() @ (Hx @ Jx)).double()
        g += (Jx.t() @ gx.reshape(-1).to(jdtype)).double()
    return H, g


def loss_terms(rig: RigParts, views: Views, cues: FrameCues, verts: Tensor, flow: FlowTargets | None = None,
               cfg: FitConfig = FitConfig(), fragments: raster.Fragments | None = None,
               prior: Tensor | None = None, anchor: AnchorRef | None = None,
               contacts: Contacts | None = None) -> tuple[Tensor, dict]:
    """Differentiable (autograd) total loss of a mesh ``verts`` (V, 3) and its unweighted terms.

    The same loss :func:`fit_frame` minimises, built from :func:`raster.silhouette`,
    :func:`raster.render_face_normals` and :func:`raster.project_vertices`, for the
    vertex ablation and to check the Gauss-Newton gradients. ``fragments``: visibility
    to hold fixed (default: rasterise ``verts``); anchor: L_an's references (None: L_an off).
    """
    pb = _make_problem(rig, views, cues, flow, cfg, prior, anchor, contacts)
    K, E = views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype)
    if fragments is None:
        fragments = raster.occlude(raster.rasterize(verts.detach(), rig.faces, K, E, views.height, views.width,
                                                    with_bary=False),
                                   pb.occluder)
    s = raster.silhouette(verts, rig.faces, K, E, fragments, rig.edges)
    lm = ((s - pb.mask.to(s.dtype)) ** 2).sum() / pb.n_mask
    terms = {"mask": lm, "normal": lm.new_zeros(()), "flow": lm.new_zeros(()), "prior": lm.new_zeros(())}
    if pb.normals is not None:
        n = raster.render_face_normals(verts, rig.faces, E, fragments)
        sel = (fragments.face_id >= 0) & pb.normal_ok
        terms["normal"] = ((n - pb.normals.to(n.dtype)) ** 2).sum(-1)[sel].sum() / pb.n_normal
    if pb.flow is not None:
        uv, _ = raster.project_vertices(verts, K, E)
        d = uv[pb.flow.cam, pb.flow.vert] - pb.flow.target.to(uv.dtype)
        terms["flow"] = (d * d).sum() / pb.n_flow
    if pb.prior is not None:
        terms["prior"] = ((verts - pb.prior.to(verts.dtype)) ** 2).sum() / verts.shape[0]
    terms["photo"] = lm.new_zeros(())
    if pb.photo is not None:  # colours bilinear in the blurred image (visibility held fixed: fragments)
        uv, _ = raster.project_vertices(verts, K, E)
        with torch.no_grad():
            vis = raster.visible_vertices(verts.detach(), K, E, fragments, cfg.vis_depth_tol)
            vis &= _pixel_ok(pb.photo_region, uv.detach())
        col = _sample(pb.photo[:, :3], uv)  # (C, V, 3)
        vis, ref = _photo_reference(vis, col)
        r = (col - ref.to(col.dtype)[None])[vis]
        s2 = cfg.photo_scale ** 2
        terms["photo"] = (s2 * torch.log1p((r * r).sum(-1) / s2)).sum() / pb.n_photo
    terms["anchor"] = lm.new_zeros(())
    if pb.anchor_feat is not None:  # chromaticity against each vertex's reference (visibility held fixed)
        uv, _ = raster.project_vertices(verts, K, E)
        with torch.no_grad():
            vis = raster.visible_vertices(verts.detach(), K, E, fragments, cfg.vis_depth_tol)
            vis &= _pixel_ok(pb.photo_region, uv.detach()) & pb.anchor.seen[None]
        r = (_sample(pb.anchor_feat[:, :3], uv) - pb.anchor.chroma.to(uv.dtype)[None])[vis]
        s2 = cfg.anchor_scale ** 2
        terms["anchor"] = (s2 * torch.log1p((r * r).sum(-1) / s2)).sum() / pb.n_photo
    terms["collision"] = lm.new_zeros(())
    if pb.contacts is not None:
        terms["collision"] = _collision_residual(pb.contacts, verts, cfg.collision_eps).pow(2).sum() / verts.shape[0]
    total = cfg.w_mask * terms["mask"] + cfg.w_normal * terms["normal"] + cfg.w_flow * terms["flow"]
    total = total + cfg.w_prior_first * terms["prior"] + cfg.w_photo * terms["photo"] + cfg.w_anchor * terms["anchor"]
    total = total + cfg.w_collision * terms["collision"]
    return total, terms


# --------------------------------------------------------------------------------------
# per-frame optimisers
# --------------------------------------------------------------------------------------


def _flow_align(rig: RigParts, views: Views, flow: FlowTargets, transforms: Tensor, iters: int) -> Tensor:
    """Minimise L_of alone over the bone increments by damped Gauss-Newton (no rasterisation).

    The flow residuals are vertex projections, nearly linear in the increments, so a few
    steps move the previous frame's pose to where the flow says the visible vertices
    went; the full loss then starts from there (frame t is still initialised from t-1).
    Every step must lower L_of, else the pose before it is kept.
    """
    G = transforms.double().clone()
    # only the U vertices with a target count: the rig restricted to them (skin_jacobian and
    # lbs read rest, weights and centres only)
    used, slot = torch.unique(flow.vert, return_inverse=True)
    U = used.numel()
    sub = rig._replace(rest=rig.rest[used], weights=rig.weights[used])

    def cost(M):
        uv, _ = raster.project_vertices(lbs(sub.rest, sub.weights, M), views.K, views.world_to_cam)
        d = uv[flow.cam, slot] - flow.target
        return float((d * d).sum())

    c = cost(G)
    for _ in range(iters):
        x = lbs(sub.rest, sub.weights, G)  # (U, 3)
        J3 = skin_jacobian(sub, G).to(JACOBIAN_DTYPE)  # (U, 3, P)
        uv, Puv = projection_jacobian(x, views)
        Pf = Puv[flow.cam, slot]  # (N, 2, 3)
        r = uv[flow.cam, slot] - flow.target
        blocks = torch.zeros(U, 3, 3, dtype=x.dtype, device=x.device).index_add_(0, slot, Pf.transpose(1, 2) @ Pf)
        gx = torch.zeros(U, 3, dtype=x.dtype, device=x.device).index_add_(0, slot, torch.einsum("nij,ni->nj", Pf, r))
        BJ = torch.einsum("vjk,vkq->vjq", blocks.to(J3.dtype), J3).reshape(3 * U, -1)  # (3U, P)
        H = (J3.reshape(3 * U, -1).t() @ BJ).double()
        g = (J3.reshape(3 * U, -1).t() @ gx.reshape(-1).to(J3.dtype)).double()
        d = H.diagonal()
        delta, info = torch.linalg.solve_ex(H + torch.diag(1e-3 * d + 1e-9 * float(d.max().clamp_min(1e-30))), -g)
        if int(info) != 0 or not bool(torch.isfinite(delta).all()):
            break
        G_new = apply_increment(G, rig.centres, delta.view(-1, 6))
        c_new = cost(G_new)
        if not c_new < c:
            break
        gain = (c - c_new) / max(c, 1e-30)
        G, c = G_new, c_new
        if gain < 1e-3:
            break
    return G


def _lm(pb: _Problem, transforms: Tensor, max_iters: int) -> FrameFit:
    """Levenberg-Marquardt on the bone increments (see the module docstring)."""
    cfg, rig = pb.cfg, pb.rig
    G = transforms.double().clone()
    ev = _evaluate(pb, lbs(rig.rest, rig.weights, G))
    if not math.isfinite(ev.loss):
        raise ValueError("fit: the loss at the starting pose is not finite (check the cues and the start pose)")
    curve = [ev.loss]
    H, g = _gauss_newton(pb, ev, G, JACOBIAN_DTYPE)
    mu, nu = None, 2.0
    it, converged = 0, False
    while it < max_iters:
        d = H.diagonal()
        dscale = d.clamp_min(1e-9 * float(d.max().clamp_min(1e-30)))
        if mu is None:
            mu = cfg.damping * float(d.max().clamp_min(1e-30))
        if float(g.abs().max()) == 0.0:
            converged = True
            break
        A = H + mu * torch.diag(dscale)
        delta, info = torch.linalg.solve_ex(A, -g)
        it += 1
        if int(info) != 0 or not bool(torch.isfinite(delta).all()):
            mu *= nu
            nu *= 2
            continue
        pred = -float(2 * g @ delta + delta @ H @ delta)
        G_new = apply_increment(G, rig.centres, delta.view(-1, 6))
        ev_new = _evaluate(pb, lbs(rig.rest, rig.weights, G_new))
        gain = ev.loss - ev_new.loss
        if math.isfinite(ev_new.loss) and gain > 0:
            rho = gain / pred if pred > 0 else 1.0
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            small = gain < cfg.rel_tol * ev.loss or float(delta.abs().max()) < cfg.step_tol
            G, ev = G_new, ev_new
            curve.append(ev.loss)
            if small:
                converged = True
                break
            H, g = _gauss_newton(pb, ev, G, JACOBIAN_DTYPE)
        else:
            if float(delta.abs().max()) < cfg.step_tol:
                converged = True
                break
            mu *= nu
            nu *= 2
    return FrameFit(G.clone(), ev.verts, dict(ev.terms), ev.loss, it, converged, curve, ev.fragments)


def _vertex_adam(pb: _Problem, cues: FrameCues, start_verts: Tensor, transforms: Tensor, max_iters: int) -> FrameFit:
    """Ablation (a): Adam on the vertex positions, same loss (autograd through the renderer)."""
    cfg, rig, views = pb.cfg, pb.rig, pb.views
    x = start_verts.double().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=cfg.vertex_lr)
    best, best_x, since = float("inf"), x.detach().clone(), 0
    curve = []
    it, converged = 0, False
    for it in range(1, max_iters + 1):
        opt.zero_grad()
        total, terms = loss_terms(rig, views, cues, x, pb.flow, cfg, prior=pb.prior)
        val = float(total)
        if not math.isfinite(val):
            break
        if val < best * (1 - cfg.rel_tol):
            since = 0
        else:
            since += 1
        if val < best:
            best, best_x = val, x.detach().clone()
        curve.append(val)
        if since >= cfg.vertex_patience:
            converged = True
            break
        total.backward()
        if not bool(torch.isfinite(x.grad).all()):
            break
        opt.step()
    ev = _evaluate(pb, best_x)
    return FrameFit(transforms.double().clone(), best_x, dict(ev.terms), ev.loss, it, converged, curve, ev.fragments)


def fit_frame(rig: RigParts, views: Views, cues: FrameCues, init: Tensor, cfg: FitConfig = FitConfig(),
              flow: FlowTargets | None = None, first: bool = False, init_verts: Tensor | None = None,
              anchor: AnchorRef | None = None) -> FrameFit:
    """Fit one frame.

    init: (B, 4, 4) starting bone transforms (frame t-1's result, or the first frame's
    start); flow: targets from :func:`flow_targets` (None at the first frame or without
    flow); first: use ``max_iters_first``. For ``cfg.method == 'vertex'`` the start mesh is
    ``init_verts`` (V, 3) (default: LBS of ``init``) and ``init`` is returned unchanged.
    anchor: L_an's references (:func:`update_anchor`; used when ``cfg.w_anchor`` > 0 and the cues
    carry images).
    Never returns non-finite poses: steps with a non-finite loss are rejected.
    """
    init = torch.as_tensor(init, device=rig.rest.device).double()
    if init.shape != (rig.weights.shape[1], 4, 4):
        raise ValueError(f"fit_frame: init must be ({rig.weights.shape[1]}, 4, 4), got {tuple(init.shape)}")
    if not bool(torch.isfinite(init).all()):
        raise ValueError("fit_frame: the starting transforms contain NaN or inf")
    _check_cues(views, cues)
    flow = None if first else flow
    full_hw = (views.height, views.width)
    G, spent = init, 0
    if cfg.method == "vertex":
        x_start = lbs(rig.rest, rig.weights, init) if init_verts is None else init_verts.double()
    else:
        if flow is not None and cfg.w_flow > 0 and cfg.flow_align_iters > 0 and flow.cam.numel():
            G = _flow_align(rig, views, flow, G, cfg.flow_align_iters)
        x_start = lbs(rig.rest, rig.weights, G)
    prior = lbs(rig.rest, rig.weights, init) if first and cfg.method == "rig" else (x_start if first else None)
    contacts = None
    if cfg.w_collision > 0 and cfg.method == "rig":
        if cues.occluder_mesh is None:
            raise ValueError("fit: w_collision > 0 needs the body mesh (FrameCues.occluder_mesh)")
        contacts = body_contacts(x_start, *cues.occluder_mesh, cfg.collision_radius)
    window = None
    if cfg.crop_margin >= 0:  # render only the windows that can hold the garment
        window = crop_window(views, cues.mask, x_start, cfg.crop_margin)
        views, cues, flow = crop_frame(views, cues, flow, window)
    if cues.occluder is None:  # the body's depth, in the windows only
        cues = cues._replace(occluder=_occluder_or_inf(cues, views), occluder_mesh=None)
    if cfg.method == "vertex":
        pb = _make_problem(rig, views, cues, flow, cfg, prior)
        res = _vertex_adam(pb, cues, x_start, init, cfg.vertex_max_iters * (3 if first else 1))
    else:
        for f in cfg.levels_first if first else cfg.levels:
            pb = _make_problem(rig, *downsample(views, cues, flow, f), cfg, prior, anchor, contacts)
            res = _lm(pb, G, cfg.max_iters_first if first else cfg.max_iters)
            G, spent = res.transforms, spent + res.iterations
        res.iterations = spent  # the curve and terms are those of the full resolution
    if window is not None:  # visibility in whole images (outside the windows: no garment)
        res.fragments = uncrop_fragments(res.fragments, window, full_hw[0], full_hw[1],
                                         torch.full((views.K.shape[0], *full_hw), float("inf"), dtype=torch.float64,
                                                    device=views.K.device))
    return res


def smooth_transforms(transforms: Tensor, passes: int = 1) -> Tensor:
    """Temporal filter of bone transforms (T, B, 4, 4) -> (T, B, 4, 4) (not in the paper).

    Each pass replaces every inner frame by (G[t-1] + 2 G[t] + G[t+1]) / 4 (the first and last
    frames are kept) and projects the rotation block back onto SO(3) (the closest rotation,
    by SVD). Skinning is linear in the transforms, so before the projection the skinned
    vertices are the same filter of the fitted vertices; the projection changes them only by
    the spread of the three rotations (second order). A rotation at constant angular velocity
    and a translation at constant velocity pass unchanged. Cuts the frame-to-frame jitter of
    per-frame fits (benchmarks/fit.md, variant anchor_smooth).
    """
    G = torch.as_tensor(transforms).clone()
    if G.ndim != 4 or G.shape[-2:] != (4, 4):
        raise ValueError(f"smooth_transforms: transforms must be (T, B, 4, 4), got {tuple(G.shape)}")
    for _ in range(int(passes)):
        if G.shape[0] < 3:
            break
        inner = 0.25 * G[:-2] + 0.5 * G[1:-1] + 0.25 * G[2:]
        inner[..., :3, :3] = nearest_rotation(inner[..., :3, :3])
        G[1:-1] = inner
    return G


def fit_sequence(rig: RigParts, views: Views, num_frames: int, cues_of: Callable[[int], FrameCues],
                 flow_of: Callable[[int], tuple[Tensor, Tensor | None] | None], init: Tensor,
                 cfg: FitConfig = FitConfig(), progress: bool = True, log=None,
                 anchor_init: AnchorRef | None = None) -> list[FrameFit]:
    """Fit frames 0..T-1 in order, frame t starting from frame t-1's result.

    cues_of(t) -> :class:`FrameCues` (with ``image`` for L_ph and L_an); flow_of(t) -> (flow (C, H, W, 2), valid (C, H, W)
    or None) of t-1 -> t, or None (no flow for that frame: L_of off there, logged);
    init: (B, 4, 4) start of frame 0. Returns one :class:`FrameFit` per frame (with the
    wall time of each in ``terms['wall_s']``). L_an's references are taken from each frame's
    result (:func:`update_anchor`) and used from the next frame on; ``anchor_init`` (e.g.
    :func:`texture_anchor`) gives references from frame 0 on (vertices it covers keep them).
    """
    from tqdm import tqdm

    out: list[FrameFit] = []
    G = torch.as_tensor(init, device=rig.rest.device).double()
    x_prev = None
    prev_mask = None
    anchor = anchor_init
    for t in tqdm(range(num_frames), desc="fit", unit="frame", disable=not progress):
        t0 = time.perf_counter()
        cues = cues_of(t)
        targets = None
        if t > 0 and cfg.w_flow > 0:
            fl = flow_of(t)
            if fl is None:
                if log is not None:
                    log.warning("fit: frame %d has no flow; L_of is off for it", t)
            else:
                prev = out[-1]
                targets = flow_targets(prev.verts, views, prev.fragments, fl[0], fl[1], prev_mask, cfg.vis_depth_tol,
                                       cfg.flow_margin_px)
        res = fit_frame(rig, views, cues, G, cfg, targets, first=(t == 0), init_verts=x_prev, anchor=anchor)
        if cfg.w_anchor > 0 and cues.image is not None:
            anchor = update_anchor(anchor, res.verts, views, res.fragments, cues.image, cues.mask, cfg)
        res.terms["wall_s"] = time.perf_counter() - t0
        res.terms["flow_targets"] = 0 if targets is None else int(targets.cam.numel())
        out.append(res)
        G = res.transforms
        x_prev = res.verts if cfg.method == "vertex" else None
        prev_mask = cues.mask
    if cfg.smooth_passes > 0 and cfg.method == "rig" and len(out) >= 3:
        Gs = smooth_transforms(torch.stack([r.transforms for r in out]), cfg.smooth_passes)
        for r, g in zip(out, Gs):
            r.transforms, r.verts = g, lbs(rig.rest, rig.weights, g)
    return out
