"""What one frame's fit holds fixed: rig, views, cues, render windows (AniDress §3.2, DESIGN.md §8).

:func:`anidress_core.fit.make_problem` gathers what stays fixed while one frame is optimised (:class:`Problem`):
the masks, the body occluder's depth, and each loss term's state (:mod:`anidress_core.fit.terms`). As in the paper
every term is a sum (over views and pixels or targets); all of them are divided by one common constant, the number
of garment pixels in the masks (``Problem.n_px``), so that their ratios are the paper's whatever the image size and
number of views. The renders are cut to a window per view around the mask and the start pose
(``FitConfig.crop_margin``, :func:`crop_window`). Shapes: V vertices, F faces, B bones, C cameras, H, W image size,
N residuals. Float64 for poses and geometry; CPU or CUDA (whatever device the inputs are on).
"""
from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as Fnn
from torch import Tensor

from .. import raster
from ..geometry import nearest_rotation
from ..rig import RigModel, fit_transforms
from .config import FitConfig

__all__ = ["RigParts", "HessianLayout", "Views", "FrameCues", "FlowTargets", "Problem", "Rendered", "Linearisation",
           "System", "occluder_depth", "occluder_or_inf", "check_cues",
           "cue_notes", "Crop", "crop_window", "crop_frame", "uncrop_fragments", "image_finite"]


class RigParts(NamedTuple):
    """The garment rig as the fit uses it (float64, one device); build with :meth:`make`."""

    rest: Tensor  # (V, 3) rest vertices (body canonical frame)
    weights: Tensor  # (V, B) convex skinning weights
    centres: Tensor  # (B, 3) rest-pose bone centres
    faces: Tensor  # (F, 3) int64
    edges: tuple  # raster.mesh_edges(faces): (E, 2) vertex ids, (E, 2) faces either side
    layout: "HessianLayout"  # sparsity pattern of the vertex-space Gauss-Newton matrix

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
        return RigParts(rest, weights, centres, faces, raster.mesh_edges(faces), HessianLayout.make(faces, V))

    def closest_pose(self, verts: Tensor) -> Tensor:
        """(T, B, 4, 4) float64: the bone transforms that best explain ``verts`` (T, V, 3)
        (:func:`anidress_core.rig.fit_transforms`)."""
        model = RigModel(self.rest, self.weights, self.rest.new_zeros(0, self.weights.shape[1], 4, 4), self.centres,
                         float("nan"))
        return fit_transforms(model, verts).double()


class HessianLayout(NamedTuple):
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
    def make(faces: Tensor, V: int) -> "HessianLayout":
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
        return HessianLayout(V, face_pair, diag, perm, crow, cols[perm])

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
        nonzero = (cams.dist.abs() > 1e-9).sum(-1).tolist()  # per camera, of k1 k2 p1 p2 k3
        bad = [f"{n} ({k} non-zero coefficient{'s' if k > 1 else ''})" for n, k in zip(cams.names, nonzero) if k]
        if bad:
            raise ValueError(f"fit: cameras {', '.join(bad)} have lens distortion, which the rasteriser does not "
                             "model: read the sequence undistorted by rule undistort (command line: --undistorted "
                             "DIR; Python: undistorted_dir=, anidress_core.io.scene.sequence_source)")
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

    mask: Tensor  # (C, H, W) bool garment pixels (label 2), or float garment coverage in [0, 1]; NaN = unknown
    # (a float mask's NaN pixels are left out of every pixel term: L_silhouette's :attr:`Target.known`)
    normals: Tensor | None  # (C, H, W, 3) camera-space unit normals; non-finite / zero = none
    occluder: Tensor | None  # (C, H, W) camera z of the body (+inf where none), see occluder_depth
    occluder_mesh: tuple | None = None
    """(verts (Vb, 3), faces (Fb, 3)) of the occluder (the posed body), rasterised by
    :func:`fit_frame` in its render windows when ``occluder`` is None (cheaper)."""
    image: Tensor | None = None
    """(C, H, W, 3) colour images in [0, 1] for L_anchor, or None (L_anchor off)."""


class FlowTargets(NamedTuple):
    """Where the flow says visible vertices of the previous fitted mesh went (N targets)."""

    cam: Tensor  # (N,) int64
    vert: Tensor  # (N,) int64
    target: Tensor  # (N, 2) float64 pixel positions in frame t


def occluder_depth(verts: Tensor, faces: Tensor, views: Views) -> Tensor:
    """(C, H, W) camera z of an occluding mesh (the posed body), +inf where it is absent."""
    return raster.rasterize(verts, faces, views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype),
                            views.height, views.width, with_bary=False).depth


