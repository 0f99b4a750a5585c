"""Synthetic scenes with full ground truth (DESIGN.md §5).

Pure functions: textures, lights, the studio background, multi-view rendering of a
set of posed meshes, and ground-truth forward optical flow. The stage that loops
over frames and writes the dataset is :mod:`anidress_core.stages.synth`.

Ground-truth flow (t-1 -> t) is exact, not estimated: every pixel of frame t-1 that
sees a surface point (face f, barycentrics b) is moved with that point to frame t,
``X_t = sum_i b_i V_t[f_i]``, and projected; the flow is the displacement of the
projection. The point is *visible* at t when its depth matches the z-buffer of
frame t where it lands; other pixels are marked occluded (``valid = 0``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from . import raster
from .camera import Cameras
from .geometry import vertex_normals

__all__ = [
    "Lights",
    "default_lights",
    "MeshLayer",
    "material_texture",
    "atlas_texture",
    "studio_background",
    "ViewRender",
    "render_views",
    "FlowGT",
    "forward_flow",
    "MATERIALS",
]

# Label values written in masks (DESIGN.md §3).
LABEL_BACKGROUND, LABEL_BODY, LABEL_GARMENT = 0, 1, 2


# --------------------------------------------------------------------------- textures


def _fbm(size: int, rng: np.random.Generator, octaves: int = 5, base: int = 4) -> np.ndarray:
    """Fractal value noise in [0, 1], (size, size): bicubic-upsampled random grids, halving amplitude."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = min(base * 2**o, size)
        grid = rng.random((cells, cells)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
    out /= total
    return np.clip((out - out.min()) / max(float(out.max() - out.min()), 1e-6), 0.0, 1.0)


def _uv_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    u = (np.arange(size, dtype=np.float32) + 0.5) / size
    return np.meshgrid(u, u, indexing="xy")


def material_texture(material: str, size: int, seed: int) -> np.ndarray:
    """A procedural fabric/skin texture (size, size, 3) float32 in [0, 1].

    Materials: ``plaid`` (woven check shirt), ``denim`` (twill trousers), ``skin``,
    ``leather`` (shoes), ``floral`` (printed fabric), ``plain`` (one-colour beige fabric with a
    faint weave, like the AniDress paper's Skirt-Beige: the weave and a faint dye unevenness
    change the brightness by a few percent and the chromaticity not at all, so a colour anchor
    sees nothing), ``floor`` (wooden planks), ``wall`` (painted backdrop). Each but ``plain``
    mixes large-scale structure with fine, non-repeating detail so optical flow and appearance
    are learnable; ``plain`` has only the fine weave and the faint unevenness.
    """
    rng = np.random.default_rng(seed)
    u, v = _uv_grid(size)
    n1 = _fbm(size, rng)
    n2 = _fbm(size, rng, octaves=6, base=16)
    if material == "plaid":
        base = np.array([0.55, 0.12, 0.12], np.float32)
        band_u = (np.sin(2 * np.pi * 6 * u) > 0.3).astype(np.float32)
        band_v = (np.sin(2 * np.pi * 6 * v) > 0.3).astype(np.float32)
        thin = ((np.sin(2 * np.pi * 24 * u) > 0.92) | (np.sin(2 * np.pi * 24 * v) > 0.92)).astype(np.float32)
        weave = 0.5 + 0.5 * np.sin(2 * np.pi * 160 * u) * np.sin(2 * np.pi * 160 * v)
        tex = base * (1 - 0.35 * band_u[..., None]) * (1 - 0.35 * band_v[..., None])
        tex = tex + thin[..., None] * np.array([0.35, 0.33, 0.2], np.float32)
        tex = tex * (0.85 + 0.1 * weave[..., None] + 0.1 * n2[..., None])
    elif material == "denim":
        base = np.array([0.14, 0.22, 0.42], np.float32)
        twill = 0.5 + 0.5 * np.sin(2 * np.pi * 140 * (u + v))
        tex = base * (0.75 + 0.2 * twill[..., None] + 0.3 * n2[..., None]) + 0.08 * n1[..., None]
    elif material == "skin":
        base = np.array([0.86, 0.64, 0.52], np.float32)
        tex = base * (0.9 + 0.08 * n1[..., None] + 0.04 * n2[..., None])
    elif material == "leather":
        base = np.array([0.22, 0.14, 0.09], np.float32)
        tex = base * (0.8 + 0.4 * n2[..., None])
    elif material == "floral":
        base = np.array([0.85, 0.8, 0.62], np.float32)
        # scattered blossoms: thresholded noise blobs in two colours, plus a fine print
        blobs_a = (_fbm(size, rng, octaves=3, base=24) > 0.62).astype(np.float32)
        blobs_b = (_fbm(size, rng, octaves=3, base=24) > 0.66).astype(np.float32)
        tex = base * (0.9 + 0.1 * n2[..., None])
        tex = tex * (1 - blobs_a[..., None]) + blobs_a[..., None] * np.array([0.75, 0.2, 0.35], np.float32)
        tex = tex * (1 - blobs_b[..., None]) + blobs_b[..., None] * np.array([0.2, 0.45, 0.25], np.float32)
    elif material == "plain":
        # one colour times a brightness pattern (the same factor on r, g, b: chromaticity constant):
        # a plain weave of ~100 threads per texture side (+-2.5 %) and a faint dye unevenness (+-2 %)
        base = np.array([0.74, 0.64, 0.50], np.float32)
        weave = np.sin(2 * np.pi * 96 * u) * np.sin(2 * np.pi * 96 * v)
        tex = base * (0.95 + 0.025 * weave + 0.04 * (n2 - 0.5))[..., None]
    elif material == "floor":
        plank = np.floor(v * 16)
        shade = 0.75 + 0.25 * ((plank * 0.618) % 1.0)
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (40 * u + 6 * n1))
        tex = np.array([0.55, 0.4, 0.26], np.float32) * (shade * (0.85 + 0.15 * grain))[..., None]
        gaps = (np.abs((v * 16) % 1.0 - 0.5) > 0.48).astype(np.float32)
        tex = tex * (1 - 0.5 * gaps[..., None])
    elif material == "wall":
        tex = np.array([0.62, 0.64, 0.66], np.float32) * (0.85 + 0.15 * n1[..., None] + 0.05 * n2[..., None])
    else:
        raise ValueError(f"unknown material {material!r}; known: {MATERIALS}")
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


