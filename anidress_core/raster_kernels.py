"""Warp kernel of :func:`anidress_core.raster.rasterize`'s coverage and depth test.

The same half-space rasteriser as the batched torch path (:func:`raster._raster_keys_torch`,
kept as its reference): snapped vertices (1/256 px), integer edge functions evaluated
exactly in float64, the canonical-edge fill rule, 1/z quantised into the high bits of an
int64 key with the face id in the low bits, and a per-pixel minimum of the keys. Only the
evaluation differs: one thread per (camera, face) walks the pixels of its bounding box
(no tiles, no grouping), and ``atomic_min`` does the depth test. The coverage is identical
(the edge functions are exact integers either way); the quantised depth can differ from
the torch path's by a unit in its last place (a different order of floating-point sums),
which changes a winner only between faces closer than ~1e-14 in 1/z.

Measured against the torch path in ``benchmarks/raster.md``.
"""
from __future__ import annotations

import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no greeting or "module loaded" lines

f64 = wp.float64


@wp.kernel
def raster_keys(
    sx: wp.array(dtype=f64),  # (C V,) snapped u, subpixels
    sy: wp.array(dtype=f64),  # (C V,) snapped v
    z: wp.array(dtype=f64),  # (C V,) camera z
    vok: wp.array(dtype=wp.int32),  # (C V,) 1 = finite and in front of the near plane
    faces: wp.array2d(dtype=wp.int32),  # (F, 3)
    front_sign: wp.array(dtype=f64),  # (C,) sign of fx fy
    num_verts: int,
    height: int,
    width: int,
    cull: int,  # 1: drop faces seen from behind
    fbits: int,
    zscale: f64,
    qmax: f64,
    keys: wp.array(dtype=wp.int64),  # (C H W,) in/out: minimum key per pixel
):
    """One thread per face instance (camera c, face f): keys[pixel] = min(keys, (q << fbits) | f)."""
    tid = wp.tid()
    nf = faces.shape[0]
    c = tid // nf
    f = tid - c * nf
    base = c * num_verts
    i0 = base + faces[f, 0]
    i1 = base + faces[f, 1]
    i2 = base + faces[f, 2]
    if vok[i0] == 0 or vok[i1] == 0 or vok[i2] == 0:
        return
    sub = f64(256.0)
    x0 = sx[i0]
    x1 = sx[i1]
    x2 = sx[i2]
    y0 = sy[i0]
    y1 = sy[i1]
    y2 = sy[i2]
    jmin = wp.max(wp.ceil(wp.min(wp.min(x0, x1), x2) / sub), f64(0.0))
    jmax = wp.min(wp.floor(wp.max(wp.max(x0, x1), x2) / sub), f64(width - 1))
    imin = wp.max(wp.ceil(wp.min(wp.min(y0, y1), y2) / sub), f64(0.0))
    imax = wp.min(wp.floor(wp.max(wp.max(y0, y1), y2) / sub), f64(height - 1))
    if jmax < jmin or imax < imin:
        return
    # twice the signed area; with y down and fx, fy > 0 a front face has area2 < 0
    area2 = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    if area2 == f64(0.0):
        return
    if cull == 1 and area2 * front_sign[c] >= f64(0.0):
        return
    sgn = f64(1.0)
    if area2 < f64(0.0):
        sgn = f64(-1.0)
    # edge k runs from corner k+1 to k+2: e_k(P) = -dy Px + dx Py + (dy x_{k+1} - dx y_{k+1});
    # inside <=> sgn e_k + sigma sgn / 2 > 0, sigma = -1 when the canonical direction is reversed
    xs = wp.vec3d(x0, x1, x2)
    ys = wp.vec3d(y0, y1, y2)
    zs = wp.vec3d(z[i0], z[i1], z[i2])
    a = wp.vec3d()
    b = wp.vec3d()
    cc = wp.vec3d()
    ia = f64(0.0)
    ib = f64(0.0)
    ic = qmax
    for k in range(3):
        xa = xs[(k + 1) % 3]
        ya = ys[(k + 1) % 3]
        dx = xs[(k + 2) % 3] - xa
        dy = ys[(k + 2) % 3] - ya
        e0 = dy * xa - dx * ya
        hs = f64(0.5)
        if dx < f64(0.0) or (dx == f64(0.0) and dy < f64(0.0)):
            hs = f64(-0.5)
        a[k] = -sgn * dy
        b[k] = sgn * dx
        cc[k] = sgn * (e0 + hs)
        # q = (1/near - 1/z) zscale is affine in screen space: 1/z = sum_k e_k / (z_k area2)
        g = -zscale / (zs[k] * area2)
        ia = ia - dy * g
        ib = ib + dx * g
        ic = ic + e0 * g
    for i in range(int(imin), int(imax) + 1):
        py = f64(i) * sub
        for j in range(int(jmin), int(jmax) + 1):
            px = f64(j) * sub
            e_0 = a[0] * px + b[0] * py + cc[0]
            e_1 = a[1] * px + b[1] * py + cc[1]
            e_2 = a[2] * px + b[2] * py + cc[2]
            if e_0 > f64(0.0) and e_1 > f64(0.0) and e_2 > f64(0.0):
                q = wp.clamp(ia * px + ib * py + ic, f64(0.0), qmax)
                key = (wp.int64(q) << wp.int64(fbits)) | wp.int64(f)
                wp.atomic_min(keys, (c * height + i) * width + j, key)
