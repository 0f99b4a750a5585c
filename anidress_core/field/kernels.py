"""Warp kernels of the field's hot paths, on the CPU and on CUDA (NVIDIA Warp, ``import warp``).

Each kernel does what a batched torch function of the field package does, one thread per
sample (or per sample and level), without the (N, L, 8, F)-sized intermediates of the torch
code; the torch functions stay as the references the tests compare with:

* :func:`hash_fwd`, :func:`hash_bwd`: the multiresolution hash encoding
  (:func:`anidress_core.field.encoding.hash_encode_torch`) and its gradients with respect to
  the table (scatter-add) and the points (the trilinear derivative);
* :func:`warp_place`: the backward warp's blend of the joints' proposals and its fixed-point
  iterations without gradients (:func:`anidress_core.field.deform.backward_warp`), which
  place the point the last, differentiable iteration starts from.

Kernels are generic in the float type (float32 or float64, as the tensors passed in); Warp
compiles each specialisation once per machine and caches it (``~/.cache/warp``).
"""
from __future__ import annotations

from typing import Any

import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no greeting or "module loaded" lines
wp.config.quiet = True



def device_of(t, what: str) -> tuple[str, object]:
    """(Warp device, stream) of torch tensor ``t``; initialises Warp. ``what`` names the caller in errors."""
    wp.init()
    if t.device.type not in ("cpu", "cuda"):
        raise ValueError(f"{what}: the Warp kernels run on cpu or cuda, not {t.device}")
    if t.device.type == "cpu":
        return "cpu", None
    return f"cuda:{t.device.index or 0}", wp.stream_from_torch(t.device)


def array(t):
    """A Warp view of torch tensor ``t`` (detached, made contiguous)."""
    return wp.from_torch(t.detach().contiguous())


# the spatial hash's primes (instant-ngp), reduced modulo 2^32 as the int32 arithmetic wraps
_P1 = -1640531535  # 2654435761 - 2^32
_P2 = 805459861


@wp.func
def _hash_entry(i: int, j: int, k: int, s: int, dense: int, mask: int) -> int:
    """Table row of grid vertex (i, j, k) of a level with s = r + 1 vertices per axis."""
    if dense == 1:
        return i + j * s + k * s * s
    return ((i & mask) ^ ((j * _P1) & mask) ^ ((k * _P2) & mask)) & mask


_vec8i = wp.types.vector(length=8, dtype=wp.int32)


@wp.func
def _cell(x: Any, r: int) -> int:
    """Cell index of a unit-cube coordinate x (clamped) on a level of r cells."""
    return wp.min(int(wp.floor(wp.clamp(x, type(x)(0.0), type(x)(1.0)) * type(x)(r))), r - 1)


