"""Triangle rasteriser, differentiable interpolation, texturing and Lambert shading.

One module (over 800 lines): the forward pass, its derivatives and the renders share the Fragments layout.

One renderer serves the whole pipeline: synthetic data (:func:`render_mesh`), garment
fitting (silhouettes and camera-space normals with gradients to the vertices, through
:func:`barycentrics`, :func:`interpolate` and :func:`antialias`) and radiance-field
sampling (depth and face ids of the posed meshes, :func:`rasterize`).

Conventions
-----------
* Cameras are OpenCV pinholes without distortion: ``X_cam = world_to_cam @ X_world``
  with ``world_to_cam`` (C, 4, 4), ``x_pix ~ K @ X_cam`` with ``K`` (C, 3, 3), last row
  ``[0, 0, 1]`` and ``fx, fy > 0``; x right, y down, z forward. ``(3, 3)`` / ``(4, 4)``
  are accepted for a single camera.
* Pixel (row i, col j) is sampled at its centre, which lies at the INTEGER pixel
  coordinate ``u = j, v = i`` (so the image covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``).
  Images are ``(C, H, W, ...)``, row-major.
* A face ``(a, b, c)`` is front-facing when ``(b - a) x (c - a)`` points towards the
  camera (counter-clockwise seen from outside: the trimesh / OpenGL convention).
* ``Fragments.bary`` are perspective-correct barycentrics of the pixel centre in the
  face ``face_id``: the 3D hit point is ``sum_k bary[k] * X[face[k]]``. ``depth`` is
  camera-space z (metres), not the distance along the ray.

Method
------
:func:`rasterize` is a half-space (edge-function) rasteriser [Pineda 1988, "A parallel
algorithm for polygon rasterization"; Olano & Greer 1997] with the discrete/differentiable
split of nvdiffrast [Laine et al. 2020, "Modular Primitives for High-Performance
Differentiable Rendering"]. Steps 1, 2, 4 and 5 below run either as one Warp kernel, a
thread per (camera, face) walking its pixel box (``backend='warp'``, the default,
:mod:`anidress_core.raster_kernels`), or as the batched tensor code of step 3
(``backend='torch'``, the reference); both give the same face ids:

1. Vertices are projected and snapped to a 1/256-pixel fixed-point grid, as GPU
   rasterisers do. Edge functions of snapped vertices at pixel centres are then
   integers below 2**53, which float64 evaluates *exactly* (for |u|, |v| < 2**16 px).
2. Faces with a vertex in front of the near plane (z < near; no clipping), zero area,
   non-finite coordinates, an empty pixel bounding box or (optionally) facing away are
   dropped.
3. Each face's pixel bounding box gets a tile of tx x ty pixels, tx, ty in
   1, 2, 3, 4, 6, ..., 48, 64 (bigger faces are split into several tiles). Faces with
   the same tile shape are evaluated together as ONE matrix product:
   ``[ox, oy, 1] (T, 3) @ coefficients (3, 4 P)`` gives the three edge functions and
   1/z (affine in screen space) of P faces at the T pixels of their tiles; memory is
   bounded by evaluating at most ``pixels_per_chunk`` tile pixels at a time.
4. Fill rule: each edge has a canonical direction (from its lexicographically smaller
   end point), and a pixel centre exactly on an edge belongs to the face on the
   edge's left. This is a symbolic perturbation of the sample point, so with the
   exact arithmetic of step 1 every pixel centre inside the projection of a closed
   surface (or of a planar triangulation) is covered exactly once: no holes, no double
   coverage, also through shared vertices (the role of the top-left rule of D3D/GL).
5. Depth test: covered (pixel, face) pairs are packed into one int64 key, 1/z
   quantised on [0, 1/near] in the high bits (smaller = nearer) and the face id in
   the low bits, and reduced per pixel with ``scatter_reduce(..., "amin")``: the
   nearest face wins, ties go to the lower face id, whatever the evaluation order.
6. Barycentrics and depth of the winners are recomputed from the unsnapped vertices
   by :func:`barycentrics` (the same function that carries gradients); at pixels
   within 1/512 px of an edge they can be slightly negative (the snapping).

Speed on the project's 2-core CPU: see ``benchmarks/raster.md``.

Rasterisation is discrete (no gradients). Interpolation is differentiable:
``interpolate(attr, faces, frags, barycentrics(verts, ...))`` gives gradients with
respect to the vertex positions and attributes inside the faces; :func:`antialias`
adds the gradients of silhouette edges (nvdiffrast's analytic antialiasing).
Everything runs on CPU or CUDA (tested on CPU), for float32 or float64 input; the exact
edge tests always run in float64.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .geometry import transform_points, vertex_normals

__all__ = [
    "Fragments",
    "Render",
    "project_vertices",
    "rasterize",
    "barycentrics",
    "interpolate",
    "sample_texture",
    "shade_lambert",
    "render_mesh",
    "face_adjacency",
    "antialias",
    "SilhouetteCrossings",
    "silhouette_crossings",
    "pair_crossings",
    "mesh_edges",
    "crossing_fraction",
    "occlude",
    "silhouette",
    "face_normals_cam",
    "render_face_normals",
    "visible_vertices",
]

_SUBPIXEL = 256.0  # fixed-point grid of snapped vertex coordinates (8 bits, like GPUs)
_LOG2_TILE_MAX = 6  # tiles of up to 64 x 64 pixels
_TILE_MAX = 1 << _LOG2_TILE_MAX
_KEY_BG = torch.iinfo(torch.int64).max
_COORD_CLAMP = 2.0**40  # subpixels; keeps far-off-screen vertices finite (exact below 2**24)


class Fragments(NamedTuple):
    """Result of :func:`rasterize`.

    face_id: (C, H, W) int64, index into ``faces`` of the visible face, -1 = background.
    bary: (C, H, W, 3) perspective-correct barycentrics of the pixel centre in that face
        (0 on background); None from ``rasterize(..., with_bary=False)``.
    depth: (C, H, W) camera-space z of the visible surface (+inf on background).
    """

    face_id: Tensor
    bary: Tensor
    depth: Tensor


class Render(NamedTuple):
    """Result of :func:`render_mesh`.

    rgb: (C, H, W, 3) shaded colour in [0, 1], ``background`` outside the mask.
    mask: (C, H, W) bool, pixel covered by the mesh.
    depth: (C, H, W) camera-space z, +inf on background.
    normals_cam: (C, H, W, 3) unit camera-space shading normals (interpolated smooth
        vertex normals, flipped on faces seen from behind so they face the camera);
        0 on background.
    fragments: the :class:`Fragments` the image was made from.
    """

    rgb: Tensor
    mask: Tensor
    depth: Tensor
    normals_cam: Tensor
    fragments: Fragments


# --------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------


def _check_cameras(name: str, K: Tensor, world_to_cam: Tensor, verts: Tensor | None = None):
    """Validate and broadcast cameras (and optionally vertices) to a common C.

    Returns K (C, 3, 3), world_to_cam (C, 4, 4), verts (V, 3) or (C, V, 3) unchanged.
    """
    if K.ndim not in (2, 3) or K.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: K must be (C, 3, 3) or (3, 3), got {tuple(K.shape)}")
    if world_to_cam.ndim not in (2, 3) or world_to_cam.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: world_to_cam must be (C, 4, 4) or (4, 4), got {tuple(world_to_cam.shape)}")
    if verts is not None and (verts.ndim not in (2, 3) or verts.shape[-1] != 3):
        raise ValueError(f"{name}: verts must be (V, 3) or (C, V, 3), got {tuple(verts.shape)}")
    sizes = {K.shape[0] if K.ndim == 3 else 1, world_to_cam.shape[0] if world_to_cam.ndim == 3 else 1}
    if verts is not None and verts.ndim == 3:
        sizes.add(verts.shape[0])
    sizes.discard(1)
    if len(sizes) > 1:
        raise ValueError(
            f"{name}: camera counts disagree: K {tuple(K.shape)}, world_to_cam "
            f"{tuple(world_to_cam.shape)}" + ("" if verts is None else f", verts {tuple(verts.shape)}")
        )
    C = sizes.pop() if sizes else 1
    K = K.reshape(-1, 3, 3).expand(C, 3, 3)
    world_to_cam = world_to_cam.reshape(-1, 4, 4).expand(C, 4, 4)
    if verts is not None and verts.ndim == 3 and verts.shape[0] != C:
        verts = verts.expand(C, -1, -1)
    return K, world_to_cam, verts


def _check_faces(name: str, faces: Tensor) -> Tensor:
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name}: faces must be (F, 3), got {tuple(faces.shape)}")
    if faces.is_floating_point() or faces.is_complex():
        raise ValueError(f"{name}: faces must be an integer tensor, got {faces.dtype}")
    return faces.long()


def _check_fragments(name: str, fragments: Fragments) -> tuple[int, int, int]:
    fid = fragments.face_id
    if fid.ndim != 3:
        raise ValueError(f"{name}: fragments.face_id must be (C, H, W), got {tuple(fid.shape)}")
    return tuple(fid.shape)  # type: ignore[return-value]


# --------------------------------------------------------------------------------------
# projection and barycentrics (differentiable)
# --------------------------------------------------------------------------------------


def project_vertices(verts: Tensor, K: Tensor, world_to_cam: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole projection. verts (V, 3) or (C, V, 3) world -> uv (C, V, 2) pixels, z (C, V).

    ``uv = (K @ X_cam)[:2] / z`` with ``X_cam = world_to_cam @ X_world``; meaningful
    for z > 0 only (z = 0 gives inf). Differentiable.
    """
    K, world_to_cam, verts = _check_cameras("project_vertices", K, world_to_cam, verts)
    Xc = transform_points(world_to_cam.to(verts.dtype), verts)  # (C, V, 3)
    z = Xc[..., 2]
    # p[c, v, i] = sum_j K[c, i, j] Xc[c, v, j]  for the two first rows of K
    p = torch.einsum("cij,cvj->cvi", K[:, :2, :].to(verts.dtype), Xc)
    return p / z[..., None], z


