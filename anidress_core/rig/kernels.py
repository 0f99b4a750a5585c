"""Warp kernel of the SSDR bone update (see :mod:`anidress_core.rig.decompose`).

One thread per (frame, bone): the weighted Procrustes problem of Le & Deng 2012
(Sec. 3.2) from its moments, i.e. the translation from the weighted centroids and the
rotation maximising tr(R^T H) with det R = +1 (Kabsch). The rotation is the polar factor
of H + cof(H) by Higham's scaled Newton iteration (cof(H) = det(H) H^-T turns the
smallest singular value of a flat or weakly reflected covariance into the Kabsch sign,
see ``decompose.kabsch_polar``), with Warp's ``svd3`` (McAdams et al. 2011) where that does
not apply. Float64 throughout.
"""
from __future__ import annotations

import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no greeting or "module loaded" lines

f64 = wp.float64


@wp.func
def _row(X: wp.mat33d, i: int):
    return wp.vec3d(X[i, 0], X[i, 1], X[i, 2])


@wp.func
def _cofactor(X: wp.mat33d):
    r0 = _row(X, 0)
    r1 = _row(X, 1)
    r2 = _row(X, 2)
    c0 = wp.cross(r1, r2)
    c1 = wp.cross(r2, r0)
    c2 = wp.cross(r0, r1)
    return wp.mat33d(c0[0], c0[1], c0[2], c1[0], c1[1], c1[2], c2[0], c2[1], c2[2])


@wp.func
def _maxabs(X: wp.mat33d):
    m = f64(0.0)
    for i in range(3):
        for j in range(3):
            m = wp.max(m, wp.abs(X[i, j]))
    return m


@wp.func
def _kabsch_svd(H: wp.mat33d):
    U = wp.mat33d()
    s = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(H, U, s, V)
    d = wp.determinant(U * wp.transpose(V))
    D = wp.mat33d(f64(1.0), f64(0.0), f64(0.0), f64(0.0), f64(1.0), f64(0.0), f64(0.0), f64(0.0), d)
    return U * D * wp.transpose(V)


@wp.func
def kabsch(H: wp.mat33d):
    """Rotation maximising tr(R^T H), det R = +1: polar factor of H + cof(H) by scaled
    Newton iterations (see decompose.kabsch_polar for why), SVD where that does not apply."""
    m = _maxabs(H)
    if m == f64(0.0):
        return wp.identity(3, dtype=f64)
    Hn = H / m
    R = Hn
    use_svd = wp.determinant(Hn) < f64(-1.0e-3)
    if not use_svd:
        X = Hn + _cofactor(Hn)
        for _it in range(16):
            C = _cofactor(X)
            det = wp.dot(_row(X, 0), _row(C, 0))
            if wp.abs(det) < f64(1.0e-300):
                use_svd = True
                break
            z = wp.pow(wp.abs(det), f64(-1.0) / f64(3.0))
            Xn = f64(0.5) * (z * X + C / (z * det))
            delta = _maxabs(Xn - X)
            X = Xn
            if delta < f64(1.0e-14):
                break
        R = X
        if not (wp.determinant(R) > f64(0.5)) or not wp.isfinite(R):
            use_svd = True
    if use_svd:
        R = _kabsch_svd(Hn)
    return R


@wp.kernel
def procrustes(
    K: wp.array3d(dtype=f64),  # (N, 3, 4) [sum a y p^T | sum a y]
    U: wp.array3d(dtype=f64),  # (N, 4, 4) sum a p~ p~^T
    M_old: wp.array3d(dtype=f64),  # (N, 3, 4) kept where the bone has no weight
    out: wp.array3d(dtype=f64),  # (N, 3, 4) [R | t]
):
    """Weighted rigid fit from moments, one thread per (frame, bone)."""
    n = wp.tid()
    S = U[n, 3, 3]
    keep = True
    if S > f64(1.0e-280):
        pbar = wp.vec3d(U[n, 0, 3], U[n, 1, 3], U[n, 2, 3]) / S
        ybar = wp.vec3d(K[n, 0, 3], K[n, 1, 3], K[n, 2, 3]) / S
        H = wp.mat33d()
        for i in range(3):
            for j in range(3):
                H[i, j] = K[n, i, j] - S * ybar[i] * pbar[j]
        R = kabsch(H)
        t = ybar - R * pbar
        if wp.isfinite(R) and wp.isfinite(t):
            keep = False
            for i in range(3):
                for j in range(3):
                    out[n, i, j] = R[i, j]
                out[n, i, 3] = t[i]
    if keep:
        for i in range(3):
            for j in range(4):
                out[n, i, j] = M_old[n, i, j]