@wp.kernel
def hash_fwd(x: wp.array2d(dtype=Any), table: wp.array2d(dtype=Any), res: wp.array(dtype=wp.int32),
             dense: wp.array(dtype=wp.int32), log2_size: int, want_dx: int, out: wp.array2d(dtype=Any),
             dout: wp.array3d(dtype=Any)):
    """out[n, l F + f] = sum_c w_c table[l T + e_c, f]: one thread per (sample n, level l).

    x (N, 3) in the unit cube (clamped here), table (L T, F) entry-major, res / dense (L,) cells per axis
    and 1 where the level is indexed densely, out (N, L F). With ``want_dx`` also
    dout (N, L F, 3) = d out / d x: the trilinear derivative times r, 0 on an axis where x
    was clamped (the backward pass of x is then sum_j g[n, j] dout[n, j]).
    """
    tid = wp.tid()
    L = res.shape[0]
    F = table.shape[1]
    n = tid // L
    lvl = tid - n * L
    one = type(x[0, 0])(1.0)
    zero = type(x[0, 0])(0.0)
    r = int(res[lvl])
    rf = type(x[0, 0])(r)
    mask = (1 << log2_size) - 1
    base = lvl << log2_size
    s = r + 1
    ix = _cell(x[n, 0], r)
    iy = _cell(x[n, 1], r)
    iz = _cell(x[n, 2], r)
    fx = wp.clamp(x[n, 0], zero, one) * rf - type(x[0, 0])(ix)
    fy = wp.clamp(x[n, 1], zero, one) * rf - type(x[0, 0])(iy)
    fz = wp.clamp(x[n, 2], zero, one) * rf - type(x[0, 0])(iz)
    # d f_a / d x_a: r inside the cube, 0 where clamped
    kx = wp.where(x[n, 0] >= zero and x[n, 0] <= one, rf, zero)
    ky = wp.where(x[n, 1] >= zero and x[n, 1] <= one, rf, zero)
    kz = wp.where(x[n, 2] >= zero and x[n, 2] <= one, rf, zero)
    e = _vec8i()
    for c in range(8):
        e[c] = base + _hash_entry(ix + (c >> 2), iy + ((c >> 1) & 1), iz + (c & 1), s, int(dense[lvl]), mask)
    for f in range(F):
        acc = zero
        gx = zero
        gy = zero
        gz = zero
        for c in range(8):
            dx = c >> 2
            dy = (c >> 1) & 1
            dz = c & 1
            wx = wp.where(dx == 1, fx, one - fx)
            wy = wp.where(dy == 1, fy, one - fy)
            wz = wp.where(dz == 1, fz, one - fz)
            v = table[e[c], f]
            acc = acc + wx * wy * wz * v
            if want_dx == 1:
                gx = gx + wp.where(dx == 1, v, -v) * wy * wz
                gy = gy + wp.where(dy == 1, v, -v) * wx * wz
                gz = gz + wp.where(dz == 1, v, -v) * wx * wy
        out[n, lvl * F + f] = acc
        if want_dx == 1:
            dout[n, lvl * F + f, 0] = gx * kx
            dout[n, lvl * F + f, 1] = gy * ky
            dout[n, lvl * F + f, 2] = gz * kz


@wp.kernel
def hash_bwd(x: wp.array2d(dtype=Any), g: wp.array2d(dtype=Any), res: wp.array(dtype=wp.int32),
             dense: wp.array(dtype=wp.int32), log2_size: int, grad_table: wp.array2d(dtype=Any)):
    """The table gradient of :func:`hash_fwd` for the output gradient g (N, L F):
    grad_table (L T, F) += w_c g, atomically (samples share entries); one thread per (sample, level)."""
    tid = wp.tid()
    L = res.shape[0]
    F = grad_table.shape[1]
    n = tid // L
    lvl = tid - n * L
    one = type(x[0, 0])(1.0)
    zero = type(x[0, 0])(0.0)
    r = int(res[lvl])
    rf = type(x[0, 0])(r)
    mask = (1 << log2_size) - 1
    base = lvl << log2_size
    s = r + 1
    ix = _cell(x[n, 0], r)
    iy = _cell(x[n, 1], r)
    iz = _cell(x[n, 2], r)
    fx = wp.clamp(x[n, 0], zero, one) * rf - type(x[0, 0])(ix)
    fy = wp.clamp(x[n, 1], zero, one) * rf - type(x[0, 0])(iy)
    fz = wp.clamp(x[n, 2], zero, one) * rf - type(x[0, 0])(iz)
    for c in range(8):
        dx = c >> 2
        dy = (c >> 1) & 1
        dz = c & 1
        ent = base + _hash_entry(ix + dx, iy + dy, iz + dz, s, int(dense[lvl]), mask)
        w = wp.where(dx == 1, fx, one - fx) * wp.where(dy == 1, fy, one - fy) * wp.where(dz == 1, fz, one - fz)
        for f in range(F):
            wp.atomic_add(grad_table, ent, f, w * g[n, lvl * F + f])


@wp.func
def _trilinear(vol: wp.array(dtype=Any), chan: int, ux: Any, uy: Any, uz: Any, D: int, H: int, W: int,
               C: int) -> Any:
    """Value of channel ``chan`` of the flat channel-last (D, H, W, C) volume at voxel coordinates (ux, uy, uz)
    (x along W); corners outside the grid read 0 (:func:`anidress_core.field.weights.sample_channels`). Channel-last:
    the candidates of one point read the same cache lines."""
    one = type(ux)(1.0)
    acc = type(ux)(0.0)
    x0 = int(wp.floor(ux))
    y0 = int(wp.floor(uy))
    z0 = int(wp.floor(uz))
    fx = ux - type(ux)(x0)
    fy = uy - type(ux)(y0)
    fz = uz - type(ux)(z0)
    for c in range(8):
        dx = c >> 2
        dy = (c >> 1) & 1
        dz = c & 1
        i = x0 + dx
        j = y0 + dy
        k = z0 + dz
        if i >= 0 and i < W and j >= 0 and j < H and k >= 0 and k < D:
            w = wp.where(dx == 1, fx, one - fx) * wp.where(dy == 1, fy, one - fy) * wp.where(dz == 1, fz, one - fz)
            acc = acc + w * vol[((k * H + j) * W + i) * C + chan]
    return acc