def occluder_or_inf(cues: FrameCues, views: Views) -> Tensor:
    """(C, H, W) float64 occluder depth of the cues (rasterised from occluder_mesh if needed; +inf: none)."""
    if cues.occluder is not None:
        occ = cues.occluder.double()
    elif cues.occluder_mesh is not None:
        occ = occluder_depth(cues.occluder_mesh[0].double(), cues.occluder_mesh[1], views).double()
    else:
        return torch.full(cues.mask.shape, float("inf"), dtype=torch.float64, device=cues.mask.device)
    return torch.where(torch.isnan(occ), torch.full_like(occ, float("inf")), occ)


def check_cues(views: Views, cues: FrameCues) -> None:
    """ValueError naming the cue whose shape is not the views' (C, H, W) (normals: (C, H, W, 3))."""
    C, H, W = views.K.shape[0], views.height, views.width
    for name, x, shape in (("mask", cues.mask, (C, H, W)), ("occluder depth", cues.occluder, (C, H, W)),
                           ("normals", cues.normals, (C, H, W, 3))):
        if x is not None and tuple(x.shape) != shape:
            raise ValueError(f"fit: {name} must be {shape}, got {tuple(x.shape)}")


def cue_notes(cues: FrameCues, flow: FlowTargets | None) -> tuple[FrameCues, FlowTargets | None, dict]:
    """Sanitise one frame's cues and say what was done (the ``notes`` of :class:`FrameFit`).

    1. A view whose mask has no garment pixel (none known to be garment) is dropped: its mask
       becomes NaN (unknown) so that no pixel term reads it. An empty view says only "no
       garment here", which for a garment inside the cameras is a failed mask; kept, the
       silhouette term would push the garment out of that view.
    2. NaN pixels of a float mask are unknown (counted); non-finite normals and image pixels are
       left out by the terms (counted).
    3. Flow targets with a non-finite target are dropped (counted); none left: None.
    Returns the cues (mask float with NaN where dropped, if any view was), the flow targets and the notes.
    """
    notes: dict = {}
    m = cues.mask
    if m.is_floating_point():
        unknown = ~torch.isfinite(m)
        if bool(unknown.any()):
            notes["mask_unknown_px"] = int(unknown.sum())
        garment = torch.where(unknown, torch.zeros_like(m), m) > 0.5
    else:
        garment = m.bool()
    empty = ~garment.flatten(1).any(1)  # (C,)
    if bool(empty.any()):
        notes["views_dropped"] = empty.nonzero().flatten().tolist()
        mf = m.double() if m.is_floating_point() else m.bool().double()
        cues = cues._replace(mask=torch.where(empty[:, None, None], torch.full_like(mf, float("nan")), mf))
        if bool(empty.all()):
            notes["no_mask"] = True
    if cues.normals is not None:
        bad = ~torch.isfinite(cues.normals).all(-1) & garment
        if bool(bad.any()):
            notes["normals_nonfinite_px"] = int(bad.sum())
    if cues.image is not None:
        bad = ~torch.isfinite(cues.image).all(-1)
        if bool(bad.any()):
            notes["image_nonfinite_px"] = int(bad.sum())
    if flow is not None:
        ok = torch.isfinite(flow.target).all(-1)
        if not bool(ok.all()):
            notes["flow_targets_nonfinite"] = int((~ok).sum())
            flow = FlowTargets(flow.cam[ok], flow.vert[ok], flow.target[ok])
        if flow.cam.numel() == 0:
            flow = None
    return cues, flow, notes


class Problem(NamedTuple):
    """Everything fixed during one frame's optimisation (:func:`anidress_core.fit.make_problem`): what every
    term reads, and each term's own state (:mod:`anidress_core.fit.terms`, its ``setup``)."""

    rig: RigParts
    views: Views
    cfg: FitConfig
    coverage: Tensor  # (C, H, W) float64 garment coverage of the masks in [0, 1] (0 where unknown)
    n_px: float  # the common normaliser of every image term: garment pixels in the masks (at least 1)
    occluder: Tensor  # (C, H, W) body depth (+inf: none)
    states: dict  # term name -> its state for this frame (None: the term is off)


class Rendered(NamedTuple):
    """One evaluation's render of the mesh: what every term's ``value`` reads."""

    verts: Tensor  # (V, 3)
    uv: Tensor  # (C, V, 2) vertex projections
    z: Tensor  # (C, V) camera depths
    fragments: raster.Fragments  # occluded fragments (visibility)