@wp.kernel
def bone_sweeps(
    Q: wp.array2d(dtype=wp.mat44d),  # (T, B) rows 0-2: sum_i W_ib x_ti p~_i^T; row 3: 0
    U: wp.array2d(dtype=wp.mat44d),  # (B, B) sum_i W_ib W_ic p~_i p~_i^T
    nbr: wp.array2d(dtype=wp.int32),  # (B, D) bones sharing a vertex with b (c != b), padded
    nnbr: wp.array(dtype=wp.int32),  # (B,) number of entries of nbr[b]
    sweeps: int,
    M: wp.array2d(dtype=wp.mat44d),  # (T, B) in: current transforms [R t; 0 1], out: updated
):
    """Gauss-Seidel SSDR bone update for one frame (thread t), bones in order, ``sweeps`` times.

    Bone b fits the residual without it: K = Q[t, b] - sum_{c != b} M[t, c] U[c, b]
    (the moments of a weighted Procrustes problem with point weights W_ib^2), solved by
    the weighted centroids + Kabsch rotation. Bones without weight keep their transform.
    """
    t = wp.tid()
    B = Q.shape[1]
    for _s in range(sweeps):
        for b in range(B):
            Ub = U[b, b]
            S = Ub[3, 3]
            if S > f64(1.0e-280):
                # 1. K = Q[t, b] - sum_c M[t, c] U[c, b] (rows 0-2 used)
                K = Q[t, b]
                for q in range(nnbr[b]):
                    c = nbr[b, q]
                    K = K - M[t, c] * U[c, b]
                # 2. centroids and centred covariance
                pbar = wp.vec3d(Ub[0, 3], Ub[1, 3], Ub[2, 3]) / S
                ybar = wp.vec3d(K[0, 3], K[1, 3], K[2, 3]) / S
                H = wp.mat33d()
                for i in range(3):
                    for j in range(3):
                        H[i, j] = K[i, j] - S * ybar[i] * pbar[j]
                # 3. rotation and translation
                R = kabsch(H)
                tr = ybar - R * pbar
                if wp.isfinite(R) and wp.isfinite(tr):
                    M[t, b] = wp.mat44d(R[0, 0], R[0, 1], R[0, 2], tr[0],
                                        R[1, 0], R[1, 1], R[1, 2], tr[1],
                                        R[2, 0], R[2, 1], R[2, 2], tr[2],
                                        f64(0.0), f64(0.0), f64(0.0), f64(1.0))


KMAX = 16  # largest candidate set (nnz) the weights kernel handles; larger goes to torch
vec16d = wp.types.vector(length=KMAX, dtype=f64)
mat16d = wp.types.matrix(shape=(KMAX, KMAX), dtype=f64)


@wp.func
def _qp_obj(G: wp.array3d(dtype=f64), h: wp.array2d(dtype=f64), i: int, w: vec16d, k: int) -> f64:
    e = f64(0.0)
    for a in range(k):
        ga = f64(0.0)
        for b in range(k):
            ga += G[i, a, b] * w[b]
        e += w[a] * ga - f64(2.0) * h[i, a] * w[a]
    return e