MATERIALS = ("plaid", "denim", "skin", "leather", "floral", "plain", "floor", "wall")


def body_part_material(part_name: str) -> str:
    """Clothing of the tight-clothed mannequin: check shirt, jeans, shoes, bare skin."""
    name = part_name.lower()
    if "head" in name or "hand" in name or "neck" in name or "lower_arm" in name or "forearm" in name:
        return "skin"
    if "foot" in name or "toe" in name:
        return "leather"
    if "leg" in name or "thigh" in name or "shin" in name or "calf" in name:
        return "denim"
    return "plaid"


def atlas_texture(face_uv: np.ndarray, face_part: np.ndarray, part_materials: Sequence[str], size: int,
                  seed: int) -> np.ndarray:
    """Texture atlas (size, size, 3) for a mesh whose UV charts are labelled by part.

    face_uv: (F, 3, 2) in [0, 1] (OBJ convention, v up); face_part: (F,) part index;
    part_materials: material name per part index. Each chart is filled with its
    material; texels outside every chart take the nearest chart's material, so
    bilinear lookups at chart borders never pick up a foreign colour.
    """
    # 1. rasterise the part id of every texel (one fillPoly call per part, not per face)
    part_map = np.full((size, size), -1, np.int32)
    pix = np.empty_like(face_uv, dtype=np.float64)
    pix[..., 0] = face_uv[..., 0] * size - 0.5
    pix[..., 1] = (1.0 - face_uv[..., 1]) * size - 0.5  # v up -> image rows down
    shift = 4  # sub-pixel precision of cv2.fillPoly
    pts = np.round(pix * (1 << shift)).astype(np.int32)
    for p in np.unique(face_part):
        polys = list(pts[face_part == p])
        cv2.fillPoly(part_map, polys, int(p), lineType=cv2.LINE_8, shift=shift)
    # 2. nearest-chart fill of empty texels (distance transform labels)
    empty = (part_map < 0).astype(np.uint8)
    if empty.any() and not empty.all():
        _, labels = cv2.distanceTransformWithLabels(empty, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        src = np.zeros(int(labels.max()) + 1, np.int32)
        ys, xs = np.nonzero(empty == 0)
        src[labels[ys, xs]] = part_map[ys, xs]
        part_map = np.where(part_map < 0, src[labels], part_map)
    part_map = np.clip(part_map, 0, None)
    # 3. compose materials
    names = sorted(set(part_materials))
    mats = {m: material_texture(m, size, seed + 101 * i) for i, m in enumerate(names)}
    mat_of_part = np.array([names.index(m) for m in part_materials])
    stack = np.stack([mats[m] for m in names])  # (M, S, S, 3)
    midx = mat_of_part[part_map]
    rows, cols = np.indices((size, size))
    return stack[midx, rows, cols]


# --------------------------------------------------------------------------- lights


class Lights(NamedTuple):
    """Directional lights in world space: directions point towards the lights."""

    directions: Tensor  # (L, 3) unit
    colors: Tensor  # (L, 3)
    ambient: Tensor  # (3,)


def default_lights(up: Sequence[float] = (0.0, 0.0, 1.0)) -> Lights:
    """Three-point studio lighting (key, fill, rim) for a z-up world."""
    if tuple(up) != (0.0, 0.0, 1.0):
        raise ValueError("default_lights is defined for a z-up world")
    d = torch.tensor([[0.5, -0.6, 0.8], [-0.7, -0.3, 0.4], [0.1, 0.9, 0.5]])
    d = d / d.norm(dim=-1, keepdim=True)
    c = torch.tensor([[0.75, 0.72, 0.68], [0.3, 0.32, 0.36], [0.25, 0.25, 0.25]])
    return Lights(d, c, torch.tensor([0.28, 0.28, 0.3]))


# --------------------------------------------------------------------------- meshes and rendering


@dataclass(frozen=True)
class MeshLayer:
    """One textured mesh of a scene at one instant.

    verts: (V, 3) world positions; faces: (F, 3); face_uv: (F, 3, 2); texture:
    (S, S, 3) float in [0, 1]; label: mask label of its pixels (1 body, 2 garment).
    """

    verts: Tensor
    faces: Tensor
    face_uv: Tensor
    texture: Tensor
    label: int


class ViewRender(NamedTuple):
    rgb: Tensor  # (C, H, W, 3) in [0, 1], background where labels == 0
    labels: Tensor  # (C, H, W) uint8: 0 background, 1 body, 2 garment
    depth: Tensor  # (C, H, W) camera z, +inf on background
    normals_cam: Tensor  # (C, H, W, 3) camera-space unit normals, 0 on background
    fragments: raster.Fragments  # of the merged mesh
    verts: Tensor  # (V, 3) merged vertices (world)
    faces: Tensor  # (F, 3) merged faces


def _merge(layers: Sequence[MeshLayer]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Concatenate layers -> verts (V,3), faces (F,3), face_uv (F,3,2), face_layer (F,)."""
    verts, faces, uvs, which = [], [], [], []
    offset = 0
    for i, layer in enumerate(layers):
        verts.append(layer.verts)
        faces.append(layer.faces + offset)
        uvs.append(layer.face_uv)
        which.append(torch.full((layer.faces.shape[0],), i, dtype=torch.long))
        offset += layer.verts.shape[0]
    return torch.cat(verts), torch.cat(faces), torch.cat(uvs), torch.cat(which)


def _shade(verts: Tensor, faces: Tensor, face_uv: Tensor, face_layer: Tensor, layers: Sequence[MeshLayer],
           cams: Cameras, lights: Lights, colour: bool = True):
    """Rasterise + shade merged meshes -> (rgb, hit, layer_of_pixel, n_cam, fragments).

    Shapes (C, H, W[, 3]). Every per-pixel quantity is computed on the covered pixels only
    (the subject fills a small part of each image) and scattered into zero images.
    colour=False: no texture lookup or shading (``rgb`` is None), for a pass that only needs
    the labels, normals and fragments.
    """
    H, W = cams.height, cams.width
    w2c = cams.world_to_cam.to(verts.dtype)
    K = cams.K.to(verts.dtype)
    C = K.shape[0]
    frags = raster.rasterize(verts, faces, K, w2c, H, W)
    hit = frags.face_id >= 0
    layer_of_pixel = face_layer[frags.face_id.clamp_min(0)]  # (C, H, W)
    pix = hit.reshape(-1).nonzero().squeeze(1)  # (N,) flat indices of the covered pixels
    f = frags.face_id.reshape(-1)[pix]  # (N,)
    b = frags.bary.reshape(-1, 3)[pix].to(verts.dtype)  # (N, 3)
    cam = pix // (H * W)
    rem = pix % (H * W)

    def lerp(a: Tensor) -> Tensor:  # a: (N, 3, D) corner values -> (N, D), as raster.interpolate
        return b[:, 0:1] * a[:, 0] + b[:, 1:2] * a[:, 1] + b[:, 2:3] * a[:, 2]

    def dense(v: Tensor) -> Tensor:  # (N, D) -> (C, H, W, D), 0 where nothing was hit
        return v.new_zeros(C * H * W, v.shape[-1]).index_put((pix,), v).view(C, H, W, -1)

    # smooth world normals, flipped to face the camera (cloth is seen from both sides)
    vn = vertex_normals(verts, faces)
    n_world = lerp(vn[faces[f]])  # (N, 3)
    n_world = n_world / n_world.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    R = w2c[cam, :3, :3]  # (N, 3, 3)
    n_cam = torch.einsum("nij,nj->ni", R, n_world)
    # a camera-space normal faces the camera when it points against the viewing ray (the
    # pixel centre's direction, unnormalised: only the sign of the dot product matters)
    Kn = K[cam]
    rays = torch.stack([((rem % W).to(K.dtype) - Kn[:, 0, 2]) / Kn[:, 0, 0],
                        ((rem // W).to(K.dtype) - Kn[:, 1, 2]) / Kn[:, 1, 1], torch.ones_like(Kn[:, 0, 0])], -1)
    flip = (n_cam * rays).sum(-1, keepdim=True) > 0
    n_cam = torch.where(flip, -n_cam, n_cam)
    rgb = None
    if colour:
        # albedo: each layer's texture where that layer won the z-test
        uv = lerp(face_uv[f])  # (N, 2)
        lop = layer_of_pixel.reshape(-1)[pix]
        albedo = torch.zeros(pix.shape[0], 3, dtype=verts.dtype)
        for i, layer in enumerate(layers):  # a handful of layers, not a per-pixel loop
            sel = lop == i
            if sel.any():
                albedo[sel] = raster.sample_texture(layer.texture.to(verts.dtype), uv[sel])
        n_w = torch.einsum("nji,nj->ni", R, n_cam)  # back to world with the flip applied
        lit = raster.shade_lambert(albedo[None, None], n_w[None, None], lights.directions.to(verts.dtype),
                                   lights.colors.to(verts.dtype), lights.ambient.to(verts.dtype))[0, 0]
        rgb = dense(lit.clamp(0, 1))
    return rgb, hit, layer_of_pixel, dense(n_cam), frags


def render_views(layers: Sequence[MeshLayer], cams: Cameras, lights: Lights,
                 background: Tensor | None = None, supersample: int = 1) -> ViewRender:
    """Render textured, Lambertian-shaded meshes into every camera (z-buffered together).

    background: optional (C, H, W, 3) plates composited behind the meshes.
    supersample: the colour image is rendered at ``supersample`` times the resolution
    and box-filtered down, as a camera integrates light over a pixel (anti-aliased
    silhouettes, no texture shimmer). Labels, depth, normals and fragments are those
    of the pixel centres.
    """
    verts, faces, face_uv, face_layer = _merge(layers)
    ss = supersample > 1
    rgb, hit, layer_of_pixel, n_cam, frags = _shade(verts, faces, face_uv, face_layer, layers, cams, lights,
                                                    colour=not ss)  # supersampled: colour from the fine pass
    if background is None:
        background = torch.zeros(*hit.shape, 3, dtype=verts.dtype)
    background = background.to(verts.dtype)
    if ss:
        hi_rgb, hi_hit = _shade(verts, faces, face_uv, face_layer, layers, cams.scaled(supersample), lights)[:2]
        pool = lambda x: F.avg_pool2d(x.permute(0, 3, 1, 2), supersample).permute(0, 2, 3, 1)  # noqa: E731
        cover = pool(hi_hit[..., None].to(verts.dtype))
        rgb = pool(hi_rgb * hi_hit[..., None]) + (1 - cover) * background
    else:
        rgb = torch.where(hit[..., None], rgb, background)
    layer_labels = torch.tensor([layer.label for layer in layers], dtype=torch.uint8)
    labels = torch.where(hit, layer_labels[layer_of_pixel], torch.zeros(hit.shape, dtype=torch.uint8))
    n_cam = torch.where(hit[..., None], n_cam, torch.zeros_like(n_cam))
    return ViewRender(rgb.clamp(0, 1), labels, frags.depth, n_cam, frags, verts, faces)


def raster_view_dirs(K: Tensor, height: int, width: int) -> Tensor:
    """Unit camera-space viewing directions of every pixel centre, (C, H, W, 3)."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=K.dtype), torch.arange(width, dtype=K.dtype), indexing="ij")
    x = (xs[None] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (ys[None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    d = torch.stack([x, y, torch.ones_like(x)], -1)
    return d / d.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------- background


def studio_background(cams: Cameras, lights: Lights, size: int = 512, seed: int = 0,
                      floor_radius: float | None = None, wall_radius: float | None = None) -> Tensor:
    """Static background plates (C, H, W, 3): a wooden floor disk and a cylindrical backdrop.

    The floor disk stays inside the camera ring (so no face crosses a camera's near
    plane) and the backdrop wall stands outside it. Plates are what a capture's
    background frames would be (used by background-subtraction mask estimation).
    """
    ring = float(cams.centers[:, :2].norm(dim=-1).min())
    floor_radius = floor_radius or 0.85 * ring
    wall_radius = wall_radius or 2.0 * ring
    n = 96
    ang = torch.linspace(0, 2 * np.pi, n + 1)[:-1]
    # floor: triangle fan around the centre, planar UVs
    rim = torch.stack([floor_radius * ang.cos(), floor_radius * ang.sin(), torch.zeros(n)], -1)
    fv = torch.cat([torch.zeros(1, 3), rim])
    i = torch.arange(n)
    ff = torch.stack([torch.zeros(n, dtype=torch.long), 1 + i, 1 + (i + 1) % n], -1)
    fuv = (fv[:, :2] / (2 * floor_radius) + 0.5)[ff]
    # wall: open cylinder, 4 m tall, u around, v up; duplicated seam column for clean UVs
    rows = 8
    angw = torch.linspace(0, 2 * np.pi, n + 1)
    z = torch.linspace(0.0, 4.0, rows + 1)
    A, Z = torch.meshgrid(angw, z, indexing="ij")
    wv = torch.stack([wall_radius * A.cos(), wall_radius * A.sin(), Z], -1).reshape(-1, 3)
    wuv_v = torch.stack([A / (2 * np.pi), Z / 4.0], -1).reshape(-1, 2)
    idx = torch.arange((n + 1) * (rows + 1)).reshape(n + 1, rows + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    wf = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    wuv = wuv_v[wf]
    floor = MeshLayer(fv, ff, fuv, torch.from_numpy(material_texture("floor", size, seed + 7)), 0)
    wall = MeshLayer(wv, wf, wuv, torch.from_numpy(material_texture("wall", size, seed + 11)), 0)
    out = render_views([floor, wall], cams, lights)
    grey = torch.tensor([0.35, 0.35, 0.37])
    return torch.where((out.fragments.face_id >= 0)[..., None], out.rgb, grey)


# --------------------------------------------------------------------------- ground-truth flow


class FlowGT(NamedTuple):
    flow: Tensor  # (C, H, W, 2) pixels (dx, dy) from frame t-1 to t, defined on frame t-1's pixels
    valid: Tensor  # (C, H, W) bool: the point is visible in frame t (not occluded, inside the image)


def forward_flow(prev: raster.Fragments, verts_next: Tensor, faces: Tensor, cams: Cameras,
                 depth_next: Tensor, depth_tol: float = 0.01) -> FlowGT:
    """Exact forward optical flow t-1 -> t of a deforming mesh with a static background.

    prev: fragments of frame t-1; verts_next: (V, 3) the same mesh at frame t;
    depth_next: (C, H, W) z-buffer of frame t (+inf on background). Background
    pixels have zero flow and are valid where frame t still shows background there.
    depth_tol: relative depth tolerance of the visibility test.
    """
    C, H, W = prev.face_id.shape
    hit = prev.face_id >= 0
    fid = prev.face_id.clamp_min(0)
    # 1. surface point of every pixel, carried to frame t: X_t = sum_i b_i V_t[f_i]
    tri = verts_next[faces[fid]]  # (C, H, W, 3 corners, 3)
    X = (prev.bary[..., :, None].to(tri.dtype) * tri).sum(-2)  # (C, H, W, 3)
    # 2. project into each camera
    w2c = cams.world_to_cam.to(X.dtype)
    Xc = torch.einsum("cij,chwj->chwi", w2c[:, :3, :3], X) + w2c[:, None, None, :3, 3]
    z = Xc[..., 2]
    K = cams.K.to(X.dtype)
    u = K[:, 0, 0, None, None] * Xc[..., 0] / z.clamp_min(1e-9) + K[:, 0, 2, None, None]
    v = K[:, 1, 1, None, None] * Xc[..., 1] / z.clamp_min(1e-9) + K[:, 1, 2, None, None]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=X.dtype), torch.arange(W, dtype=X.dtype), indexing="ij")
    flow = torch.stack([u - xs, v - ys], -1)
    # 3. visibility at t: the carried point is (nearly) the first surface along its new pixel's ray
    ui, vi = u.round().long(), v.round().long()
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H) & (z > 0)
    cidx = torch.arange(C)[:, None, None].expand(C, H, W)
    d_at = depth_next[cidx, vi.clamp(0, H - 1), ui.clamp(0, W - 1)]
    visible = inside & ((z - d_at).abs() <= depth_tol * z.abs().clamp_min(1e-6))
    flow = torch.where(hit[..., None], flow, torch.zeros_like(flow))
    valid = torch.where(hit, visible, ~torch.isfinite(depth_next))
    return FlowGT(flow, valid)


# --------------------------------------------------------------------------- "predicted" normals


def _gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur of (N, Ch, H, W) with reflect padding."""
    r = max(1, int(round(3 * sigma)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype) / sigma) ** 2)
    k = k / k.sum()
    ch = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1).expand(ch, 1, 1, -1), groups=ch)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1).expand(ch, 1, -1, 1), groups=ch)


def degrade_normals(normals: Tensor, mask: Tensor, blur_px: float, noise_std: float,
                    generator: torch.Generator | None = None) -> Tensor:
    """Turn true normal maps into what a normal-prediction network gives (DESIGN.md §5).

    normals: (C, H, W, 3) unit camera-space normals, 0 off the subject; mask:
    (C, H, W) bool subject pixels. Fine wrinkles are lost (Gaussian blur of
    ``blur_px`` pixels, normalised inside the mask so the background does not
    bleed in), then per-pixel Gaussian noise of ``noise_std`` is added and the
    result renormalised. Returns (C, H, W, 3), 0 outside the mask.
    """
    n = normals.permute(0, 3, 1, 2)
    m = mask[:, None].to(n.dtype)
    if blur_px > 0:
        n = _gaussian_blur(n * m, blur_px) / _gaussian_blur(m, blur_px).clamp_min(1e-6)
    if noise_std > 0:
        n = n + noise_std * torch.randn(n.shape, generator=generator, dtype=n.dtype)
    n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-8)
    return (n * m).permute(0, 2, 3, 1)