@wp.func
def _apply(T: wp.array2d(dtype=Any), row: int, px: Any, py: Any, pz: Any, a: int) -> Any:
    """Row a of the 3x4 transform T[row] (flattened to 12) applied to (px, py, pz, 1)."""
    return T[row, 4 * a] * px + T[row, 4 * a + 1] * py + T[row, 4 * a + 2] * pz + T[row, 4 * a + 3]


@wp.kernel
def warp_place(x_o: wp.array2d(dtype=Any), frame: wp.array(dtype=wp.int32), cand: wp.array2d(dtype=wp.int16),
               num_joints: int, inv_t: wp.array2d(dtype=Any), fwd_t: wp.array2d(dtype=Any),
               vol: wp.array(dtype=Any), lo: wp.array(dtype=Any), scale: wp.array(dtype=Any), D: int, H: int,
               W: int, C: int, iterations: int, eps: float, tol: float, final: int, x_c: wp.array2d(dtype=Any),
               s_out: wp.array(dtype=Any)):
    """Blend of the candidates' proposals, then ``iterations`` fixed-point steps of forward skinning,
    no gradients: one thread per sample (the torch reference: ``backward_warp`` without its last step).

    x_o (N, 3); frame (N,) row block of the (T K, 12) transform tables (3x4 parts of T_k^-1 and
    T_k); cand (N, M), K = no joint; vol (D H W C,) flat channel-last weights; voxel coordinate
    u = (p - lo) * scale, clamped to [-2, max(D, H, W) + 1] as the torch path. s_out (N,): the
    sum of the candidates' weights where the last step (or the blend) read them, the foreground
    likelihood (before its clamp to 1) of the warp without gradients. With ``final`` 1 (rendering: the last
    step is the warp's final one) a sample whose step moved it less than ``tol`` (metres, max norm) has
    converged and skips the steps that follow but the last; with 0 every sample takes every step.
    """
    n = wp.tid()
    M = cand.shape[1]
    zero = type(x_o[0, 0])(0.0)
    one = type(x_o[0, 0])(1.0)
    e = type(x_o[0, 0])(eps)
    hi = type(x_o[0, 0])(wp.max(wp.max(D, H), W) + 1)
    lo2 = type(x_o[0, 0])(-2.0)
    px = x_o[n, 0]
    py = x_o[n, 1]
    pz = x_o[n, 2]
    fb = int(frame[n]) * num_joints
    # 1. HumanNeRF's blend: proposals T_k^-1 x_o, each weighted by its joint's volume weight there
    s = zero
    cx = zero
    cy = zero
    cz = zero
    for m in range(M):
        k = int(cand[n, m])
        if k < num_joints:
            qx = _apply(inv_t, fb + k, px, py, pz, 0)
            qy = _apply(inv_t, fb + k, px, py, pz, 1)
            qz = _apply(inv_t, fb + k, px, py, pz, 2)
            w = _trilinear(vol, k, wp.clamp((qx - lo[0]) * scale[0], lo2, hi), wp.clamp((qy - lo[1]) * scale[1], lo2, hi),
                           wp.clamp((qz - lo[2]) * scale[2], lo2, hi), D, H, W, C)
            s = s + w
            cx = cx + w * qx
            cy = cy + w * qy
            cz = cz + w * qz
    d = wp.max(s, e)
    cx = cx / d
    cy = cy / d
    cz = cz / d
    # 2. fixed point of x_o = (sum_k w_k(x_c) T_k) x_c: A = sum_k w_k T_k[:3, :] (w normalised)
    done = int(0)
    for it in range(iterations):
        # a converged sample (its last step moved it less than tol) skips the steps before the last one
        if done == 1 and final == 1 and it < iterations - 1:
            continue
        ux = wp.clamp((cx - lo[0]) * scale[0], lo2, hi)
        uy = wp.clamp((cy - lo[1]) * scale[1], lo2, hi)
        uz = wp.clamp((cz - lo[2]) * scale[2], lo2, hi)
        s = zero
        a00 = zero
        a01 = zero
        a02 = zero
        a03 = zero
        a10 = zero
        a11 = zero
        a12 = zero
        a13 = zero
        a20 = zero
        a21 = zero
        a22 = zero
        a23 = zero
        for m in range(M):
            k = int(cand[n, m])
            if k < num_joints:
                w = _trilinear(vol, k, ux, uy, uz, D, H, W, C)
                row = fb + k
                s = s + w
                a00 = a00 + w * fwd_t[row, 0]
                a01 = a01 + w * fwd_t[row, 1]
                a02 = a02 + w * fwd_t[row, 2]
                a03 = a03 + w * fwd_t[row, 3]
                a10 = a10 + w * fwd_t[row, 4]
                a11 = a11 + w * fwd_t[row, 5]
                a12 = a12 + w * fwd_t[row, 6]
                a13 = a13 + w * fwd_t[row, 7]
                a20 = a20 + w * fwd_t[row, 8]
                a21 = a21 + w * fwd_t[row, 9]
                a22 = a22 + w * fwd_t[row, 10]
                a23 = a23 + w * fwd_t[row, 11]
        if s > e:
            # x_c = R^-1 (x_o - t), R^-1 = adj(R) / det(R), with R, t the normalised blend
            r00 = a00 / s
            r01 = a01 / s
            r02 = a02 / s
            r10 = a10 / s
            r11 = a11 / s
            r12 = a12 / s
            r20 = a20 / s
            r21 = a21 / s
            r22 = a22 / s
            bx = px - a03 / s
            by = py - a13 / s
            bz = pz - a23 / s
            c00 = r11 * r22 - r12 * r21
            c01 = r02 * r21 - r01 * r22
            c02 = r01 * r12 - r02 * r11
            c10 = r12 * r20 - r10 * r22
            c11 = r00 * r22 - r02 * r20
            c12 = r02 * r10 - r00 * r12
            c20 = r10 * r21 - r11 * r20
            c21 = r01 * r20 - r00 * r21
            c22 = r00 * r11 - r01 * r10
            det = r00 * c00 + r01 * c10 + r02 * c20
            if wp.abs(det) > type(x_o[0, 0])(1.0e-6):
                nx = (c00 * bx + c01 * by + c02 * bz) / det
                ny = (c10 * bx + c11 * by + c12 * bz) / det
                nz = (c20 * bx + c21 * by + c22 * bz) / det
                if wp.max(wp.max(wp.abs(nx - cx), wp.abs(ny - cy)), wp.abs(nz - cz)) < type(x_o[0, 0])(tol):
                    done = 1
                cx = nx
                cy = ny
                cz = nz
            else:
                done = 1
        else:
            done = 1
    x_c[n, 0] = cx
    x_c[n, 1] = cy
    x_c[n, 2] = cz
    s_out[n] = s