def _bary_depth(u: Tensor, v: Tensor, z: Tensor, pu: Tensor, pv: Tensor) -> tuple[Tensor, Tensor]:
    """Perspective-correct barycentrics of pixel centres in projected triangles.

    u, v, z: (3, N) projected corners (one row per corner) and their camera z; pu, pv:
    (N,) pixel centres. Returns bary (3, N) and depth (N,). With the screen-space edge
    functions w_k = (p_{k+2} - p_{k+1}) x (p - p_{k+1}) (nvdiffrast, sum_k w_k = twice
    the area): b_k = (w_k / z_k) / sum_j (w_j / z_j) and z = sum_k w_k / sum_j (w_j / z_j)
    (1/z is affine in screen space). Degenerate triangles (sum w at the rounding level
    of its terms) give bary 0 and depth inf, without NaN, also in the gradient.
    """
    u1, v1 = u[[1, 2, 0]], v[[1, 2, 0]]
    t1 = (u[[2, 0, 1]] - u1) * (pv - v1)
    t2 = (v[[2, 0, 1]] - v1) * (pu - u1)
    w = t1 - t2  # (3, N)
    wsum = w.sum(0)
    # rounding error of wsum is a few ulps of the terms it is made of
    ok = wsum.abs() > 64 * torch.finfo(w.dtype).eps * (t1.abs() + t2.abs()).sum(0).detach()
    q = w / torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    s = q.sum(0)
    ok &= (s != 0) & torch.isfinite(s)
    s_safe = torch.where(ok, s, torch.ones_like(s))
    bary = torch.where(ok, q / s_safe, torch.zeros_like(q))
    depth = torch.where(ok, wsum / s_safe, torch.full_like(s, float("inf")))
    return bary, depth


