"""L_anchor (ours, not in the paper): the temporal chromaticity anchor.

Every vertex keeps the chromaticity rgb / (r + g + b) of its reference (:class:`AnchorRef`); at
every frame each (view, visible vertex) pays a robust Cauchy loss s^2 log(1 + |r|^2 / s^2) of its
chromaticity there (blurred image, bilinear) against that reference, summed and divided by the
problem's garment pixel count. Weight ``fit/weights/anchor``, Cauchy scale ``fit/anchor_scale``.
Chromaticity does not change with Lambertian shading under white light, which the colour itself does as the
garment turns; a reference that follows the material point holds a vertex on it over many frames, which L_flow's
chained targets do not (studies/fit/fit_drift.md).

References (``fit/anchor_reference``): ``images``, each vertex's chromaticity in the first frame it is seen
(:func:`update_anchor`; a start error stays), or ``texture``, the garment's texture at the template's UVs
(:func:`texture_anchor`): then L_anchor sees where each material point is from frame 0 on, which masks, normals
and flow cannot (studies/fit/fit_normal_weight.md).

Gauss-Newton: IRLS, residual sqrt(weight) (colour - reference), d colour / d x = dI/duv duv/dx
with dI/duv the central differences of the blurred image (:func:`anidress_core.fit.images.image_features`).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ... import raster
from ..config import FitConfig
from ..images import chromaticity, eroded, image_features, pixel_ok, sample, sample_blurred
from ..problem import FrameCues, Linearisation, Problem, Rendered, System, Views, image_finite

NAME = "anchor"


class AnchorRef(NamedTuple):
    """L_anchor's references: each vertex's chromaticity in the first frame it was seen."""

    chroma: Tensor  # (V, 3)
    seen: Tensor  # (V,) bool: has a reference


class Colours(NamedTuple):
    """L_anchor's state: the references and the frame's images."""

    ref: AnchorRef
    feat: Tensor  # (C, 9, H, W) image_features of the chromaticity
    region: Tensor  # (C, H, W) bool: where colours count (the eroded garment mask, away from non-finite pixels)


class ColourData(NamedTuple):
    cam: Tensor  # (N,)
    vert: Tensor  # (N,)
    residual: Tensor  # (N, 3) chromaticity - reference
    grad: Tensor  # (N, 3, 2) d chromaticity / d uv
    weight: Tensor  # (N,) Cauchy IRLS weight 1 / (1 + |r|^2 / s^2)


def update_anchor(ref: AnchorRef | None, verts: Tensor, views: Views, fragments: raster.Fragments, image: Tensor,
                  mask: Tensor, cfg: FitConfig) -> AnchorRef:
    """Give the vertices without a reference one from this frame: the mean chromaticity
    (blurred image (C, H, W, 3), bilinear) over the views in which the vertex of ``verts`` (V, 3) is
    visible (``fragments``, whole images) and lies inside the eroded garment ``mask`` (C, H, W).
    Vertices that already have a reference keep it; vertices seen nowhere stay without one.
    Only the new references' pixels are read (:func:`sample_blurred`)."""
    K, E = views.K.to(verts.dtype), views.world_to_cam.to(verts.dtype)
    uv, _ = raster.project_vertices(verts.detach(), K, E)
    soft = mask.double() if mask.is_floating_point() else mask.bool().double()
    soft = soft * image_finite(image, cfg.image_blur).double()  # no reference from non-finite colours
    vis = raster.visible_vertices(verts.detach(), K, E, fragments, cfg.visibility_depth_tol)
    vis &= pixel_ok(eroded(torch.where(torch.isfinite(soft), soft, torch.zeros_like(soft)), cfg.flow_margin_px), uv)
    seen_now = vis.any(0)
    new = seen_now if ref is None else seen_now & ~ref.seen
    if ref is not None and not bool(new.any()):
        return ref
    c, v = (vis & new[None]).nonzero(as_tuple=True)
    V = verts.shape[0]
    total = torch.zeros(V, 3, dtype=torch.float64, device=uv.device).index_add_(
        0, v, sample_blurred(chromaticity(image), c, uv[c, v], cfg.image_blur))
    mean = total / torch.zeros(V, dtype=torch.float64, device=uv.device).index_add_(
        0, v, torch.ones_like(v, dtype=torch.float64)).clamp_min(1)[:, None]
    if ref is None:
        return AnchorRef(torch.where(seen_now[:, None], mean, torch.zeros_like(mean)), seen_now)
    return AnchorRef(torch.where(new[:, None], mean, ref.chroma.to(mean.dtype)), ref.seen | new)