@wp.func
def _trilinear_add(grad: wp.array(dtype=Any), chan: int, ux: Any, uy: Any, uz: Any, D: int, H: int, W: int,
                   C: int, g: Any):
    """grad[chan, corners of u] += corner weight * g (the transpose of :func:`_trilinear`)."""
    one = type(ux)(1.0)
    x0 = int(wp.floor(ux))
    y0 = int(wp.floor(uy))
    z0 = int(wp.floor(uz))
    fx = ux - type(ux)(x0)
    fy = uy - type(ux)(y0)
    fz = uz - type(ux)(z0)
    for c in range(8):
        dx = c >> 2
        dy = (c >> 1) & 1
        dz = c & 1
        i = x0 + dx
        j = y0 + dy
        k = z0 + dz
        if i >= 0 and i < W and j >= 0 and j < H and k >= 0 and k < D:
            w = wp.where(dx == 1, fx, one - fx) * wp.where(dy == 1, fy, one - fy) * wp.where(dz == 1, fz, one - fz)
            wp.atomic_add(grad, ((k * H + j) * W + i) * C + chan, w * g)


@wp.func
def _dot_row(T: wp.array2d(dtype=Any), row: int, cx: Any, cy: Any, cz: Any, lx: Any, ly: Any, lz: Any) -> Any:
    """lambda . (T[row] [c; 1]) for the 3x4 transform T[row] (flattened to 12)."""
    return lx * _apply(T, row, cx, cy, cz, 0) + ly * _apply(T, row, cx, cy, cz, 1) + lz * _apply(T, row, cx, cy, cz, 2)