def _foreground(fid: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Flat indices of covered pixels of face_id (C, H, W): pix, cam, row, col, face (N,)."""
    C, H, W = fid.shape
    flat = fid.reshape(-1)
    pix = (flat >= 0).nonzero().squeeze(1)
    f = flat[pix]
    cam = pix // (H * W)
    rem = pix - cam * (H * W)
    row = rem // W
    col = rem - row * W
    return pix, cam, row, col, f


def _bary_from_projection(uv: Tensor, z: Tensor, faces: Tensor, fid: Tensor) -> tuple[Tensor, Tensor]:
    """Barycentrics (C, H, W, 3) and depth (C, H, W) of the faces fid (C, H, W) given
    projected vertices uv (C, V, 2), z (C, V)."""
    C, H, W = fid.shape
    V = uv.shape[1]
    pix, cam, row, col, f = _foreground(fid)
    idx = faces[f].t() + cam * V  # (3, N) rows of the flattened (C V) vertex arrays
    u = uv[..., 0].reshape(-1)[idx]
    v = uv[..., 1].reshape(-1)[idx]
    zc = z.reshape(-1)[idx]
    b, d = _bary_depth(u, v, zc, col.to(uv.dtype), row.to(uv.dtype))
    bary = uv.new_zeros(C * H * W, 3).index_put((pix,), b.t())
    depth = z.new_full((C * H * W,), float("inf")).index_put((pix,), d)
    return bary.view(C, H, W, 3), depth.view(C, H, W)


def barycentrics(verts: Tensor, faces: Tensor, K: Tensor, world_to_cam: Tensor, fragments: Fragments) -> Tensor:
    """Perspective-correct barycentrics (C, H, W, 3) of the pixel centres in the faces of
    ``fragments.face_id``, as a differentiable function of ``verts`` (V, 3) or (C, V, 3).

    The visibility (which face a pixel sees) is taken from ``fragments`` and held fixed;
    the barycentrics move with the vertices (nvdiffrast's split). Background gives 0.
    Equals ``fragments.bary`` when ``fragments`` came from ``rasterize`` on the same input.
    """
    faces = _check_faces("barycentrics", faces)
    _check_fragments("barycentrics", fragments)
    uv, z = project_vertices(verts, K, world_to_cam)
    if uv.shape[0] != fragments.face_id.shape[0]:
        raise ValueError(
            f"barycentrics: {uv.shape[0]} cameras but fragments.face_id is {tuple(fragments.face_id.shape)}"
        )
    return _bary_from_projection(uv, z, faces, fragments.face_id)[0]


# --------------------------------------------------------------------------------------
# rasterisation (discrete)
# --------------------------------------------------------------------------------------


# Tile sizes per axis: pieces of n pixels use the smallest size >= n (waste <= 1.5x per axis).
_TILE_SIZES = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
_NCLS = len(_TILE_SIZES)
_MIN_GROUP_WORK = 1 << 13  # tile pixels below which a group is merged into a bigger tile shape


def _tile_classes() -> list[int]:
    """lut[n] = index of the smallest tile size >= n, for n in 0..TILE_MAX."""
    return [next(i for i, s in enumerate(_TILE_SIZES) if s >= max(n, 1)) for n in range(_TILE_MAX + 1)]


def _merge_groups(counts: list[int]) -> list[int]:
    """Map every (cx, cy) tile class to the class its pieces are evaluated with.

    Groups with little work (count * tile area < _MIN_GROUP_WORK) move up to the next
    bigger tile along their shorter side, so a frame runs a handful of matrix products
    rather than dozens of tiny ones. counts: (NCLS * NCLS) pieces per class.
    """
    counts = list(counts)
    target = list(range(_NCLS * _NCLS))
    order = sorted(range(_NCLS * _NCLS), key=lambda b: _TILE_SIZES[b // _NCLS] * _TILE_SIZES[b % _NCLS])
    for b in order:
        n = counts[b]
        cx, cy = divmod(b, _NCLS)
        if n == 0 or n * _TILE_SIZES[cx] * _TILE_SIZES[cy] >= _MIN_GROUP_WORK or (cx, cy) == (_NCLS - 1, _NCLS - 1):
            continue
        if (_TILE_SIZES[cx] <= _TILE_SIZES[cy] and cx < _NCLS - 1) or cy == _NCLS - 1:
            nb = (cx + 1) * _NCLS + cy
        else:
            nb = cx * _NCLS + cy + 1
        counts[nb] += n
        counts[b] = 0
        target[b] = nb
    for b in range(len(target)):  # follow chains b -> nb -> ...
        while target[target[b]] != target[b]:
            target[b] = target[target[b]]
    return target


def _key_layout(num_faces: int, near: float) -> tuple[int, float, float]:
    """The depth key's layout, shared by both backends and the decoder in :func:`rasterize`:
    ``key = (q << fbits) | face`` with fbits = bit length of F - 1 (at least 1) and
    q = (1/near - 1/z) * zscale in [0, qmax], qmax = 2**(62 - fbits), zscale = qmax * near."""
    fbits = max(1, (num_faces - 1).bit_length())
    qmax = float(2 ** (62 - fbits))
    return fbits, qmax * near, qmax


def _snap(uv: Tensor, z: Tensor, near: float) -> tuple[Tensor, Tensor]:
    """Vertices snapped to the 1/256-pixel grid (C, V, 2) float64 (integers, clamped) and
    (C V,) bool: finite and in front of the near plane."""
    S = torch.round(uv.to(torch.float64) * _SUBPIXEL).clamp_(-_COORD_CLAMP, _COORD_CLAMP)
    return S, (torch.isfinite(uv).all(-1) & (z >= near)).reshape(-1)


def _raster_keys_warp(
    uv: Tensor,
    z: Tensor,
    faces: Tensor,
    fx_fy_sign: Tensor,
    height: int,
    width: int,
    near: float,
    cull_backfaces: bool,
) -> Tensor:
    """:func:`_raster_keys_torch`'s keys (C, H, W) int64 from one Warp kernel
    (:mod:`anidress_core.raster_kernels`): one thread per (camera, face) over its pixel box."""
    import warp as wp

    from . import raster_kernels

    C, V = z.shape
    F = faces.shape[0]
    dev = uv.device
    H, W = height, width
    keys = torch.full((C * H * W,), _KEY_BG, dtype=torch.int64, device=dev)
    if F == 0 or H == 0 or W == 0 or C == 0:
        return keys.view(C, H, W)
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"rasterize: the warp backend runs on cpu or cuda, not {dev}; pass backend='torch'")
    S, vok = _snap(uv, z, near)
    fbits, zscale, qmax = _key_layout(F, near)
    wp.init()
    wdev = "cpu" if dev.type == "cpu" else str(dev)
    args = [wp.from_torch(S[..., 0].reshape(-1).contiguous()), wp.from_torch(S[..., 1].reshape(-1).contiguous()),
            wp.from_torch(z.to(torch.float64).reshape(-1).contiguous()), wp.from_torch(vok.to(torch.int32)),
            wp.from_torch(faces.to(device=dev, dtype=torch.int32).contiguous()),
            wp.from_torch(fx_fy_sign.to(device=dev, dtype=torch.float64).contiguous()),
            V, H, W, int(cull_backfaces), fbits, zscale, qmax,
            wp.from_torch(keys)]
    stream = wp.stream_from_torch(dev) if dev.type == "cuda" else None
    wp.launch(raster_kernels.raster_keys, C * F, inputs=args, device=wdev, stream=stream)
    return keys.view(C, H, W)


def _raster_keys_torch(
    uv: Tensor,
    z: Tensor,
    faces: Tensor,
    fx_fy_sign: Tensor,
    height: int,
    width: int,
    near: float,
    cull_backfaces: bool,
    faces_per_chunk: int,
    pixels_per_chunk: int,
) -> Tensor:
    """Depth-test keys (C, H, W) int64 of the nearest face per pixel (_KEY_BG if none).

    uv (C, V, 2), z (C, V) projected vertices; fx_fy_sign (C,) sign of fx * fy.
    The key is ``(quantised depth << fbits) | face``, fbits = bit length of F - 1.
    """
    C, V = z.shape
    F = faces.shape[0]
    dev = uv.device
    f64 = torch.float64
    H, W = height, width
    if F == 0 or H == 0 or W == 0 or C == 0:
        return torch.full((C, H, W), _KEY_BG, dtype=torch.int64, device=dev)

    # 1. snap to the 1/256 pixel grid (integers held in float64); corner planes (3, C F)
    S, vok = _snap(uv, z, near)
    Sx, Sy = S[..., 0].reshape(-1), S[..., 1].reshape(-1)  # (C V,)
    corner = (faces.t()[:, None, :] + (torch.arange(C, device=dev) * V)[None, :, None]).reshape(3, C * F)
    X, Y = Sx[corner], Sy[corner]  # (3, C F)

    # 2. drop faces crossing the near plane, non-finite, off-screen, degenerate (back-facing)
    valid = vok[corner].all(0)
    jmin = torch.ceil(X.amin(0) / _SUBPIXEL).clamp_min_(0)
    jmax = torch.floor(X.amax(0) / _SUBPIXEL).clamp_max_(W - 1)
    imin = torch.ceil(Y.amin(0) / _SUBPIXEL).clamp_min_(0)
    imax = torch.floor(Y.amax(0) / _SUBPIXEL).clamp_max_(H - 1)
    valid &= (jmax >= jmin) & (imax >= imin)
    # twice the signed area; with y down and fx, fy > 0 a front face has area2 < 0
    area2 = (X[1] - X[0]) * (Y[2] - Y[0]) - (Y[1] - Y[0]) * (X[2] - X[0])
    valid &= area2 != 0
    if cull_backfaces:
        valid &= (area2.view(C, F) * fx_fy_sign.to(f64)[:, None] < 0).view(-1)
    sel = valid.nonzero().squeeze(1)  # (M,) face instances c * F + f
    M = sel.numel()
    if M == 0:
        return torch.full((C, H, W), _KEY_BG, dtype=torch.int64, device=dev)
    jmin, jmax, imin, imax = (t[sel].long() for t in (jmin, jmax, imin, imax))

    # 3. split faces whose box exceeds the largest tile into several tiles ("pieces")
    nx, ny = jmax - jmin + 1, imax - imin + 1
    npx = (nx + _TILE_MAX - 1) >> _LOG2_TILE_MAX
    npy = (ny + _TILE_MAX - 1) >> _LOG2_TILE_MAX
    npieces = npx * npy
    if bool((npieces > 1).any()):
        owner = torch.repeat_interleave(torch.arange(M, device=dev), npieces)
        first = torch.cumsum(npieces, 0) - npieces
        local = torch.arange(owner.numel(), device=dev) - first[owner]
        qx = local % npx[owner]
        qy = local // npx[owner]
        x0 = jmin[owner] + qx * _TILE_MAX
        y0 = imin[owner] + qy * _TILE_MAX
        nxp = (jmax[owner] - x0 + 1).clamp_max(_TILE_MAX)
        nyp = (imax[owner] - y0 + 1).clamp_max(_TILE_MAX)
    else:
        owner = None
        x0, y0, nxp, nyp = jmin, imin, nx, ny

    # 4. group pieces by tile shape (small groups merged into bigger shapes), sort by group
    lut = torch.tensor(_tile_classes(), device=dev)
    group = lut[nxp] * _NCLS + lut[nyp]
    counts = torch.bincount(group, minlength=_NCLS * _NCLS).tolist()
    group = torch.tensor(_merge_groups(counts), device=dev)[group]
    counts = torch.bincount(group, minlength=_NCLS * _NCLS).tolist()
    order = torch.argsort(group)
    used = [g for g, n in enumerate(counts) if n]
    Wp = W + max(_TILE_SIZES[g // _NCLS] for g in used) - 1  # tiles overhang right / bottom
    Hp = H + max(_TILE_SIZES[g % _NCLS] for g in used) - 1
    inst = sel[order if owner is None else owner[order]]  # (Mp,) face instance of each piece
    x0, y0 = x0[order], y0[order]
    cam = inst // F
    fid = inst - cam * F
    vid = faces.t().index_select(1, fid) + cam * V  # (3, Mp) rows of the flat (C V) arrays
    X, Y = Sx[vid], Sy[vid]  # (3, Mp) snapped corners
    Zc = z.reshape(-1)[vid].to(f64)
    area2 = area2[inst]

    # 5. edge functions. Edge k runs from corner k+1 to k+2 (opposite corner k):
    #    e_k(P) = d x (P - p_{k+1}) = -dy Px + dx Py + (dy x_{k+1} - dx y_{k+1}),
    #    an integer at every pixel centre P (subpixel units), and sum_k e_k = area2.
    X1, Y1 = X.roll(-1, 0), Y.roll(-1, 0)  # corners k+1
    dX, dY = X.roll(-2, 0) - X1, Y.roll(-2, 0) - Y1
    sgn = torch.sign(area2)
    e0 = dY * X1 - dX * Y1  # e_k at P = 0
    # 6. fill rule. The canonical direction of an edge runs from its lexicographically
    #    smaller end point (sigma = -1 when that is corner k+2). A pixel centre on the
    #    edge (e_k = 0) belongs to the face on the left of the canonical direction, i.e.
    #    inside <=> sgn e_k + sigma sgn / 2 > 0 (e_k is an integer): one strict test.
    swap = (dX < 0) | ((dX == 0) & (dY < 0))
    half_sigma = 0.5 - swap.to(f64)  # sigma / 2
    a = -sgn * dY  # (3, Mp) coefficient of Px
    b = sgn * dX  # coefficient of Py
    Px0, Py0 = x0.to(f64) * _SUBPIXEL, y0.to(f64) * _SUBPIXEL
    c = a * Px0 + b * Py0 + sgn * (e0 + half_sigma)  # value at the tile origin
    # 1/z is affine in screen space: 1/z(P) = sum_k e_k(P) / (z_k area2). The depth key
    # uses 1/z quantised uniformly on [0, 1/near] (like a GPU z-buffer) to the bits left
    # over by the face id, q = (1/near - 1/z) * zscale, smaller = nearer; q is affine
    # too, so the matrix product below evaluates it directly.
    fbits, zscale, qmax = _key_layout(F, near)
    g = -zscale / (Zc * area2)  # (3, Mp)
    ia, ib = -(dY * g).sum(0), (dX * g).sum(0)
    ic = ia * Px0 + ib * Py0 + (e0 * g).sum(0) + qmax
    # rows (e_0, e_1, e_2, q) x columns (ox, oy, 1) in tile-pixel offsets: (Mp, 4, 3);
    # exact for the edges (integers below 2**53)
    Mp = inst.numel()
    coef = torch.empty(Mp, 4, 3, dtype=f64, device=dev)
    torch.mul(a.t(), _SUBPIXEL, out=coef[:, :3, 0])
    torch.mul(b.t(), _SUBPIXEL, out=coef[:, :3, 1])
    coef[:, :3, 2] = c.t()
    torch.mul(ia, _SUBPIXEL, out=coef[:, 3, 0])
    torch.mul(ib, _SUBPIXEL, out=coef[:, 3, 1])
    coef[:, 3, 2] = ic
    base = (cam * Hp + y0) * Wp + x0  # (Mp,) flat buffer index of the tile origin

    buf = torch.full((C * Hp * Wp,), _KEY_BG, dtype=torch.int64, device=dev)
    start = 0
    for grp in used:
        n = counts[grp]
        tx, ty = _TILE_SIZES[grp // _NCLS], _TILE_SIZES[grp % _NCLS]
        T = tx * ty
        t = torch.arange(T, device=dev)
        ox, oy = t % tx, t // tx
        OT = torch.stack([ox.to(f64), oy.to(f64), torch.ones(T, dtype=f64, device=dev)], 1)  # (T, 3)
        poff = oy * Wp + ox  # (T,)
        # P pieces per matrix product, a power of two so flat index -> (t, p) is a shift
        P = min(faces_per_chunk, max(1, pixels_per_chunk // T))
        P = 1 << (P.bit_length() - 1)
        if n < P:
            P = 1 << (n - 1).bit_length()
        logP = P.bit_length() - 1
        for s0 in range(start, start + n, P):
            s1 = min(s0 + P, start + n)
            cf, base_c, fid_c = coef[s0:s1], base[s0:s1], fid[s0:s1]
            if s1 - s0 < P:  # zero rows are never inside
                cf = torch.cat([cf, cf.new_zeros(P - (s1 - s0), 4, 3)])
            # R[t, r, p] = sum_j OT[t, j] coef[p, r, j]: the edge functions (r < 3) and the
            # depth q (r = 3) of every piece p at every pixel t of its tile
            R = torch.mm(OT, cf.transpose(0, 1).reshape(4 * P, 3).t()).view(T, 4, P)
            m = torch.minimum(R[:, 0], R[:, 1])
            torch.minimum(m, R[:, 2], out=m)
            nz = (m > 0).view(-1).nonzero().squeeze(1)  # covered (t, p) as t * P + p
            if nz.numel() == 0:
                continue
            tt = nz >> logP
            p = nz & (P - 1)
            qz = R.view(-1)[nz + ((tt * 3 + 3) << logP)].clamp_(0.0, qmax).to(torch.int64)  # R[tt, 3, p]
            # 7. depth test: one packed key per covered pixel, minimum per pixel
            buf.scatter_reduce_(0, base_c[p] + poff[tt], (qz << fbits) | fid_c[p], "amin")
        start += n
    return buf.view(C, Hp, Wp)[:, :H, :W]


@torch.no_grad()
def rasterize(
    verts: Tensor,
    faces: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    height: int,
    width: int,
    near: float = 1e-3,
    cull_backfaces: bool = False,
    faces_per_chunk: int = 1 << 14,
    pixels_per_chunk: int = 1 << 18,
    with_bary: bool = True,
    backend: str = "warp",
) -> Fragments:
    """Z-buffer rasterisation of a triangle mesh into C cameras (no gradients).

    verts: (V, 3) world-space vertices shared by all cameras, or (C, V, 3) per camera.
    faces: (F, 3) integer vertex indices. K: (C, 3, 3). world_to_cam: (C, 4, 4).
    height, width: image size H, W. near: faces with any vertex at z < near are dropped
    (no clipping); depth resolution is that of 1/z quantised on [0, 1/near] with
    62 - log2(F) bits. cull_backfaces: drop faces seen from behind (see the module
    docstring for the winding). backend: ``'warp'`` (one Warp kernel thread per camera and
    face, :mod:`anidress_core.raster_kernels`; CPU or CUDA) or ``'torch'`` (the batched tensor
    code below, the reference; same coverage, see ``benchmarks/raster.md`` for the speed).
    faces_per_chunk, pixels_per_chunk (torch backend): at most this many face tiles and tile
    pixels are evaluated at once, which bounds the memory (about 60 bytes per tile pixel)
    whatever the size of the faces.

    Returns :class:`Fragments` (C, H, W): face id (-1 background), perspective-correct
    barycentrics, camera z (+inf background). See the module docstring for the method.
    with_bary=False (visibility only, e.g. silhouettes while fitting): ``bary`` is None and
    ``depth`` is the depth-test value decoded from its key (1/z of the plane through the
    1/256-pixel-snapped vertices, quantised to 62 - log2(F) bits: relative error ~1e-4,
    from the snapping), which skips the per-pixel barycentric pass.
    """
    faces = _check_faces("rasterize", faces)
    K, world_to_cam, verts = _check_cameras("rasterize", K, world_to_cam, verts)
    if not verts.is_floating_point():
        raise ValueError(f"rasterize: verts must be floating point, got {verts.dtype}")
    if height < 0 or width < 0:
        raise ValueError(f"rasterize: bad image size {height} x {width}")
    if faces_per_chunk < 1 or pixels_per_chunk < 1:
        raise ValueError("rasterize: faces_per_chunk and pixels_per_chunk must be >= 1")
    if not near > 0:
        raise ValueError(f"rasterize: near must be > 0, got {near}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= verts.shape[-2]):
        raise ValueError(f"rasterize: faces index out of range for {verts.shape[-2]} vertices")
    uv, z = project_vertices(verts, K, world_to_cam)  # (C, V, 2), (C, V)
    sign = torch.sign(K[:, 0, 0] * K[:, 1, 1])
    if backend == "warp":
        keys = _raster_keys_warp(uv, z, faces, sign, height, width, near, cull_backfaces)
    elif backend == "torch":
        keys = _raster_keys_torch(
            uv, z, faces, sign, height, width, near, cull_backfaces, faces_per_chunk, pixels_per_chunk
        )
    else:
        raise ValueError(f"rasterize: backend must be 'warp' or 'torch', got {backend!r}")
    fbits, zscale, _ = _key_layout(int(faces.shape[0]), near)
    fg = keys != _KEY_BG
    face_id = torch.where(fg, keys & ((1 << fbits) - 1), torch.full_like(keys, -1))
    if not with_bary:
        # q = (1/near - 1/z) * zscale (_key_layout)
        q = (keys >> fbits).to(torch.float64)
        inv_z = 1.0 / near - q / zscale
        depth = torch.where(fg, 1.0 / inv_z.clamp_min(1e-300), torch.full_like(q, float("inf")))
        return Fragments(face_id, None, depth.to(z.dtype))  # type: ignore[arg-type]
    bary, depth = _bary_from_projection(uv, z, faces, face_id)
    return Fragments(face_id, bary, depth)


# --------------------------------------------------------------------------------------
# attributes, textures, shading
# --------------------------------------------------------------------------------------


def interpolate(
    attr: Tensor, faces: Tensor, fragments: Fragments, bary: Tensor | None = None, per_corner: bool | None = None
) -> Tensor:
    """Barycentric interpolation of attributes at the pixels: (C, H, W, D), 0 on background.

    attr: per-vertex (V, D) or (C, V, D), or per face corner (F, 3, D) (e.g. UVs with
    seams). ``per_corner`` says which a 3-D ``attr`` is; by default it is inferred from
    the shape (an error when both readings fit). bary: (C, H, W, 3), default
    ``fragments.bary``; pass :func:`barycentrics` for gradients to the vertex positions.
    Differentiable with respect to ``attr`` and ``bary``.
    """
    faces = _check_faces("interpolate", faces)
    C, H, W = _check_fragments("interpolate", fragments)
    F = faces.shape[0]
    bary = fragments.bary if bary is None else bary
    if bary.shape != (C, H, W, 3):
        raise ValueError(f"interpolate: bary must be {(C, H, W, 3)}, got {tuple(bary.shape)}")
    if attr.ndim == 2:
        mode = "shared"
    elif attr.ndim == 3:
        corner_ok = attr.shape[:2] == (F, 3)
        camera_ok = attr.shape[0] == C
        if per_corner is None:
            if corner_ok and camera_ok:
                raise ValueError(
                    f"interpolate: attr {tuple(attr.shape)} is both (F, 3, D) and (C, V, D); pass per_corner"
                )
            per_corner = corner_ok
        if per_corner and not corner_ok:
            raise ValueError(f"interpolate: per-corner attr must be (F, 3, D) = ({F}, 3, D), got {tuple(attr.shape)}")
        if not per_corner and not camera_ok:
            raise ValueError(f"interpolate: attr must be (V, D), ({C}, V, D) or ({F}, 3, D), got {tuple(attr.shape)}")
        mode = "corner" if per_corner else "camera"
    else:
        raise ValueError(f"interpolate: attr must be (V, D), (C, V, D) or (F, 3, D), got {tuple(attr.shape)}")
    D = attr.shape[-1]
    flat = fragments.face_id.reshape(-1)
    pix = (flat >= 0).nonzero().squeeze(1)
    f = flat[pix]
    if mode == "shared":
        a = attr[faces[f]]  # (N, 3, D)
    elif mode == "camera":
        V = attr.shape[1]
        a = attr.reshape(C * V, D)[faces[f] + (pix // (H * W) * V)[:, None]]
    else:
        a = attr[f]
    b = bary.reshape(-1, 3)[pix].to(a.dtype)
    # val[n, d] = sum_k b[n, k] a[n, k, d]
    val = b[:, 0:1] * a[:, 0] + b[:, 1:2] * a[:, 1] + b[:, 2:3] * a[:, 2]
    out = a.new_zeros(C * H * W, D).index_put((pix,), val)
    return out.view(C, H, W, D)


def sample_texture(texture: Tensor, uv: Tensor, mask: Tensor | None = None, wrap: str = "clamp") -> Tensor:
    """Bilinear texture lookup. texture (Ht, Wt, Ch), uv (..., 2), e.g. (C, H, W, 2) -> (..., Ch).

    OBJ convention: u runs left to right, v bottom to top (v = 0 is the LAST row of the
    texture image); texel (r, c) has its centre at u = (c + 0.5) / Wt,
    v = 1 - (r + 0.5) / Ht. ``wrap="clamp"`` repeats the border texels beyond the
    centres of the outer texels (and outside [0, 1]); ``wrap="repeat"`` tiles the
    texture (u, v taken modulo 1, filtering across the seam). mask (...) bool: only
    those pixels are sampled, the others are 0. Differentiable w.r.t. texture and uv
    (``torch.nn.functional.grid_sample`` underneath, ``align_corners=False``).
    """
    if texture.ndim != 3:
        raise ValueError(f"sample_texture: texture must be (Ht, Wt, Ch), got {tuple(texture.shape)}")
    if uv.shape[-1] != 2:
        raise ValueError(f"sample_texture: uv must be (..., 2), got {tuple(uv.shape)}")
    if wrap not in ("clamp", "repeat"):
        raise ValueError(f"sample_texture: wrap must be 'clamp' or 'repeat', got {wrap!r}")
    lead = uv.shape[:-1]
    flat_uv = uv.reshape(-1, 2)
    if mask is not None:
        if mask.shape != lead:
            raise ValueError(f"sample_texture: mask must be {tuple(lead)}, got {tuple(mask.shape)}")
        pix = mask.reshape(-1).nonzero().squeeze(1)
        val = _sample_texture_flat(texture, flat_uv[pix], wrap)
        return val.new_zeros(flat_uv.shape[0], texture.shape[2]).index_put((pix,), val).view(*lead, -1)
    return _sample_texture_flat(texture, flat_uv, wrap).view(*lead, -1)


def _sample_texture_flat(texture: Tensor, uv: Tensor, wrap: str) -> Tensor:
    """texture (Ht, Wt, Ch), uv (N, 2) -> (N, Ch); see :func:`sample_texture`."""
    Ht, Wt, Ch = texture.shape
    tex = texture.permute(2, 0, 1)[None]  # (1, Ch, Ht, Wt)
    uv = uv.to(texture.dtype)
    # grid_sample coordinates, align_corners=False: x = 2u - 1 (left edge -1), y = 1 - 2v
    # (v = 1 is the top edge, y = -1)
    if wrap == "repeat":
        # pad one wrapped texel on every side, then sample frac(u), frac(v) in the padded image
        tex = torch.cat([tex[..., -1:, :], tex, tex[..., :1, :]], 2)
        tex = torch.cat([tex[..., -1:], tex, tex[..., :1]], 3)
        u = (torch.frac(uv[:, 0]) + 1) % 1  # [0, 1) also for negative u
        v = (torch.frac(uv[:, 1]) + 1) % 1
        gx = (2 * u * Wt + 2) / (Wt + 2) - 1
        gy = (2 * (1 - v) * Ht + 2) / (Ht + 2) - 1
    else:
        gx = 2 * uv[:, 0] - 1
        gy = 1 - 2 * uv[:, 1]
    grid = torch.stack([gx, gy], -1)[None, None]  # (1, 1, N, 2)
    out = torch.nn.functional.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].t()  # (N, Ch)


def _lambert(albedo: Tensor, normals: Tensor, light_dirs: Tensor, light_colors: Tensor, ambient: Tensor,
             two_sided: bool) -> Tensor:
    """albedo, normals (N, 3); light_dirs, light_colors (L, 3) or (N, L, 3); ambient (3,) -> (N, 3)."""
    ld = light_dirs.to(normals.dtype)
    ld = ld / ld.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    lc = light_colors.to(albedo.dtype)
    if ld.ndim == 2:
        cos = normals @ ld.t()  # cos[n, l] = sum_k n[n, k] d[l, k]
    else:
        cos = torch.einsum("nk,nlk->nl", normals, ld)
    cos = cos.abs() if two_sided else cos.clamp_min(0)
    # light[n, i] = sum_l cos[n, l] colour[l, i]
    light = cos.to(albedo.dtype) @ lc if lc.ndim == 2 else torch.einsum("nl,nli->ni", cos.to(albedo.dtype), lc)
    return (albedo * (ambient.reshape(-1) + light)).clamp(0, 1)


def shade_lambert(
    albedo: Tensor,
    normals: Tensor,
    light_dirs: Tensor,
    light_colors: Tensor,
    ambient: Tensor,
    two_sided: bool = False,
) -> Tensor:
    """Lambertian shading, clamped to [0, 1]: albedo * (ambient + sum_l color_l max(0, n . l)).

    albedo (C, H, W, 3), normals (C, H, W, 3) unit; light_dirs (L, 3) or (C, L, 3)
    directions FROM the surface TOWARDS each (directional) light, in the same frame as
    the normals (normalised here); light_colors (L, 3) or (C, L, 3); ambient (3,).
    two_sided: use |n . l| (lights both sides of a surface) instead of max(0, n . l).
    Differentiable.
    """
    if albedo.shape[-1] != 3 or normals.shape != albedo.shape or albedo.ndim != 4:
        raise ValueError(
            f"shade_lambert: albedo and normals must be (C, H, W, 3), got {tuple(albedo.shape)}, {tuple(normals.shape)}"
        )
    C = albedo.shape[0]
    if (
        light_dirs.shape[-1] != 3
        or light_dirs.ndim not in (2, 3)
        or light_colors.shape != light_dirs.shape
        or (light_dirs.ndim == 3 and light_dirs.shape[0] != C)
    ):
        raise ValueError(
            f"shade_lambert: light_dirs and light_colors must be (L, 3) or ({C}, L, 3), got "
            f"{tuple(light_dirs.shape)}, {tuple(light_colors.shape)}"
        )
    ambient = torch.as_tensor(ambient, dtype=albedo.dtype, device=albedo.device)
    if ambient.numel() not in (1, 3):
        raise ValueError(f"shade_lambert: ambient must be (3,), got {tuple(ambient.shape)}")
    n_per_cam = albedo[0].numel() // 3
    if light_dirs.ndim == 3:  # per camera -> per pixel (a view, no copy)
        L = light_dirs.shape[1]
        light_dirs = light_dirs[:, None].expand(C, n_per_cam, L, 3).reshape(-1, L, 3)
        light_colors = light_colors[:, None].expand(C, n_per_cam, L, 3).reshape(-1, L, 3)
    out = _lambert(albedo.reshape(-1, 3), normals.reshape(-1, 3), light_dirs, light_colors, ambient, two_sided)
    return out.view(albedo.shape)


def render_mesh(
    verts: Tensor,
    faces: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    height: int,
    width: int,
    face_uv: Tensor | None = None,
    texture: Tensor | None = None,
    vertex_colors: Tensor | None = None,
    light_dirs: Tensor | None = None,
    light_colors: Tensor | None = None,
    ambient: Tensor | None = None,
    background: float | Tensor = 0.0,
    near: float = 1e-3,
    cull_backfaces: bool = False,
    texture_wrap: str = "clamp",
) -> Render:
    """Render a (textured, lit) mesh into C cameras; what synthetic data generation calls.

    verts (V, 3) or (C, V, 3) world; faces (F, 3); K (C, 3, 3); world_to_cam (C, 4, 4).
    Albedo: ``texture`` (Ht, Wt, 3) sampled at the interpolated ``face_uv`` (F, 3, 2)
    (see :func:`sample_texture`), else ``vertex_colors`` (V, 3) or (C, V, 3), else white.
    Lighting, in WORLD space: directional lights ``light_dirs`` (L, 3) pointing from the
    surface towards the lights, ``light_colors`` (L, 3) (default white), ``ambient`` (3,)
    (default 0); shading happens in world space with the two-sided smooth normals (see
    ``Render.normals_cam``; near silhouettes an interpolated normal can still lean
    slightly away from the camera). Without lights and ambient the albedo is returned
    unlit. background: scalar or (3,) colour of uncovered pixels.
    Differentiable w.r.t. texture, vertex_colors and lights; w.r.t. ``verts`` too when
    they require grad (through the barycentrics, inside faces only; compose with
    :func:`antialias` for silhouette gradients).
    """
    faces = _check_faces("render_mesh", faces)
    K, world_to_cam, verts = _check_cameras("render_mesh", K, world_to_cam, verts)
    F = faces.shape[0]
    if texture is not None:
        if face_uv is None or face_uv.shape != (F, 3, 2):
            raise ValueError(
                f"render_mesh: a texture needs face_uv (F, 3, 2) = ({F}, 3, 2), got "
                f"{None if face_uv is None else tuple(face_uv.shape)}"
            )
        if texture.ndim != 3 or texture.shape[-1] != 3:
            raise ValueError(f"render_mesh: texture must be (Ht, Wt, 3), got {tuple(texture.shape)}")
    if vertex_colors is not None and (
        vertex_colors.ndim not in (2, 3) or vertex_colors.shape[-1] != 3 or vertex_colors.shape[-2] != verts.shape[-2]
    ):
        raise ValueError(f"render_mesh: vertex_colors must be (V, 3) or (C, V, 3), got {tuple(vertex_colors.shape)}")
    frags = rasterize(verts.detach(), faces, K, world_to_cam, height, width, near=near, cull_backfaces=cull_backfaces)
    C, H, W = frags.face_id.shape
    V = verts.shape[-2]
    dtype, dev = verts.dtype, verts.device

    # 1. covered pixels and the corners of their faces
    pix, cam, row, col, f = _foreground(frags.face_id)
    idx = faces[f].t() + cam * V  # (3, N) rows of per-camera (C V) arrays
    idx_shared = faces[f].t()  # (3, N) rows of shared (V) arrays
    uv, z = project_vertices(verts, K, world_to_cam)  # (C, V, 2), (C, V)
    u, v = uv[..., 0].reshape(-1)[idx], uv[..., 1].reshape(-1)[idx]  # (3, N)
    if verts.requires_grad:
        b = _bary_depth(u, v, z.reshape(-1)[idx], col.to(dtype), row.to(dtype))[0]  # (3, N)
    else:
        b = frags.bary.reshape(-1, 3)[pix].t()

    def lerp(attr: Tensor) -> Tensor:  # per-vertex (V, D) / (C, V, D) -> (N, D)
        a = attr.reshape(-1, attr.shape[-1])
        i = idx if attr.ndim == 3 else idx_shared
        return b[0, :, None] * a[i[0]] + b[1, :, None] * a[i[1]] + b[2, :, None] * a[i[2]]

    # 2. albedo (N, 3)
    if texture is not None:
        fuv = face_uv[f].to(dtype)  # (N, 3, 2)
        tuv = b[0, :, None] * fuv[:, 0] + b[1, :, None] * fuv[:, 1] + b[2, :, None] * fuv[:, 2]
        albedo = _sample_texture_flat(texture, tuv, texture_wrap).to(dtype)
    elif vertex_colors is not None:
        albedo = lerp(vertex_colors.to(dtype))
    else:
        albedo = torch.ones(pix.shape[0], 3, dtype=dtype, device=dev)

    # 3. smooth world-space normals, flipped on faces seen from behind: with y down and
    #    fx fy > 0 those have positive screen-space area
    n = lerp(vertex_normals(verts, faces))  # (N, 3)
    with torch.no_grad():
        ud, vd = u.detach(), v.detach()
        area2 = (ud[1] - ud[0]) * (vd[2] - vd[0]) - (vd[1] - vd[0]) * (ud[2] - ud[0])
        back = area2 * torch.sign(K[:, 0, 0] * K[:, 1, 1]).to(dtype)[cam] > 0
    n = torch.where(back[:, None], -n, n)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    # 4. shading in world space
    if light_dirs is not None or ambient is not None:
        if light_dirs is None:
            light_dirs = torch.zeros(0, 3, dtype=dtype, device=dev)
        if light_dirs.ndim != 2 or light_dirs.shape[-1] != 3:
            raise ValueError(f"render_mesh: light_dirs must be (L, 3), got {tuple(light_dirs.shape)}")
        if light_colors is None:
            light_colors = torch.ones_like(light_dirs)
        if light_colors.shape != light_dirs.shape:
            raise ValueError(
                f"render_mesh: light_colors must be {tuple(light_dirs.shape)}, got {tuple(light_colors.shape)}"
            )
        amb = torch.zeros(3, dtype=dtype, device=dev) if ambient is None else torch.as_tensor(ambient).to(dtype)
        rgb_fg = _lambert(albedo, n, light_dirs, light_colors, amb, two_sided=False)
    else:
        rgb_fg = albedo.clamp(0, 1)

    # 5. camera-space normals, images
    Rg = world_to_cam[:, :3, :3].to(dtype)[cam]  # (N, 3, 3)
    # n_cam[n, i] = sum_j R[i, j] n_world[j]
    n_cam = Rg[:, :, 0] * n[:, 0:1] + Rg[:, :, 1] * n[:, 1:2] + Rg[:, :, 2] * n[:, 2:3]
    bg = torch.as_tensor(background, dtype=rgb_fg.dtype, device=dev).reshape(-1).expand(3)
    rgb = bg.expand(C * H * W, 3).index_put((pix,), rgb_fg)
    normals_cam = n_cam.new_zeros(C * H * W, 3).index_put((pix,), n_cam)
    mask = frags.face_id >= 0
    return Render(rgb.view(C, H, W, 3), mask, frags.depth, normals_cam.view(C, H, W, 3), frags)


# --------------------------------------------------------------------------------------
# silhouette gradients (nvdiffrast antialias)
# --------------------------------------------------------------------------------------


def face_adjacency(faces: Tensor) -> Tensor:
    """(F, 3) int64: the face across edge k (corners k+1, k+2) of each face, -1 on a
    boundary (or non-manifold) edge. Topology only; compute once per mesh."""
    faces = _check_faces("face_adjacency", faces)
    F = faces.shape[0]
    if F == 0:
        return faces.new_empty(0, 3)
    a = faces[:, [1, 2, 0]].reshape(-1)
    b = faces[:, [2, 0, 1]].reshape(-1)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    n = int(faces.max()) + 1
    code = lo * n + hi  # (3F,) undirected edge id
    order = torch.argsort(code, stable=True)
    sc = code[order]
    same_next = torch.zeros_like(sc, dtype=torch.bool)
    same_next[:-1] = sc[1:] == sc[:-1]
    # manifold pairs: exactly two half-edges share the code
    cnt = torch.unique_consecutive(sc, return_counts=True)[1]
    mult = torch.repeat_interleave(cnt, cnt)
    pair = same_next & (mult == 2)
    adj = torch.full((3 * F,), -1, dtype=torch.int64, device=faces.device)
    i = pair.nonzero().squeeze(1)
    h0, h1 = order[i], order[i + 1]
    adj[h0] = h1 // 3
    adj[h1] = h0 // 3
    return adj.view(F, 3)


class SilhouetteCrossings(NamedTuple):
    """Visible silhouette edges crossing the segment between two adjacent pixel centres
    of which exactly one is covered by the mesh (see :func:`silhouette_crossings`); N pairs.

    inside, outside: (N,) int64 flat indices into (C * H * W) of the covered pixel and of
        its uncovered horizontal or vertical neighbour.
    cam: (N,) int64 camera of the pair.
    edge: (N, 2) int64 vertex ids of the crossing silhouette edge.
    inside_xy, outside_xy: (N, 2) float64 pixel-centre coordinates (u = column, v = row).
    """

    inside: Tensor
    outside: Tensor
    cam: Tensor
    edge: Tensor
    inside_xy: Tensor
    outside_xy: Tensor


def mesh_edges(faces: Tensor, adjacency: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Unique undirected edges of a triangle mesh and the faces on either side.

    Returns edges (E, 2) int64 vertex ids and edge_faces (E, 2) int64 (the second is -1
    on a boundary or non-manifold edge). Topology only; compute once per mesh.
    """
    faces = _check_faces("mesh_edges", faces)
    if adjacency is None:
        adjacency = face_adjacency(faces)
    F = faces.shape[0]
    f = torch.arange(F, device=faces.device)[:, None].expand(F, 3)
    take = (adjacency < 0) | (f < adjacency)  # each interior edge once, from its lower face
    fi, k = take.nonzero(as_tuple=True)
    edges = torch.stack([faces[fi, (k + 1) % 3], faces[fi, (k + 2) % 3]], -1)
    return edges, torch.stack([fi, adjacency[fi, k]], -1)


@torch.no_grad()
def silhouette_crossings(uv: Tensor, z: Tensor, faces: Tensor, fragments: Fragments,
                         edges: tuple[Tensor, Tensor] | None = None, near: float = 1e-3,
                         depth_tol: float = 0.25) -> SilhouetteCrossings:
    """Find where the visible silhouette edges of a mesh cross pixel-centre segments (no gradients).

    Edge-centric counterpart of nvdiffrast's pixel-pair search in :func:`antialias`
    (which only blends a pair when the covered pixel's *own* face has the crossing
    edge: with faces of 1-2 pixels that misses more than half of the silhouette pixels).

    1. Silhouette edges per camera: mesh-boundary edges and edges between faces whose
       projections have opposite orientation; edges with an end point closer than
       ``near`` are skipped.
    2. Each one is intersected with the horizontal segments between pixel centres of the
       rows it spans (rows i with y_min <= i < y_max) and the vertical segments of the
       columns it spans.
    3. A crossing is kept when exactly one of the two pixels is covered
       (``fragments.face_id >= 0``; :func:`occlude` first for occluders), the uncovered
       pixel's depth (+inf on background, the occluder's where one hides the mesh) is
       not in front of the edge, and the edge is not more than ``depth_tol`` (relative)
       behind the covered pixel's surface (an edge far behind the visible surface; the
       margin allows for the depth change across the faces next to a grazing contour).
    4. Of several crossings of one segment, the nearest edge (camera z at the crossing,
       1/z interpolated in screen space) wins: an edge hidden behind the visible surface
       loses to that surface's own silhouette edge, which crosses the same segment.

    uv (C, V, 2), z (C, V): :func:`project_vertices` of the mesh the fragments come
    from; edges: :func:`mesh_edges` (computed when not given).
    """
    faces = _check_faces("silhouette_crossings", faces)
    C, H, W = _check_fragments("silhouette_crossings", fragments)
    if uv.ndim != 3 or uv.shape[0] != C or uv.shape[-1] != 2 or z.shape != uv.shape[:2]:
        raise ValueError(f"silhouette_crossings: uv must be ({C}, V, 2) and z ({C}, V), got "
                         f"{tuple(uv.shape)}, {tuple(z.shape)}")
    E_v, E_f = mesh_edges(faces) if edges is None else edges
    dev = uv.device
    f64 = torch.float64
    uv = uv.detach().to(f64)
    z = z.detach().to(f64)
    empty_i = torch.zeros(0, dtype=torch.int64, device=dev)
    empty_xy = torch.zeros(0, 2, dtype=f64, device=dev)
    empty = SilhouetteCrossings(empty_i, empty_i, empty_i, empty_i.view(0, 2), empty_xy, empty_xy)
    if E_v.shape[0] == 0 or C == 0 or H == 0 or W == 0:
        return empty
    # 1. silhouette edges per camera
    p = uv[:, faces]  # (C, F, 3, 2)
    e1, e2 = p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0]
    orient = torch.sign(e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0])  # (C, F)
    fa, fb = E_f[:, 0], E_f[:, 1]
    o_a = orient[:, fa]
    o_b = torch.where(fb >= 0, orient[:, fb.clamp_min(0)], torch.zeros_like(o_a))
    sil = (fb < 0)[None] | (o_a != o_b)
    sil &= (z[:, E_v[:, 0]] >= near) & (z[:, E_v[:, 1]] >= near)
    sil &= torch.isfinite(uv[:, E_v].reshape(C, -1, 4)).all(-1)
    cam, ei = sil.nonzero(as_tuple=True)
    if cam.numel() == 0:
        return empty
    va, vb = E_v[ei, 0], E_v[ei, 1]
    A, B = uv[cam, va], uv[cam, vb]  # (M, 2)
    za, zb = z[cam, va], z[cam, vb]
    fid = fragments.face_id.reshape(-1)
    depth = fragments.depth.reshape(-1).to(f64)
    parts = []
    for axis in (1, 0):  # rows (horizontal segments, x varies), columns (vertical segments)
        other = 1 - axis
        lo = torch.minimum(A[:, axis], B[:, axis])
        hi = torch.maximum(A[:, axis], B[:, axis])
        limit = (H if axis == 1 else W) - 1
        first = torch.ceil(lo).clamp_min(0)
        last = (torch.ceil(hi) - 1).clamp_max(limit)
        n = (last - first + 1).clamp_min(0).to(torch.int64)
        if int(n.sum()) == 0:
            continue
        m = torch.repeat_interleave(torch.arange(cam.numel(), device=dev), n)
        k = torch.arange(m.numel(), device=dev) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        line = first[m] + k.to(f64)  # the row (or column) index of the segment
        lam = (line - A[m, axis]) / (B[m, axis] - A[m, axis])  # position along the edge, [0, 1)
        cross = A[m, other] + lam * (B[m, other] - A[m, other])
        lo_pix = torch.floor(cross)
        ok = (lo_pix >= 0) & (lo_pix <= (W if axis == 1 else H) - 2)
        m, line, lam, lo_pix = m[ok], line[ok], lam[ok], lo_pix[ok]
        if m.numel() == 0:
            continue
        c = cam[m]
        li, pi = line.to(torch.int64), lo_pix.to(torch.int64)
        if axis == 1:  # row li, columns pi, pi + 1
            pa = (c * H + li) * W + pi
            pb = pa + 1
            xa = torch.stack([lo_pix, line], -1)
            xb = torch.stack([lo_pix + 1, line], -1)
        else:  # column li, rows pi, pi + 1
            pa = (c * H + pi) * W + li
            pb = pa + W
            xa = torch.stack([line, lo_pix], -1)
            xb = torch.stack([line, lo_pix + 1], -1)
        ha, hb = fid[pa] >= 0, fid[pb] >= 0
        ok = ha != hb
        inside = torch.where(ha, pa, pb)
        outside = torch.where(ha, pb, pa)
        # camera z of the edge at the crossing: 1/z is affine along the projected edge
        ze = 1.0 / ((1 - lam) / za[m] + lam / zb[m])
        ok &= ~(depth[outside] < ze * (1 - 1e-9))  # an occluder in front of the edge hides it
        ok &= ze <= depth[inside] * (1 + depth_tol)  # the edge is not behind the visible surface
        if not bool(ok.any()):
            continue
        sel = ok.nonzero().squeeze(1)
        pair = pa[sel] * 2 + (1 if axis == 0 else 0)
        parts.append((pair, ze[sel], inside[sel], outside[sel], c[sel], m[sel],
                      torch.where(ha[sel, None], xa[sel], xb[sel]), torch.where(ha[sel, None], xb[sel], xa[sel])))
    if not parts:
        return empty
    pair, ze, inside, outside, c, m, xin, xout = (torch.cat(x) for x in zip(*parts))
    # 4. one crossing per segment: the nearest edge
    order = torch.argsort(ze)
    order = order[torch.argsort(pair[order], stable=True)]
    ps = pair[order]
    first_of = torch.ones_like(ps, dtype=torch.bool)
    first_of[1:] = ps[1:] != ps[:-1]
    keep = order[first_of]
    edge = torch.stack([va[m[keep]], vb[m[keep]]], -1)
    return SilhouetteCrossings(inside[keep], outside[keep], c[keep], edge, xin[keep], xout[keep])