@wp.kernel
def simplex_qp(
    G: wp.array3d(dtype=f64),  # (V, k, k) SPD
    h: wp.array2d(dtype=f64),  # (V, k)
    w0: wp.array2d(dtype=f64),  # (V, k) warm start, on the simplex
    max_iters: int,
    tol: f64,
    out: wp.array2d(dtype=f64),  # (V, k)
):
    """min w^T G w - 2 h^T w, w >= 0, sum w = 1, one thread per vertex (primal-dual active set).

    Same algorithm as ``decompose.simplex_qp_torch`` (its batched torch reference): solve the
    equality-constrained problem on the free set (Cholesky), drop the most negative free
    weight, else add the fixed weight with the most negative KKT multiplier, stop when
    neither exists; never worse than the warm start.
    """
    i = wp.tid()
    k = G.shape[1]
    w = vec16d()
    free = vec16d()
    for a in range(k):
        w[a] = w0[i, a]
        if w0[i, a] > f64(0.0):
            free[a] = f64(1.0)
    # ridge relative to the diagonal (as the torch reference)
    dmean = f64(0.0)
    for a in range(k):
        dmean += G[i, a, a]
    dmean = wp.max(dmean / f64(k), f64(1.0e-300))
    ridge = f64(2.220446049250313e-13) * dmean
    for _it in range(max_iters):
        # 1. Cholesky of the free block (identity on fixed rows/cols), two right-hand sides
        L = mat16d()
        ok = bool(True)
        for a in range(k):
            for b in range(a + 1):
                s = f64(0.0)
                if a == b:
                    s = f64(1.0)
                if free[a] > f64(0.0) and free[b] > f64(0.0):
                    s = G[i, a, b]
                    if a == b:
                        s = s + ridge
                for c in range(b):
                    s = s - L[a, c] * L[b, c]
                if a == b:
                    if s <= f64(0.0):
                        ok = False
                        s = f64(1.0)
                    L[a, a] = wp.sqrt(s)
                else:
                    L[a, b] = s / L[b, b]
        if not ok:
            break
        u = vec16d()
        v = vec16d()
        for a in range(k):  # forward
            su = h[i, a] * free[a]
            sv = free[a]
            for c in range(a):
                su = su - L[a, c] * u[c]
                sv = sv - L[a, c] * v[c]
            u[a] = su / L[a, a]
            v[a] = sv / L[a, a]
        for a2 in range(k):  # backward
            a = k - 1 - a2
            su = u[a]
            sv = v[a]
            for c in range(a + 1, k):
                su = su - L[c, a] * u[c]
                sv = sv - L[c, a] * v[c]
            u[a] = su / L[a, a]
            v[a] = sv / L[a, a]
        su = f64(0.0)
        sv = f64(0.0)
        for a in range(k):
            u[a] = u[a] * free[a]
            v[a] = v[a] * free[a]
            su += u[a]
            sv += v[a]
        if not (sv > f64(0.0)):
            break
        mu = (su - f64(1.0)) / sv
        wn = vec16d()
        worst = int(-1)
        worst_v = f64(0.0) - tol
        for a in range(k):
            wn[a] = (u[a] - mu * v[a]) * free[a]
            if free[a] > f64(0.0) and wn[a] < worst_v:
                worst_v = wn[a]
                worst = a
        if not wp.isfinite(wn):
            break
        if worst >= 0:
            free[worst] = f64(0.0)  # 2a. drop the most negative weight
            continue
        for a in range(k):
            w[a] = wp.max(wn[a], f64(0.0))
        # 2b. KKT multipliers of the fixed weights: (G w - h)_j + mu >= 0
        add = int(-1)
        add_v = f64(0.0)
        for a in range(k):
            if free[a] == f64(0.0):
                g = f64(0.0)
                for b in range(k):
                    g += G[i, a, b] * wn[b]
                lam = g - h[i, a] + mu
                if lam < -tol * (f64(1.0) + wp.abs(h[i, a])) and lam < add_v:
                    add_v = lam
                    add = a
        if add < 0:
            break
        free[add] = f64(1.0)
    s = f64(0.0)
    for a in range(k):
        s += w[a]
    if s > f64(0.0):
        for a in range(k):
            w[a] = w[a] / s
    wst = vec16d()
    for a in range(k):
        wst[a] = w0[i, a]
    if _qp_obj(G, h, i, wst, k) < _qp_obj(G, h, i, w, k):
        w = wst
    for a in range(k):
        out[i, a] = w[a]