@wp.kernel
def warp_step(x_o: wp.array2d(dtype=Any), x_bar: wp.array2d(dtype=Any), frame: wp.array(dtype=wp.int32),
              cand: wp.array2d(dtype=wp.int16), num_joints: int, fwd_t: wp.array2d(dtype=Any),
              vol: wp.array(dtype=Any), lo: wp.array(dtype=Any), scale: wp.array(dtype=Any), D: int, H: int, W: int,
              C: int, eps: float, backward: int, g_xc: wp.array2d(dtype=Any), g_s: wp.array(dtype=Any), want_t: int,
              x_c: wp.array2d(dtype=Any), s_out: wp.array(dtype=Any), grad_vol: wp.array(dtype=Any),
              grad_t: wp.array2d(dtype=Any)):
    """The warp's last fixed-point step from x_bar, with its gradient (``backward`` 1); one thread per sample.

    Forward (the torch reference: ``deform._skinning_step``): w_m = W_{c_m}(x_bar), s = sum_m w_m,
    A = sum_m (w_m / s) T_{c_m}[:3, :] = (R | t), x_c = R^-1 (x_o - t) where s > eps and
    |det R| > 1e-6, else x_bar; s_out = s. Backward, for g_xc = dL/dx_c (N, 3) and g_s = dL/ds
    (N,): with lambda = R^-T g_xc, dL/dA = -lambda [x_c; 1]^T, so dL/dwhat_m = -lambda . (T_m x_c),
    dL/dT_m = -what_m lambda [x_c; 1]^T (``want_t``), dL/dw_m = (dL/dwhat_m - sum_k what_k
    dL/dwhat_k) / s + g_s; the volume gradient is the transposed trilinear splat (atomic).
    """
    n = wp.tid()
    M = cand.shape[1]
    zero = type(x_o[0, 0])(0.0)
    e = type(x_o[0, 0])(eps)
    hi = type(x_o[0, 0])(wp.max(wp.max(D, H), W) + 1)
    lo2 = type(x_o[0, 0])(-2.0)
    fb = int(frame[n]) * num_joints
    px = x_o[n, 0]
    py = x_o[n, 1]
    pz = x_o[n, 2]
    ux = wp.clamp((x_bar[n, 0] - lo[0]) * scale[0], lo2, hi)
    uy = wp.clamp((x_bar[n, 1] - lo[1]) * scale[1], lo2, hi)
    uz = wp.clamp((x_bar[n, 2] - lo[2]) * scale[2], lo2, hi)
    s = zero
    a00 = zero
    a01 = zero
    a02 = zero
    a03 = zero
    a10 = zero
    a11 = zero
    a12 = zero
    a13 = zero
    a20 = zero
    a21 = zero
    a22 = zero
    a23 = zero
    for m in range(M):
        k = int(cand[n, m])
        if k < num_joints:
            w = _trilinear(vol, k, ux, uy, uz, D, H, W, C)
            row = fb + k
            s = s + w
            a00 = a00 + w * fwd_t[row, 0]
            a01 = a01 + w * fwd_t[row, 1]
            a02 = a02 + w * fwd_t[row, 2]
            a03 = a03 + w * fwd_t[row, 3]
            a10 = a10 + w * fwd_t[row, 4]
            a11 = a11 + w * fwd_t[row, 5]
            a12 = a12 + w * fwd_t[row, 6]
            a13 = a13 + w * fwd_t[row, 7]
            a20 = a20 + w * fwd_t[row, 8]
            a21 = a21 + w * fwd_t[row, 9]
            a22 = a22 + w * fwd_t[row, 10]
            a23 = a23 + w * fwd_t[row, 11]
    cx = x_bar[n, 0]
    cy = x_bar[n, 1]
    cz = x_bar[n, 2]
    solved = int(0)
    det = zero
    c00 = zero
    c01 = zero
    c02 = zero
    c10 = zero
    c11 = zero
    c12 = zero
    c20 = zero
    c21 = zero
    c22 = zero
    if s > e:
        r00 = a00 / s
        r01 = a01 / s
        r02 = a02 / s
        r10 = a10 / s
        r11 = a11 / s
        r12 = a12 / s
        r20 = a20 / s
        r21 = a21 / s
        r22 = a22 / s
        c00 = r11 * r22 - r12 * r21
        c01 = r02 * r21 - r01 * r22
        c02 = r01 * r12 - r02 * r11
        c10 = r12 * r20 - r10 * r22
        c11 = r00 * r22 - r02 * r20
        c12 = r02 * r10 - r00 * r12
        c20 = r10 * r21 - r11 * r20
        c21 = r01 * r20 - r00 * r21
        c22 = r00 * r11 - r01 * r10
        det = r00 * c00 + r01 * c10 + r02 * c20
        if wp.abs(det) > type(x_o[0, 0])(1.0e-6):
            bx = px - a03 / s
            by = py - a13 / s
            bz = pz - a23 / s
            cx = (c00 * bx + c01 * by + c02 * bz) / det
            cy = (c10 * bx + c11 * by + c12 * bz) / det
            cz = (c20 * bx + c21 * by + c22 * bz) / det
            solved = 1
    if backward == 0:
        x_c[n, 0] = cx
        x_c[n, 1] = cy
        x_c[n, 2] = cz
        s_out[n] = s
        return
    # lambda = R^-T g = adj(R)^T g / det
    lx = zero
    ly = zero
    lz = zero
    if solved == 1:
        gx = g_xc[n, 0]
        gy = g_xc[n, 1]
        gz = g_xc[n, 2]
        lx = (c00 * gx + c10 * gy + c20 * gz) / det
        ly = (c01 * gx + c11 * gy + c21 * gz) / det
        lz = (c02 * gx + c12 * gy + c22 * gz) / det
    # sum_k what_k dL/dwhat_k = -lambda . (A x_c + t) / s... computed as the weighted mean below
    mean = zero
    if solved == 1:
        for m in range(M):
            k = int(cand[n, m])
            if k < num_joints:
                w = _trilinear(vol, k, ux, uy, uz, D, H, W, C)
                mean = mean + (w / s) * (-_dot_row(fwd_t, fb + k, cx, cy, cz, lx, ly, lz))
    gs = g_s[n]
    for m in range(M):
        k = int(cand[n, m])
        if k < num_joints:
            gw = gs
            if solved == 1:
                gw = gw + (-_dot_row(fwd_t, fb + k, cx, cy, cz, lx, ly, lz) - mean) / s
                if want_t == 1:
                    wh = _trilinear(vol, k, ux, uy, uz, D, H, W, C) / s
                    row = fb + k
                    wp.atomic_add(grad_t, row, 0, -wh * lx * cx)
                    wp.atomic_add(grad_t, row, 1, -wh * lx * cy)
                    wp.atomic_add(grad_t, row, 2, -wh * lx * cz)
                    wp.atomic_add(grad_t, row, 3, -wh * lx)
                    wp.atomic_add(grad_t, row, 4, -wh * ly * cx)
                    wp.atomic_add(grad_t, row, 5, -wh * ly * cy)
                    wp.atomic_add(grad_t, row, 6, -wh * ly * cz)
                    wp.atomic_add(grad_t, row, 7, -wh * ly)
                    wp.atomic_add(grad_t, row, 8, -wh * lz * cx)
                    wp.atomic_add(grad_t, row, 9, -wh * lz * cy)
                    wp.atomic_add(grad_t, row, 10, -wh * lz * cz)
                    wp.atomic_add(grad_t, row, 11, -wh * lz)
            _trilinear_add(grad_vol, k, ux, uy, uz, D, H, W, C, gw)