def pair_crossings(uv: Tensor, faces: Tensor, fragments: Fragments,
                   adjacency: Tensor | None = None) -> SilhouetteCrossings:
    """nvdiffrast's pixel-pair search used by :func:`antialias` (no gradients).

    uv (C, V, 2) projected vertices (:func:`project_vertices`), faces (F, 3), fragments
    (C, H, W) from :func:`rasterize` of the same mesh, adjacency (F, 3) from
    :func:`face_adjacency` (computed when not given).

    For each pair of horizontally or vertically adjacent pixels showing different faces
    (-1 = background or an occluder), the pixel with the smaller depth is the near one
    (``inside``); if it shows a face, the first of that face's silhouette edges that
    separates the two pixel centres is returned (``outside`` = the far pixel, which may
    be covered by a farther face).
    """
    with torch.no_grad():
        return _pair_crossings_impl(uv, faces, fragments, adjacency)


def _pair_crossings_impl(uv, faces, fragments, adjacency) -> SilhouetteCrossings:
    C, H, W = fragments.face_id.shape
    if adjacency is None:
        adjacency = face_adjacency(faces)
    uv = uv.detach()
    dev = uv.device
    fid = fragments.face_id
    depth = fragments.depth
    # 1. orientation of every face in every camera (sign of the screen-space area)
    p = uv[:, faces]  # (C, F, 3, 2)
    e1, e2 = p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0]
    orient = torch.sign(e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0])  # (C, F)
    out: list[tuple[Tensor, ...]] = []
    for axis in (2, 1):  # horizontal pairs (along W), vertical pairs (along H)
        if fid.shape[axis] < 2:
            continue
        n = fid.shape[axis] - 1
        fa, fb = fid.narrow(axis, 0, n), fid.narrow(axis, 1, n)
        da, db = depth.narrow(axis, 0, n), depth.narrow(axis, 1, n)
        cand = (fa != fb).reshape(-1).nonzero().squeeze(1)
        if cand.numel() == 0:
            continue
        # pixel indices of the pair in the full (C, H, W) grid
        shape = list(fid.shape)
        shape[axis] = n
        cc = cand // (shape[1] * shape[2])
        rr = (cand // shape[2]) % shape[1]
        ww = cand % shape[2]
        ia = (cc * H + rr) * W + ww
        ib = ia + (1 if axis == 2 else W)
        a_near = da.reshape(-1)[cand] <= db.reshape(-1)[cand]
        near_pix = torch.where(a_near, ia, ib)
        far_pix = torch.where(a_near, ib, ia)
        fnear = fid.reshape(-1)[near_pix]
        keep = fnear >= 0
        near_pix, far_pix, fnear, cc = near_pix[keep], far_pix[keep], fnear[keep], cc[keep]
        if near_pix.numel() == 0:
            continue
        # 2. silhouette edges of the near face: boundary, or neighbour oriented the other way
        nb = adjacency[fnear]  # (N, 3)
        o_self = orient[cc, fnear]
        o_nb = torch.where(nb >= 0, orient[cc[:, None], nb.clamp_min(0)], torch.zeros_like(nb, dtype=orient.dtype))
        sil = (nb < 0) | (o_nb != o_self[:, None])
        # 3. edge functions of the three edges at both pixel centres
        vid = faces[fnear]  # (N, 3)
        q = uv[cc[:, None], vid]  # (N, 3, 2)
        q1, q2 = q[:, [1, 2, 0]], q[:, [2, 0, 1]]
        pn, pf = _pixel_xy(near_pix, H, W).to(q.dtype), _pixel_xy(far_pix, H, W).to(q.dtype)
        d = q2 - q1
        en = d[..., 0] * (pn[:, None, 1] - q1[..., 1]) - d[..., 1] * (pn[:, None, 0] - q1[..., 0])  # (N, 3)
        ef = d[..., 0] * (pf[:, None, 1] - q1[..., 1]) - d[..., 1] * (pf[:, None, 0] - q1[..., 0])
        crosses = sil & ((en * o_self[:, None]) >= 0) & ((ef * o_self[:, None]) < 0)
        has = crosses.any(-1)
        if not bool(has.any()):
            continue
        rows = has.nonzero().squeeze(1)
        k = crosses.to(torch.int8).argmax(-1)[rows]  # first crossing silhouette edge
        edge = torch.stack([vid[rows, (k + 1) % 3], vid[rows, (k + 2) % 3]], -1)
        out.append((near_pix[rows], far_pix[rows], cc[rows], edge, pn[rows].double(), pf[rows].double()))
    if not out:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        xy = torch.zeros(0, 2, dtype=torch.float64, device=dev)
        return SilhouetteCrossings(e, e, e, e.view(0, 2), xy, xy)
    return SilhouetteCrossings(*(torch.cat(parts) for parts in zip(*out)))


def _pixel_xy(pixels: Tensor, H: int, W: int) -> Tensor:
    """(N,) flat (C H W) pixel indices -> (N, 2) float64 centres (u = column, v = row)."""
    return torch.stack([pixels % W, (pixels // W) % H], -1).to(torch.float64)


def crossing_fraction(q1: Tensor, q2: Tensor, near_xy: Tensor, far_xy: Tensor) -> Tensor:
    """Where the line through q1, q2 (N, 2) crosses the segment near_xy -> far_xy (N, 2).

    Returns t (N,), the fraction of the way from the near to the far pixel centre:
    ``t = e(near) / (e(near) - e(far))`` with the edge function
    ``e(p) = (q2 - q1) x (p - q1)``. Differentiable (w.r.t. q1, q2); finite whenever the
    line separates the two centres, as for every pair of :func:`silhouette_crossings`.
    """
    d = q2 - q1
    pn, pf = near_xy.to(q1.dtype), far_xy.to(q1.dtype)
    en = d[:, 0] * (pn[:, 1] - q1[:, 1]) - d[:, 1] * (pn[:, 0] - q1[:, 0])
    ef = d[:, 0] * (pf[:, 1] - q1[:, 1]) - d[:, 1] * (pf[:, 0] - q1[:, 0])
    return en / (en - ef)


def antialias(
    color: Tensor,
    verts: Tensor,
    faces: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    fragments: Fragments,
    adjacency: Tensor | None = None,
) -> Tensor:
    """Analytic antialiasing of silhouette edges with gradients to the vertex positions.

    nvdiffrast's ``antialias`` [Laine et al. 2020, sec. 3.3]: for each pair of
    horizontally or vertically adjacent pixels showing different faces, the nearer of
    the two faces (the other may be background) is tested for a silhouette edge (an
    edge on the mesh boundary or between a front- and a back-facing face) that crosses
    the segment between the two pixel centres, at fraction t from the nearer pixel's
    centre. The colours are then blended by the coverage of the pixel the edge lies in:
    if t > 1/2 the far pixel takes (t - 1/2) of the near one's colour, else the near
    pixel takes (1/2 - t) of the far one's. t is a differentiable function of the
    projected vertices, so e.g. ``antialias(mask[..., None].float(), ...)`` is a
    silhouette whose gradient moves the boundary (see :func:`silhouette`).

    color (C, H, W, Ch) (usually from :func:`interpolate`), verts (V, 3) or (C, V, 3),
    fragments from :func:`rasterize` of the same mesh (optionally :func:`occlude`-d);
    adjacency from :func:`face_adjacency` (computed when not given). Returns (C, H, W, Ch).
    """
    faces = _check_faces("antialias", faces)
    C, H, W = _check_fragments("antialias", fragments)
    if color.ndim != 4 or color.shape[:3] != (C, H, W):
        raise ValueError(f"antialias: color must be ({C}, {H}, {W}, Ch), got {tuple(color.shape)}")
    uv, _ = project_vertices(verts, K, world_to_cam)  # (C, V, 2)
    cr = pair_crossings(uv, faces, fragments, adjacency)
    Ch = color.shape[-1]
    flat = color.reshape(-1, Ch)
    if cr.inside.numel() == 0:
        return color
    V = uv.shape[1]
    uvf = uv.reshape(-1, 2)
    q1, q2 = uvf[cr.cam * V + cr.edge[:, 0]], uvf[cr.cam * V + cr.edge[:, 1]]
    t = crossing_fraction(q1, q2, cr.inside_xy, cr.outside_xy)
    cn, cf = flat[cr.inside], flat[cr.outside]
    # blend by coverage of the pixel containing the edge
    over = t > 0.5
    w_far = torch.where(over, t - 0.5, torch.zeros_like(t))[:, None].to(flat.dtype)
    w_near = torch.where(over, torch.zeros_like(t), 0.5 - t)[:, None].to(flat.dtype)
    delta = torch.zeros_like(flat).index_add(0, cr.outside, w_far * (cn - cf))
    delta = delta.index_add(0, cr.inside, w_near * (cf - cn))
    return (flat + delta).view(C, H, W, Ch)


# --------------------------------------------------------------------------------------
# differentiable rendering for fitting: occlusion, silhouettes, face normals, visibility
# --------------------------------------------------------------------------------------


def occlude(fragments: Fragments, occluder_depth: Tensor) -> Fragments:
    """Hide the pixels of ``fragments`` where another surface (e.g. the body) is nearer.

    occluder_depth: (C, H, W) camera z of the occluder (+inf where there is none), e.g.
    ``rasterize(body_verts, body_faces, ...).depth``. Hidden pixels get face -1,
    barycentrics 0 and the occluder's depth, so :func:`antialias` / :func:`silhouette`
    treat an occluder edge in front of the mesh as the occluder's (no gradient to the
    mesh) and a mesh edge in front of the occluder as a silhouette edge of the mesh.
    Equivalent to rasterising both meshes together and keeping the mesh's faces.
    """
    C, H, W = _check_fragments("occlude", fragments)
    if occluder_depth.shape != (C, H, W):
        raise ValueError(f"occlude: occluder_depth must be ({C}, {H}, {W}), got {tuple(occluder_depth.shape)}")
    od = occluder_depth.to(fragments.depth.dtype)
    hidden = od < fragments.depth
    bary = fragments.bary
    if bary is not None:
        bary = torch.where(hidden[..., None], torch.zeros_like(bary), bary)
    return Fragments(
        torch.where(hidden, torch.full_like(fragments.face_id, -1), fragments.face_id), bary,
        torch.minimum(fragments.depth, od),
    )


def silhouette(
    verts: Tensor,
    faces: Tensor,
    K: Tensor,
    world_to_cam: Tensor,
    fragments: Fragments,
    edges: tuple[Tensor, Tensor] | None = None,
    depth_tol: float = 0.25,
) -> Tensor:
    """Soft silhouette (C, H, W) with gradients to the vertex positions at its edges.

    The hard coverage of ``fragments`` (face id >= 0; :func:`occlude` them for
    occluders) plus, for every crossing of :func:`silhouette_crossings` at fraction t
    from the covered pixel's centre, nvdiffrast's coverage rule [Laine et al. 2020]: if
    t > 1/2 the uncovered pixel gains t - 1/2, else the covered one loses 1/2 - t. For a
    straight edge this is continuous as the edge sweeps over pixel centres, and the
    covered area changes by (edge length in pixels) * dx when the edge moves by dx.

    Choice of method (fitting at ~1 cm per pixel): analytic edge antialiasing rather
    than SoftRas soft rasterisation [Liu et al. 2019], because (1) away from the one-pixel
    band an edge crosses, the value is the hard rasterisation, so a fitted silhouette is
    not biased by a blur width (SoftRas' sigma) and matches binary masks; (2) the
    gradient is the exact derivative of that coverage w.r.t. the edge's end points; (3)
    the cost is O(silhouette pixels), not O(pixels x faces), and every value depends on
    two vertices only, which lets the fitting stage build exact Gauss-Newton Jacobians.
    Unlike :func:`antialias` the crossings are found from the silhouette edges (not
    from the covered pixel's own face), so every silhouette pixel of a mesh with faces
    of 1-2 pixels gets its gradient. Limits: no gradient beyond one pixel from an edge;
    a pixel touched by several crossings adds them all (values may leave [0, 1]).
    verts (V, 3) world; edges: :func:`mesh_edges` (computed when not given).
    """
    C, H, W = _check_fragments("silhouette", fragments)
    faces = _check_faces("silhouette", faces)
    dtype = verts.dtype if verts.is_floating_point() else torch.get_default_dtype()
    uv, z = project_vertices(verts, K, world_to_cam)
    cr = silhouette_crossings(uv, z, faces, fragments, edges, depth_tol=depth_tol)
    hard = (fragments.face_id >= 0).to(dtype).reshape(-1)
    if cr.inside.numel() == 0:
        return hard.view(C, H, W)
    V = uv.shape[1]
    uvf = uv.reshape(-1, 2)
    t = crossing_fraction(uvf[cr.cam * V + cr.edge[:, 0]], uvf[cr.cam * V + cr.edge[:, 1]], cr.inside_xy,
                          cr.outside_xy)
    pix = torch.where(t > 0.5, cr.outside, cr.inside)
    return hard.index_add(0, pix, (t - 0.5).to(dtype)).view(C, H, W)


def face_normals_cam(verts: Tensor, faces: Tensor, world_to_cam: Tensor) -> Tensor:
    """Unit camera-space normals of every face in every camera, turned towards the camera.

    verts (V, 3) or (C, V, 3) world, faces (F, 3), world_to_cam (C, 4, 4) -> (C, F, 3),
    OpenCV axes (x right, y down, z forward). A face is seen from the side its normal
    points to: n is negated where ``n . X_centroid > 0`` in camera space (the side the
    camera sees; the convention of :func:`render_mesh`'s two-sided normals and of the
    synthetic normal maps). Differentiable (the flip is piecewise constant).
    """
    faces = _check_faces("face_normals_cam", faces)
    if world_to_cam.ndim not in (2, 3) or world_to_cam.shape[-2:] != (4, 4):
        raise ValueError(f"face_normals_cam: world_to_cam must be (C, 4, 4), got {tuple(world_to_cam.shape)}")
    if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
        raise ValueError(f"face_normals_cam: verts must be (V, 3) or (C, V, 3), got {tuple(verts.shape)}")
    E = world_to_cam.reshape(-1, 4, 4).to(verts.dtype)
    Xc = transform_points(E, verts if verts.ndim == 3 else verts[None].expand(E.shape[0], -1, -1))  # (C, V, 3)
    tri = Xc[:, faces]  # (C, F, 3, 3)
    n = torch.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny ** 0.5)
    with torch.no_grad():
        away = (n * tri.sum(2)).sum(-1) > 0
    return torch.where(away[..., None], -n, n)


def render_face_normals(verts: Tensor, faces: Tensor, world_to_cam: Tensor, fragments: Fragments) -> Tensor:
    """Camera-space normals of the visible faces per pixel: (C, H, W, 3), 0 on background.

    Flat (per face, :func:`face_normals_cam`) normals of ``fragments.face_id``,
    differentiable w.r.t. ``verts`` (V, 3) or (C, V, 3); visibility held fixed.
    """
    faces = _check_faces("render_face_normals", faces)
    C, H, W = _check_fragments("render_face_normals", fragments)
    n = face_normals_cam(verts, faces, world_to_cam)  # (C, F, 3)
    if n.shape[0] != C:
        raise ValueError(f"render_face_normals: {n.shape[0]} cameras but fragments are {(C, H, W)}")
    pix, cam, _, _, f = _foreground(fragments.face_id)
    F = faces.shape[0]
    val = n.reshape(-1, 3)[cam * F + f]
    return n.new_zeros(C * H * W, 3).index_put((pix,), val).view(C, H, W, 3)


@torch.no_grad()
def visible_vertices(verts: Tensor, K: Tensor, world_to_cam: Tensor, fragments: Fragments,
                     depth_tol: float = 0.005) -> Tensor:
    """(C, V) bool: vertices seen in each camera (not hidden by other faces or occluders).

    A vertex is visible when it projects inside the image (z > 0), the pixel nearest
    to its projection shows a face of the mesh (``fragments.face_id >= 0``; pass
    :func:`occlude`-d fragments to account for occluders), and its camera depth exceeds
    that pixel's depth by at most ``depth_tol * z`` (relative tolerance). Vertices on
    grazing silhouettes can fail the test (the depth varies fast across the pixel).
    """
    C, H, W = _check_fragments("visible_vertices", fragments)
    uv, z = project_vertices(verts, K, world_to_cam)  # (C, V, 2), (C, V)
    if uv.shape[0] != C:
        raise ValueError(f"visible_vertices: {uv.shape[0]} cameras but fragments are {(C, H, W)}")
    finite = torch.isfinite(uv).all(-1) & torch.isfinite(z)
    col = torch.where(finite, uv[..., 0], torch.full_like(z, -1.0)).round()
    row = torch.where(finite, uv[..., 1], torch.full_like(z, -1.0)).round()
    inside = finite & (z > 0) & (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1)
    ci = col.clamp(0, W - 1).long()
    ri = row.clamp(0, H - 1).long()
    cam = torch.arange(C, device=uv.device)[:, None].expand_as(ci)
    fid = fragments.face_id[cam, ri, ci]
    d = fragments.depth[cam, ri, ci].to(z.dtype)
    return inside & (fid >= 0) & (z <= d + depth_tol * z.abs())