def texture_anchor(faces: Tensor, face_uv: Tensor, texture: Tensor, blur_texels: float,
                   num_vertices: int | None = None) -> AnchorRef:
    """L_anchor's references from a textured template instead of from the first frame a vertex is seen.

    faces (F, 3), face_uv (F, 3, 2) the template's UVs (OBJ convention, :func:`raster.sample_texture`);
    a vertex on a UV seam takes the UV of its first face. texture (Ht, Wt, 3) colours in [0, 1].
    Each vertex's reference (every vertex gets one: ``seen`` all True) is the chromaticity at its UV of the
    texture blurred by a Gaussian of ``blur_texels`` texels (what one image pixel, blurred like the images,
    covers: :func:`texture_blur_texels`). num_vertices: V (default: the largest index in ``faces`` + 1); every
    vertex must be in a face (studies/fit/fit_frame0.md).
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
    # the blurred texture at V points only (sample_blurred: the same values as blurring the whole
    # texture, then raster.sample_texture with its clamped border; blurring a whole 1024^2 texture costs seconds)
    Ht, Wt = texture.shape[:2]
    px = torch.stack([uv[:, 0] * Wt - 0.5, (1 - uv[:, 1]) * Ht - 0.5], -1)  # texel coordinates, centres at integers
    chroma = chromaticity(texture.double())[None]  # (1, Ht, Wt, 3)
    cam = torch.zeros(V, dtype=torch.int64, device=uv.device)
    step = 1024  # vertices per gather: (step, 2r + 2, 2r + 2, 3) texels at a time
    ref = torch.cat([sample_blurred(chroma, cam[i:i + step], px[i:i + step], blur_texels) for i in range(0, V, step)])
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


def cauchy_colour(cam: Tensor, vert: Tensor, samples: Tensor, reference: Tensor, scale: float
                   ) -> tuple[float, ColourData]:
    """L_anchor's form: samples (N, 9) of image_features at the (cam, vert) pairs
    (N,) against each vertex's reference (V, 3); the Cauchy loss sum s^2 log(1 + |r|^2 / s^2) and
    what the Gauss-Newton blocks need (residuals, colour gradients, IRLS weights)."""
    r = samples[:, :3] - reference.to(samples.dtype)[vert]
    s2 = scale ** 2
    e = (r * r).sum(-1)
    return (float((s2 * torch.log1p(e / s2)).sum()),
            ColourData(cam, vert, r, torch.stack([samples[:, 3:6], samples[:, 6:9]], -1), 1.0 / (1.0 + e / s2)))


def setup(pb: Problem, cues: FrameCues, given: AnchorRef | None) -> Colours | None:
    """On with a weight, images and references ``given`` (some vertex seen). Colours count inside the eroded
    garment mask, away from non-finite image pixels (the blur of image_features spreads them over ~3 sigma:
    they are grown by that much)."""
    cfg = pb.cfg
    if not (cfg.weights.anchor > 0 and cues.image is not None and given is not None and bool(given.seen.any())):
        return None
    feat = image_features(chromaticity(cues.image), cfg.image_blur)
    return Colours(given, feat, eroded(pb.coverage * image_finite(cues.image, cfg.image_blur).double(),
                                       cfg.flow_margin_px))


def value(pb: Problem, st: Colours, r: Rendered) -> tuple[float, ColourData]:
    """L_anchor at the render ``r``: each visible vertex's chromaticity against its reference."""
    views, cfg = pb.views, pb.cfg
    vis_col = raster.visible_vertices(r.verts, views.K, views.world_to_cam, r.fragments, cfg.visibility_depth_tol) \
        & pixel_ok(st.region, r.uv)  # vertices whose colour counts
    c, vv = (vis_col & st.ref.seen[None]).nonzero(as_tuple=True)
    val, anc = cauchy_colour(c, vv, sample(st.feat, r.uv)[c, vv], st.ref.chroma, cfg.anchor_scale)
    return val / pb.n_px, anc


def gauss_newton(pb: Problem, st: Colours, data: ColourData, lin: Linearisation, out: System) -> bool:
    """Add the IRLS blocks and gradient in place (the reference is fixed: exact)."""
    if not data.cam.numel():
        return False
    Jr = data.grad @ lin.Puv[data.cam, data.vert]  # (N, 3, 3)
    w = (pb.cfg.weights.anchor / pb.n_px) * data.weight
    out.blocks.index_add_(0, pb.rig.layout.diag[data.vert], w[:, None, None] * Jr.transpose(1, 2) @ Jr)
    out.gx.index_add_(0, data.vert, w[:, None] * torch.einsum("nij,ni->nj", Jr, data.residual))
    return True


def reference(pb: Problem, st: Colours, verts: Tensor, fragments: raster.Fragments) -> Tensor:
    """Differentiable L_anchor (visibility held fixed: ``fragments``)."""
    cfg = pb.cfg
    K, E = pb.views.K.to(verts.dtype), pb.views.world_to_cam.to(verts.dtype)
    uv, _ = raster.project_vertices(verts, K, E)
    with torch.no_grad():
        vis = raster.visible_vertices(verts.detach(), K, E, fragments, cfg.visibility_depth_tol)
        vis &= pixel_ok(st.region, uv.detach()) & st.ref.seen[None]
    r = (sample(st.feat[:, :3], uv) - st.ref.chroma.to(uv.dtype)[None])[vis]
    s2 = cfg.anchor_scale ** 2
    return (s2 * torch.log1p((r * r).sum(-1) / s2)).sum() / pb.n_px