@wp.func
def _ray_span(origins: wp.array2d(dtype=Any), dirs: wp.array2d(dtype=Any), r: int, f: int,
              g_origin: wp.array2d(dtype=Any), g_voxel: wp.array2d(dtype=Any), G: wp.array(dtype=wp.int32)) -> Any:
    """Entry (clamped to 0) and exit of ray r in the grid box of frame f, as a 2-vector of the float type:
    the slab test of the torch path (directions below 1e-12 in magnitude count as +1e-12)."""
    zero = type(origins[0, 0])(0.0)
    tiny = type(origins[0, 0])(1.0e-12)
    tmin = type(origins[0, 0])(-3.0e38)
    tmax = type(origins[0, 0])(3.0e38)
    for a in range(3):
        d = dirs[r, a]
        if wp.abs(d) < tiny:
            d = tiny
        inv = type(origins[0, 0])(1.0) / d
        lo = g_origin[f, a]
        hi = lo + g_voxel[f, a] * type(origins[0, 0])(G[a])
        t0 = (lo - origins[r, a]) * inv
        t1 = (hi - origins[r, a]) * inv
        tmin = wp.max(tmin, wp.min(t0, t1))
        tmax = wp.min(tmax, wp.max(t0, t1))
    return wp.vector(wp.max(tmin, zero), tmax)