class Linearisation(NamedTuple):
    """Where a term's ``gauss_newton`` linearises its residuals: the mesh and its derivatives."""

    verts: Tensor  # (V, 3)
    uv: Tensor  # (C, V, 2)
    Puv: Tensor  # (C, V, 2, 3) d uv / d x
    Jx: Tensor  # (3V, P) d x / d(bone increments), in ``jdtype``
    jdtype: torch.dtype  # dtype of the (3V, P) Jacobian products


class System(NamedTuple):
    """The Gauss-Newton system a term's ``gauss_newton`` adds to, in place: H (P, P) and g (P,) directly, or
    the vertex-space blocks (pairs, 3, 3) of :class:`HessianLayout` and gradient gx (V, 3), chained once."""

    H: Tensor
    g: Tensor
    blocks: Tensor
    gx: Tensor


def image_finite(image: Tensor, blur: float) -> Tensor:
    """(C, H, W) bool: pixels of ``image`` (C, H, W, 3) at least ceil(3 blur) + 1 pixels from any
    non-finite value (the pixels that :func:`anidress_core.fit.images.image_features` computes from finite data)."""
    bad = ~torch.isfinite(image).all(-1)
    if not bool(bad.any()):
        return ~bad
    r = int(math.ceil(3 * blur)) + 1
    grown = Fnn.max_pool2d(bad.double()[:, None], 2 * r + 1, stride=1, padding=r)[:, 0] > 0
    return ~grown


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

    def span(lo: Tensor, hi: Tensor, lines: Tensor, size: int) -> tuple[Tensor, int]:
        """(C,) window starts and the common length along one axis; lines (C, size): garment columns or rows."""
        ar = torch.arange(size, device=mask.device, dtype=uv.dtype)
        lo = (torch.minimum(lo, torch.where(lines, ar, big).amin(1)) - margin).clamp(0, size - 1)
        hi = (torch.maximum(hi, torch.where(lines, ar, -big).amax(1)) + margin).clamp(0, size - 1)
        empty = hi < lo
        lo, hi = torch.where(empty, torch.zeros_like(lo), lo), torch.where(empty, torch.zeros_like(hi), hi)
        n = int((hi - lo).max()) + 1
        return lo.long().clamp(max=size - n), n

    (x0, cw), (y0, ch) = span(lo[:, 0], hi[:, 0], m.any(1), W), span(lo[:, 1], hi[:, 1], m.any(2), H)
    return Crop(x0, y0, ch, cw)


def _window_pixels(c: Crop) -> tuple[Tensor, Tensor, Tensor]:
    """Index tensors (C, 1, 1), (C, h, 1), (C, 1, w) of the windows' pixels in whole (C, H, W) images."""
    dev = c.x0.device
    return (torch.arange(c.x0.shape[0], device=dev)[:, None, None],
            (c.y0[:, None] + torch.arange(c.height, device=dev)[None])[:, :, None],
            (c.x0[:, None] + torch.arange(c.width, device=dev)[None])[:, None, :])


def crop_frame(views: Views, cues: FrameCues, flow: FlowTargets | None, c: Crop
               ) -> tuple[Views, FrameCues, FlowTargets | None]:
    """The frame seen through the windows ``c``: principal points shifted, cue maps cut out."""
    K = views.K.clone()
    K[:, 0, 2] -= c.x0.to(K.dtype)
    K[:, 1, 2] -= c.y0.to(K.dtype)
    px = _window_pixels(c)

    def cut(x):
        return None if x is None else x[px]

    fl = None
    if flow is not None:
        off = torch.stack([c.x0, c.y0], -1).to(flow.target.dtype)[flow.cam]
        fl = FlowTargets(flow.cam, flow.vert, flow.target - off)
    return (Views(K, views.world_to_cam, c.height, c.width),
            FrameCues(cut(cues.mask), cut(cues.normals), cut(cues.occluder), cues.occluder_mesh, cut(cues.image)), fl)


def uncrop_fragments(frags: raster.Fragments, c: Crop, height: int, width: int,
                     occluder: Tensor | None = None) -> raster.Fragments:
    """Paste windowed fragments back into full (C, H, W) images (outside: face -1, the occluder's depth or +inf)."""
    C, dev = frags.face_id.shape[0], frags.face_id.device
    fid = torch.full((C, height, width), -1, dtype=frags.face_id.dtype, device=dev)
    depth = (torch.full((C, height, width), float("inf"), dtype=frags.depth.dtype, device=dev) if occluder is None
             else occluder.to(frags.depth.dtype).clone())
    px = _window_pixels(c)
    fid[px], depth[px] = frags.face_id, frags.depth
    return raster.Fragments(fid, None, depth)  # type: ignore[arg-type]