@wp.func
def _grid_row(px: Any, py: Any, pz: Any, f: int, g_origin: wp.array2d(dtype=Any), g_voxel: wp.array2d(dtype=Any),
              G: wp.array(dtype=wp.int32), index: wp.array2d(dtype=wp.int32)) -> int:
    """Row of point p of frame f in the occupancy grid's candidate table; -1 outside or empty
    (:meth:`anidress_core.field.sampler.OccupancyGrid.lookup`)."""
    i = int(wp.floor((px - g_origin[f, 0]) / g_voxel[f, 0]))
    j = int(wp.floor((py - g_origin[f, 1]) / g_voxel[f, 1]))
    k = int(wp.floor((pz - g_origin[f, 2]) / g_voxel[f, 2]))
    if i < 0 or j < 0 or k < 0 or i >= int(G[0]) or j >= int(G[1]) or k >= int(G[2]):
        return -1
    return int(index[f, (i * int(G[1]) + j) * int(G[2]) + k])


@wp.kernel
def march_count(origins: wp.array2d(dtype=Any), dirs: wp.array2d(dtype=Any), frame: wp.array(dtype=wp.int32),
                u: wp.array(dtype=Any), step: float, g_origin: wp.array2d(dtype=Any), g_voxel: wp.array2d(dtype=Any),
                G: wp.array(dtype=wp.int32), index: wp.array2d(dtype=wp.int32), fill: int,
                offset: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), considered: wp.array(dtype=wp.int32),
                ray: wp.array(dtype=wp.int64), t_out: wp.array(dtype=Any), row_out: wp.array(dtype=wp.int32)):
    """Ray marching in the occupancy grid (:func:`anidress_core.field.sampler.march`), one thread per ray:
    samples t = entry + (i + u[r]) step while t < exit, kept where the grid is occupied. Pass ``fill`` 0
    counts them (count, considered); pass 1 writes them from ``offset`` (ray, t, row), in depth order."""
    r = wp.tid()
    f = int(frame[r])
    span = _ray_span(origins, dirs, r, f, g_origin, g_voxel, G)
    st = type(origins[0, 0])(step)
    n = int(wp.ceil((span[1] - span[0]) / st))
    kept = int(0)
    seen = int(0)
    pos = int(0)
    if fill == 1:
        pos = int(offset[r])
    for i in range(n):
        t = span[0] + (type(origins[0, 0])(i) + u[r]) * st
        if t < span[1]:
            seen += 1
            row = _grid_row(origins[r, 0] + t * dirs[r, 0], origins[r, 1] + t * dirs[r, 1],
                            origins[r, 2] + t * dirs[r, 2], f, g_origin, g_voxel, G, index)
            if row >= 0:
                if fill == 1:
                    ray[pos + kept] = wp.int64(r)
                    t_out[pos + kept] = t
                    row_out[pos + kept] = row
                kept += 1
    if fill == 0:
        count[r] = kept
        considered[r] = seen
