"""Garment rigging model: Smooth Skinning Decomposition with Rigid Bones (SSDR).

One module (over 800 lines): one algorithm whose steps share the SSDRData / _NormalEq moments.

A garment simulated on a moving body, ``frames (T, V, 3)`` over a rest pose
``rest (V, 3)``, is decomposed into B "virtual bones" (Le & Deng 2012, "Smooth
Skinning Decomposition with Rigid Bones"; AniDress uses B = 25 and 50 iterations):

    x[t, i] = sum_b W[i, b] (R[t, b] rest[i] + t[t, b])

with convex per-vertex weights (W >= 0, rows sum to one, at most ``nnz`` non-zeros
per row) and rigid bone transforms ``transforms (T, B, 4, 4)`` that map the rest pose
to frame t (column vectors, no bind matrices) -- the convention of Dem Bones
(Binh Le, EA SEED, ``DemBones.h``), whose defaults this module follows (``init_iters``
10, ``nnz`` 8, ``smooth`` 1e-4, weights energy
``|A_i w - x_i|^2 / (modelSize^2 T) + smooth |w - ws_i|^2``) except for the inner
iteration counts: 2 bone sweeps and 1 weights round per global iteration instead of
Dem Bones' 5 and 3, and an initialisation on at most 50 frames -- measured on simulated
skirts to cost a few hundredths of a millimetre of RMSE for 2-3x less time
(benchmarks/rig.md has both settings).

Both updates work on moments of the data, so that the per-vertex, per-frame work is
two dense matrix products per iteration (the SSDR paper's own formulation):

* bones (Sec. 3.2): with ``p~ = (p, 1)``, the moments ``Q[t, b] = sum_i W_ib x_ti p~_i^T``
  (T, B, 3, 4) and ``U[b, c] = sum_i W_ib W_ic p~_i p~_i^T`` (B, B, 4, 4) give bone b's
  weighted Procrustes problem (point weights W_ib^2, targets the residual without
  bone b) in closed form: ``K = Q[t, b] - sum_{c != b} M[t, c] U[c, b]``; the sweep
  over bones is Gauss-Seidel, batched over every frame and over bones that share no
  vertex (a greedy colouring of the bone overlap graph; for such bones ``U[c, b] = 0``,
  so a colour at once equals the sequential update);
* weights (Sec. 3.3): ``G_i = A_i^T A_i`` (V, B, B) from ``sum_t M_tb^T M_tc`` and
  ``h_i = A_i^T x_i`` (V, B) from one product of the frames with the transforms; each
  vertex then solves a convex QP on at most ``nnz`` candidate bones (the largest
  Laplacian-smoothed weights, then the bones that fit it best alone) by a batched
  active-set method warm-started at the previous weights.

Differences from Dem Bones, on purpose:

* initial clusters are split along the dominant direction of their *residual
  trajectories* (Dem Bones seeds a new cluster at a mesh neighbourhood), so the
  initialisation works without faces; it runs on at most ``init_frames`` frames
  (evenly strided), the iterations then use all frames;
* a vertex's candidate bones include, after the ones its smoothed weights propose,
  the bones that explain its trajectory best alone, so a vertex can gain a bone
  without a mesh;
* the smoothness target is the uniform-Laplacian implicit smoothing
  ``(I + L) ws = W`` (Dem Bones uses edge weights from the edge-length variation),
  solved with a few Jacobi steps; without faces the target is the current weights,
  a proximal term that vanishes at convergence;
* no translation-affinity regulariser (``transAffine``).

Shapes: T frames, V vertices, F faces, B bones. Float32 and float64, CPU and GPU.
The alternation converges linearly (a known property of SSDR); RMSE is not monotone
in the iteration count because of the smoothness term, so compare at a fixed count.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..geometry import edges_of_faces, lbs, make_transform, nearest_rotation

__all__ = ["RigModel", "ssdr", "fit_transforms", "reconstruct", "rmse",
           # the solver's steps, public so that tests compare each Warp kernel with its torch reference
           "SSDRData", "ssdr_data", "normalise", "energy", "det3", "kabsch_polar", "procrustes", "procrustes_torch",
           "update_transforms", "update_transforms_torch", "simplex_project", "simplex_qp", "simplex_qp_torch"]


@dataclass(frozen=True)
class RigModel:
    """A linear-blend-skinning rig of a garment sequence."""

    rest: Tensor
    """(V, 3) rest-pose vertices."""
    weights: Tensor
    """(V, B) convex skinning weights, at most ``nnz`` non-zeros per row (dense storage)."""
    transforms: Tensor
    """(T, B, 4, 4) rigid bone transforms, rest pose -> frame t, column vectors."""
    bone_centres: Tensor
    """(B, 3) rest-pose weighted centroid of each bone's vertices."""
    rmse: float
    """Root mean squared vertex error of the reconstruction over all frames and vertices."""
    history: tuple = ()
    """RMSE after the initialisation, then after every iteration."""

    @property
    def num_bones(self) -> int:
        return int(self.weights.shape[1])

    @property
    def num_frames(self) -> int:
        return int(self.transforms.shape[0])


# --------------------------------------------------------------------------- helpers


def rmse(a: Tensor, b: Tensor) -> float:
    """sqrt(mean over all points of the squared distance); a, b: (..., 3)."""
    if a.shape != b.shape:
        raise ValueError(f"rmse: shapes differ, {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.numel() == 0:
        return 0.0
    return float(((a - b) ** 2).sum(-1).mean().sqrt())


def reconstruct(rig: RigModel | Sequence[Tensor], *args: Tensor) -> Tensor:
    """LBS reconstruction (T, V, 3) of ``rig`` or of ``(rest, weights, transforms)``."""
    if isinstance(rig, RigModel):
        rest, weights, transforms = rig.rest, rig.weights, rig.transforms
    elif args:
        rest, weights, transforms = (rig, *args)
    else:
        rest, weights, transforms = rig
    return lbs(rest, weights, transforms)


def _as_float(x, name: str, device=None, dtype=None) -> Tensor:
    x = torch.as_tensor(x, device=device)
    if dtype is not None:
        x = x.to(dtype)
    elif x.dtype not in (torch.float32, torch.float64):
        if x.is_floating_point():
            raise ValueError(f"{name}: dtype {x.dtype} not supported, use float32 or float64")
        x = x.to(torch.get_default_dtype())
    return x


def _check_finite(x: Tensor, name: str) -> None:
    bad = ~torch.isfinite(x)
    if bad.any():
        idx = bad.nonzero()[0].tolist()
        raise ValueError(f"{name} contains NaN or inf (first at index {tuple(idx)})")


def _eps(dtype) -> float:
    return float(torch.finfo(dtype).eps)


def det3(A: Tensor) -> Tensor:
    """Determinant of (..., 3, 3) by the triple product (cheaper than LU for 3x3)."""
    return (torch.cross(A[..., 0, :], A[..., 1, :], dim=-1) * A[..., 2, :]).sum(-1)


def _homogeneous(P: Tensor) -> Tensor:
    return torch.cat([P, torch.ones_like(P[:, :1])], -1)


def simplex_project(v: Tensor, mask: Tensor | None = None) -> Tensor:
    """Euclidean projection of each row of v (N, B) onto the probability simplex.

    With ``mask`` (N, B) bool, entries outside the mask are forced to zero and the
    projection is onto the simplex of the masked coordinates (every row must have at
    least one masked entry). Duchi et al. 2008, sort-based, batched.
    """
    if mask is None:
        mask = torch.ones_like(v, dtype=torch.bool)
    neg = torch.finfo(v.dtype).min
    u, _ = torch.sort(torch.where(mask, v, torch.full_like(v, neg)), dim=-1, descending=True)
    valid = torch.arange(v.shape[-1], device=v.device)[None] < mask.sum(-1, keepdim=True)
    css = torch.cumsum(torch.where(valid, u, torch.zeros_like(u)), dim=-1)
    k = torch.arange(1, v.shape[-1] + 1, device=v.device, dtype=v.dtype)[None]
    cond = valid & (u * k > css - 1)
    rho = (cond.to(v.dtype) * k).argmax(-1, keepdim=True)  # last index where cond holds
    theta = (css.gather(-1, rho) - 1) / (rho + 1).to(v.dtype)
    return torch.where(mask, (v - theta).clamp_min(0), torch.zeros_like(v))


# --------------------------------------------------------------------------- moments


class SSDRData(NamedTuple):
    """The fixed arrays of a decomposition, laid out once for the two products per iteration.

    P (V, 3) rest, Ph (V, 4) homogeneous rest, X (T, V, 3) frames, Xt (3T, V) and
    Xv (V, 3T) the frames as matrices (rows (t, j) / columns (t, j)): the bone moments are
    Q = Xt A with A = W (x) p~ and the weights' right-hand sides come from Xv M.
    """

    P: Tensor
    Ph: Tensor
    X: Tensor
    Xt: Tensor
    Xv: Tensor


def ssdr_data(P: Tensor, X: Tensor) -> SSDRData:
    """Lay out rest P (V, 3) and frames X (T, V, 3) (normalised, :func:`normalise`) as :class:`SSDRData`."""
    T, V = X.shape[:2]
    Xt = X.transpose(1, 2).reshape(T * 3, V).contiguous()
    Xv = X.permute(1, 0, 2).reshape(V, T * 3).contiguous()
    return SSDRData(P, _homogeneous(P), X, Xt, Xv)


def _xm(D: SSDRData, M: Tensor) -> Tensor:
    """sum_t x_ti . M_tb p~_i for every vertex and bone, (V, B)."""
    T, B = M.shape[:2]
    Mf = M.transpose(1, 2).reshape(T * 3, B * 4)  # Mf[(t, j), (b, k)] = M[t, b, j, k]
    return ((D.Xv @ Mf).reshape(-1, B, 4) * D.Ph[:, None, :]).sum(-1)


def _moments(D: SSDRData, W: Tensor) -> tuple[Tensor, Tensor]:
    """Moments of the bone problem, W (V, B) ->
    Q (T, B, 3, 4): Q[t, b] = sum_i W_ib x_ti p~_i^T, and
    U (B, B, 4, 4): U[b, c] = sum_i W_ib W_ic p~_i p~_i^T.
    """
    T = D.X.shape[0]
    V, B = W.shape
    A = (W[:, :, None] * D.Ph[:, None, :]).reshape(V, 4 * B)  # A[i, (b, k)] = W_ib p~_ik
    Q = (D.Xt @ A).reshape(T, 3, B, 4).transpose(1, 2)  # Q[t, b, j, k] = sum_i x_tij A[i, (b, k)]
    U = (A.T @ A).reshape(B, 4, B, 4).transpose(1, 2)  # U[b, c, k, l]
    return Q, U


def _polar_rotation(H: Tensor, iters: int = 12) -> Tensor:
    """Orthogonal polar factor of H (..., 3, 3) with det H > 0.

    Scaled Newton iteration X <- (z X + X^-T / z) / 2, z = |det X|^(-1/3) (Higham 1986),
    with the 3x3 inverse-transpose from cofactors, all elementwise: converges
    quadratically (~6 iterations in float64) and is an order of magnitude faster than a
    batched 3x3 SVD on the CPU.
    """
    X = H / H.abs().amax((-2, -1), keepdim=True).clamp_min(torch.finfo(H.dtype).tiny)
    tol = 10 * _eps(H.dtype)
    for _ in range(iters):
        C = _cofactor(X)
        det = (X[..., 0, :] * C[..., 0, :]).sum(-1)  # X^-T = C / det
        z = det.abs().clamp_min(torch.finfo(H.dtype).tiny) ** (-1.0 / 3.0)
        Xn = 0.5 * (z[..., None, None] * X + C / (z * det)[..., None, None])
        delta = float((Xn - X).abs().amax()) if Xn.numel() else 0.0
        X = Xn
        if delta < tol:
            break
    return X


def _cofactor(X: Tensor) -> Tensor:
    """Cofactor matrix (..., 3, 3) of X: rows are cross products of X's rows (= det X X^-T)."""
    r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    return torch.stack([torch.cross(r1, r2, dim=-1), torch.cross(r2, r0, dim=-1), torch.cross(r0, r1, dim=-1)], -2)


def kabsch_polar(H: Tensor) -> Tensor:
    """Rotation maximising tr(R^T H) (Kabsch, det R = +1) without a batched SVD.

    With H = U S V^T and d = det(U V^T), the cofactor matrix is
    cof(H) = d U diag(s2 s3, s1 s3, s1 s2) V^T, so H + cof(H) (H scaled to unit max
    entry) = U diag(s1 + d s2 s3, s2 + d s1 s3, s3 + d s1 s2) V^T: for a nearly flat
    covariance (a patch of cloth: s3 ~ 0) or a weak reflection its polar factor is
    U diag(1, 1, d) V^T, the Kabsch rotation, and for det H > 0 it is U V^T as for H
    itself. The polar factor comes from :func:`_polar_rotation`; clear reflections
    (det < -1e-3 after scaling, rare) and anything that does not come out a rotation go
    to :func:`anidress_core.geometry.nearest_rotation` (SVD).
    """
    Hn = H / H.abs().amax((-2, -1), keepdim=True).clamp_min(torch.finfo(H.dtype).tiny)
    det = det3(Hn)
    easy = det > -1e-3
    eye = torch.eye(3, dtype=H.dtype, device=H.device)
    R = _polar_rotation(torch.where(easy[..., None, None], Hn + _cofactor(Hn), eye))
    ok = easy & torch.isfinite(R).all(-1).all(-1) & (det3(R) > 0.5)
    if not bool(ok.all()):
        R = R.clone()
        R[~ok] = nearest_rotation(Hn[~ok])
    return R


def procrustes_torch(K: Tensor, Ubb: Tensor, M_old: Tensor, exact: bool = False) -> Tensor:
    """Weighted rigid fit from moments in torch (reference for :func:`procrustes`).

    K (..., 3, 4) = [sum a_i y_i p_i^T | sum a_i y_i], Ubb (..., 4, 4) = sum a_i p~_i p~_i^T.
    Returns (..., 3, 4) [R | t] minimising sum_i a_i |R p_i + t - y_i|^2 with det R = +1.
    ``exact``: every rotation by SVD; otherwise by :func:`kabsch_polar`. Where the bone has
    no weight (sum a_i = 0) ``M_old`` is kept; rank-deficient covariances (collinear or
    single points) still give a rotation.
    """
    S = Ubb[..., 3, 3]
    ok = S > torch.finfo(K.dtype).tiny * 1e6
    Ss = torch.where(ok, S, torch.ones_like(S))[..., None]
    pbar = Ubb[..., :3, 3] / Ss  # (..., 3)
    ybar = K[..., :, 3] / Ss
    # 1. centred covariance sum a (y - ybar)(p - pbar)^T = sum a y p^T - S ybar pbar^T
    cov = K[..., :, :3] - Ss[..., None] * ybar[..., :, None] * pbar[..., None, :]
    # 2. rotation maximising tr(R^T cov) with det R = +1
    R = nearest_rotation(cov) if exact else kabsch_polar(cov)
    # 3. t = ybar - R pbar
    t = ybar - (R @ pbar[..., None])[..., 0]
    Mn = torch.cat([R, t[..., None]], -1)
    good = ok[..., None, None] & torch.isfinite(Mn).all(-1, keepdim=True).all(-2, keepdim=True)
    return torch.where(good, Mn, M_old)


def procrustes(K: Tensor, Ubb: Tensor, M_old: Tensor) -> Tensor:
    """Weighted rigid fit from moments (SSDR Sec. 3.2; the 4x4 form of Dem Bones' qpT2m).

    Same contract as :func:`procrustes_torch`, computed by the Warp kernel
    :func:`anidress_core.rig.kernels.procrustes` (one thread per matrix, float64): the
    bone update calls this once per colour and sweep on a few hundred 3x3 problems, where
    a chain of ~150 small torch operations cost ~5x more than the compiled kernel
    (measured on the 3K-vertex skirt, benchmarks/rig.md).
    """
    import warp as wp

    from . import kernels

    shape = K.shape[:-2]
    n = int(np.prod(shape)) if len(shape) else 1
    if n == 0:
        return M_old.clone()
    k64 = K.reshape(n, 3, 4).to(torch.float64).contiguous()
    u64 = Ubb.expand(*shape, 4, 4).reshape(n, 4, 4).to(torch.float64).contiguous()
    m64 = M_old.expand(*shape, 3, 4).reshape(n, 3, 4).to(torch.float64).contiguous()
    out = torch.empty_like(m64)
    wp.init()
    dev = "cpu" if K.device.type == "cpu" else str(K.device)
    wp.launch(kernels.procrustes, n, inputs=[wp.from_torch(k64), wp.from_torch(u64), wp.from_torch(m64),
                                             wp.from_torch(out)], device=dev)
    return out.to(K.dtype).reshape(*shape, 3, 4)


def _bone_colours(W: Tensor) -> list[Tensor]:
    """Greedy colouring of the bone overlap graph: bones in one colour share no vertex."""
    nz = (W > 0).to(W.dtype)
    overlap = ((nz.T @ nz) > 0).cpu().numpy()
    nb = overlap.shape[0]
    colour = np.full(nb, -1)
    for b in np.argsort(-overlap.sum(1), kind="stable"):
        used = set(colour[overlap[b] & (colour >= 0)].tolist())
        c = 0
        while c in used:
            c += 1
        colour[b] = c
    return [torch.as_tensor(np.nonzero(colour == c)[0], device=W.device) for c in range(colour.max() + 1)]


def update_transforms(D: SSDRData, W: Tensor, M: Tensor, sweeps: int) -> Tensor:
    """SSDR bone update (Le & Deng 2012, Sec. 3.2): ``sweeps`` Gauss-Seidel sweeps over the bones.

    W (V,B), M (T,B,3,4) -> updated M. The moments Q (T,B,3,4), U (B,B,4,4) come from two
    matrix products (:func:`_moments`); the sweeps run in one Warp launch
    (:func:`anidress_core.rig.kernels.bone_sweeps`, a thread per frame, the bones in
    order as Dem Bones does), which replaces ~15 colour groups x ~150 small torch
    operations per sweep of :func:`update_transforms_torch` (same result up to rounding).
    """
    import warp as wp

    from . import kernels

    T, B = M.shape[:2]
    if T == 0 or B == 0 or sweeps <= 0:
        return M
    Q, U = _moments(D, W)
    # bones sharing a vertex with b (U[c, b] != 0, c != b), padded neighbour lists
    overlap = (U.abs().amax((-2, -1)) > 0).cpu()
    overlap.fill_diagonal_(False)
    deg = overlap.sum(1)
    nbr = torch.zeros(B, max(1, int(deg.max())), dtype=torch.int32)
    for b in range(B):  # B bones, not a hot loop
        idx = overlap[b].nonzero()[:, 0]
        nbr[b, : idx.numel()] = idx.to(torch.int32)
    dev = M.device
    q44 = torch.zeros(T, B, 4, 4, dtype=torch.float64, device=dev)
    q44[:, :, :3] = Q
    m44 = torch.zeros(T, B, 4, 4, dtype=torch.float64, device=dev)
    m44[:, :, :3] = M
    m44[:, :, 3, 3] = 1
    u64 = U.to(torch.float64).contiguous()
    wp.init()
    wdev = "cpu" if dev.type == "cpu" else str(dev)
    m44w = wp.from_torch(m44, dtype=wp.mat44d)
    wp.launch(kernels.bone_sweeps, T, inputs=[wp.from_torch(q44, dtype=wp.mat44d), wp.from_torch(u64, dtype=wp.mat44d),
                                              wp.from_torch(nbr.to(dev)), wp.from_torch(deg.to(torch.int32).to(dev)),
                                              int(sweeps), m44w], device=wdev)
    return m44[:, :, :3].to(M.dtype)


def update_transforms_torch(D: SSDRData, W: Tensor, M: Tensor, sweeps: int) -> Tensor:
    """SSDR bone update in torch (reference of :func:`update_transforms`), batched over frames and bones.

    W (V,B), M (T,B,3,4) -> updated M. Bone b is fitted to the
    residual target q_ti = x_ti - sum_{c != b} W_ic M_tc p~_i by W_ib (R p_i + t): a
    weighted Procrustes problem with point weights W_ib^2 and targets q_ti / W_ib, whose
    moments are K = Q[t, b] - sum_{c != b} M_tc U[c, b] and U[b, b].
    """
    T, B = M.shape[:2]
    Q, U = _moments(D, W)
    Ucols = U.permute(0, 2, 1, 3).reshape(4 * B, B, 4)  # Ucols[(c, k), b, l] = U[c, b, k, l]
    M = M.clone()
    colours = _bone_colours(W)
    for _ in range(sweeps):
        for g in colours:
            # K[t, b] = Q[t, b] - sum_c M[t, c] U[c, b] + M[t, b] U[b, b]
            MU = M.transpose(1, 2).reshape(T, 3, 4 * B) @ Ucols[:, g].reshape(4 * B, -1)  # (T, 3, G*4)
            MU = MU.reshape(T, 3, g.shape[0], 4).transpose(1, 2)
            Ubb = U[g, g]  # (G, 4, 4)
            K = Q[:, g] - MU + M[:, g] @ Ubb
            M[:, g] = procrustes_torch(K, Ubb.expand(T, -1, -1, -1), M[:, g])
    return M


# --------------------------------------------------------------------------- weights


class _NormalEq(NamedTuple):
    """Normal equations of the weights problem, G_i = A_i^T A_i and h_i = A_i^T x_i, where
    column b of A_i (3T, B) stacks M_tb p~_i over frames; G is kept factored:
    G[i, b, c] = pp[i] . MM[b, c] (never materialised as (V, B, B))."""

    pp: Tensor  # (V, 16) p~_i p~_i^T flattened
    MM: Tensor  # (B, B, 16) MM[b, c, (k, l)] = sum_t sum_j M_tbjk M_tcjl
    h: Tensor  # (V, B)
    diag: Tensor  # (V, B) G[i, b, b]


def _normal_equations(D: SSDRData, M: Tensor) -> _NormalEq:
    """Per-vertex normal equations of the weights problem for transforms M (T, B, 3, 4)."""
    T, B = M.shape[:2]
    V = D.P.shape[0]
    Mf = M.transpose(1, 2).reshape(T * 3, B * 4)  # Mf[(t, j), (b, k)] = M[t, b, j, k]
    MM = (Mf.T @ Mf).reshape(B, 4, B, 4).permute(0, 2, 1, 3).reshape(B, B, 16)
    pp = (D.Ph[:, :, None] * D.Ph[:, None, :]).reshape(V, 16)
    ar = torch.arange(B, device=M.device)
    diag = pp @ MM[ar, ar].T  # (V, B)
    h = _xm(D, M)  # h[i, b] = sum_t x_ti . M_tb p~_i
    return _NormalEq(pp, MM, h, diag)


def _gram(ne: _NormalEq, idx: Tensor) -> Tensor:
    """G restricted to each row's bones ``idx`` (V, k) -> (V, k, k)."""
    V, k = idx.shape
    B = ne.MM.shape[0]
    flat = (idx[:, :, None] * B + idx[:, None, :]).reshape(-1)
    MMk = ne.MM.reshape(B * B, 16).index_select(0, flat).reshape(V, k * k, 16)
    return (MMk @ ne.pp[:, :, None]).reshape(V, k, k)


def _neighbour_mean(edges: Tensor | None, V: int, dtype, device) -> Tensor | None:
    """Sparse (V, V) operator D^-1 A of the mesh graph (I - it = uniform Laplacian).

    Rows of vertices without neighbours are zero. None when there are no edges.
    """
    if edges is None or edges.shape[0] == 0:
        return None
    i = torch.cat([edges[:, 0], edges[:, 1]])
    j = torch.cat([edges[:, 1], edges[:, 0]])
    deg = torch.bincount(i, minlength=V).to(dtype)
    vals = 1.0 / deg[i]
    coo = torch.sparse_coo_tensor(torch.stack([i, j]), vals, (V, V), device=device, check_invariants=False)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": used for one product only
        warnings.simplefilter("ignore", UserWarning)
        return coo.coalesce().to_sparse_csr()  # CSR: the fastest sparse @ dense on the CPU


def _smooth_target(W: Tensor, nbr: Tensor | None, steps: int = 10) -> Tensor:
    """ws = (I + L)^-1 W with the uniform Laplacian L = I - D^-1 A (Jacobi iterations).

    Convex rows stay convex (each step averages convex rows); isolated vertices keep
    their weights. No mesh: ws = W.
    """
    if nbr is None:
        return W
    has = (nbr @ torch.ones_like(W[:, :1])) > 0.5
    ws = W
    for _ in range(steps):
        # (I + L) ws = W  <=>  2 ws - D^-1 A ws = W  <=>  ws = (W + mean_neighbours(ws)) / 2
        ws = torch.where(has, 0.5 * (W + nbr @ ws), W)
    return ws


def _candidates(ws: Tensor, ne: _NormalEq, k: int) -> Tensor:
    """(V, k) candidate bones per vertex.

    First the bones with positive smoothed weight ``ws`` (largest first, as Dem Bones),
    then the bones whose single-bone fit error ``G_bb - 2 h_b`` is smallest.
    """
    e = ne.diag - 2 * ne.h  # (V, B) single-bone error (up to a constant)
    lo, hi = e.amin(-1, keepdim=True), e.amax(-1, keepdim=True)
    fit = (hi - e) / (hi - lo).clamp_min(torch.finfo(e.dtype).tiny)  # 1 best .. 0 worst
    pos = ws > 1e-12
    score = torch.where(pos, 2.0 + ws, 0.5 * fit)
    return score.topk(k, dim=-1).indices


def _solve_on_free(G: Tensor, h: Tensor, free: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Equality-constrained QP on the free set: min w^T G w - 2 h^T w, sum w = 1, w = 0 off ``free``.

    G (n, k, k) SPD, h (n, k), free (n, k) bool (>= 1 per row). KKT: G w = h - mu 1, so
    w = G^-1 h - mu G^-1 1 with mu fixing the sum. Returns w (n, k), mu (n,), ok (n,).
    """
    f = free.to(G.dtype)
    Gs = G * f[:, :, None] * f[:, None, :] + torch.diag_embed(1 - f)
    L, info = torch.linalg.cholesky_ex(Gs)
    sol = torch.cholesky_solve(torch.stack([h * f, f], -1), L)
    u, v = sol[..., 0] * f, sol[..., 1] * f
    den = v.sum(-1)
    ok = (info == 0) & (den > 0)
    mu = (u.sum(-1) - 1) / torch.where(ok, den, torch.ones_like(den))
    w = (u - mu[:, None] * v) * f
    ok = ok & torch.isfinite(w).all(-1)
    return w, mu, ok


def simplex_qp(G: Tensor, h: Tensor, w0: Tensor, max_iters: int | None = None) -> Tensor:
    """min_w w^T G w - 2 h^T w  s.t. w >= 0, sum w = 1 per row; G (N, k, k) SPD, h (N, k), start w0 (N, k)
    -> w (N, k). The Warp kernel
    :func:`anidress_core.rig.kernels.simplex_qp` (one thread per vertex, float64) for up to
    16 candidate bones, else :func:`simplex_qp_torch`. Same algorithm; the kernel avoids
    the ~100 small batched torch operations of the reference (measured ~4x faster on
    3K vertices, benchmarks/rig.md)."""
    from . import kernels

    N, k = h.shape
    if k > kernels.KMAX or N == 0:
        return simplex_qp_torch(G, h, w0, max_iters)
    import warp as wp

    g64 = G.to(torch.float64).contiguous()
    h64 = h.to(torch.float64).contiguous()
    w64 = simplex_project(w0).to(torch.float64).contiguous()
    out = torch.empty_like(w64)
    wp.init()
    dev = "cpu" if G.device.type == "cpu" else str(G.device)
    tol = 1e2 * _eps(G.dtype)
    wp.launch(kernels.simplex_qp, N, inputs=[wp.from_torch(g64), wp.from_torch(h64), wp.from_torch(w64),
                                             int(max_iters or 2 * k + 2), float(tol), wp.from_torch(out)], device=dev)
    return out.to(G.dtype)


def simplex_qp_torch(G: Tensor, h: Tensor, w0: Tensor, max_iters: int | None = None) -> Tensor:
    """min_w w^T G w - 2 h^T w  s.t. w >= 0, sum w = 1, batched over rows; G (N, k, k) SPD, h (N, k),
    w0 (N, k) -> w (N, k).

    Primal-dual active set, warm-started at the support of ``w0`` (after one SSDR
    iteration the support rarely changes, so most rows finish after one Cholesky solve):
    solve on the free set; where a free weight is negative drop the most negative one,
    else where a fixed-at-zero weight has a negative KKT multiplier
    ``(G w - h)_j + mu`` add the most violating one; rows that satisfy KKT stop. Rows still
    unfinished after ``max_iters`` rounds (cycling, rare) keep their best feasible point.
    The result is never worse than ``w0`` projected onto the simplex.
    """
    N, k = h.shape
    dtype = G.dtype
    tiny = torch.finfo(dtype).tiny
    diag = torch.diagonal(G, dim1=-2, dim2=-1)
    G = G + (1e3 * _eps(dtype) * diag.mean(-1).clamp_min(tiny))[:, None, None] * torch.eye(k, dtype=dtype,
                                                                                         device=G.device)
    tol = 1e2 * _eps(dtype)
    max_iters = max_iters or 2 * k + 2

    def obj(w, Gm, hm):
        return (w * (Gm @ w[..., None])[..., 0]).sum(-1) - 2 * (hm * w).sum(-1)

    w0 = simplex_project(w0)
    free = w0 > 0
    w = w0.clone()
    rows = torch.arange(N, device=G.device)
    for _ in range(max_iters):
        if rows.numel() == 0:
            break
        Gr, hr, fr = G[rows], h[rows], free[rows]
        wr, mu, ok = _solve_on_free(Gr, hr, fr)
        neg = fr & (wr < -tol)
        lam = (Gr @ wr[..., None])[..., 0] - hr + mu[:, None]  # KKT multipliers of the zero weights
        viol = ~fr & (lam < -tol * (1 + hr.abs()))
        has_neg, has_viol = neg.any(-1), viol.any(-1)
        done = ok & ~has_neg & ~has_viol
        feasible = ok & ~has_neg
        w[rows[feasible]] = wr[feasible].clamp_min(0)
        # next free sets: drop the most negative weight, or add the most violating bone
        drop = ok & has_neg
        add = ok & ~has_neg & has_viol
        j_drop = torch.where(neg, wr, torch.zeros_like(wr)).argmin(-1)
        j_add = torch.where(viol, lam, torch.zeros_like(lam)).argmin(-1)
        fr = fr.clone()
        fr[drop, j_drop[drop]] = False
        fr[add, j_add[add]] = True
        free[rows] = fr
        nxt = ~done & ok & (fr.sum(-1) > 0)
        rows = rows[nxt]
    w = w / w.sum(-1, keepdim=True).clamp_min(tiny)
    better0 = obj(w0, G, h) < obj(w, G, h)
    return torch.where(better0[:, None], w0, w)


def _update_weights(D: SSDRData, M, W, nbr, nnz, smooth, iters) -> tuple[Tensor, float]:
    """SSDR weights update (Le & Deng 2012, Sec. 3.3) with Dem Bones' regularisation.

    Per vertex: min |A_i w - x_i|^2 / T + smooth |w - ws_i|^2 on the simplex with at most
    nnz non-zeros (coordinates are normalised to unit model size, so T is Dem Bones'
    ``reg_scale = modelSize^2 nF``). Returns the weights and sum_i |A_i w_i - x_i|^2 - |x_i|^2
    for them (the reconstruction energy up to the constant sum |x|^2, float64).
    """
    T, B = D.X.shape[0], W.shape[1]
    ne = _normal_equations(D, M)
    k = min(nnz, B)
    eyek = torch.eye(k, dtype=W.dtype, device=W.device)
    e = 0.0
    for _ in range(iters):
        ws = _smooth_target(W, nbr)
        idx = _candidates(ws, ne, k)  # (V, k)
        Gk = _gram(ne, idx)  # (V, k, k), unnormalised
        hk = ne.h.gather(1, idx)
        wk = simplex_qp(Gk / T + smooth * eyek, hk / T + smooth * ws.gather(1, idx), W.gather(1, idx))
        W = torch.zeros_like(W).scatter_(1, idx, wk)
        e = float(((wk * (Gk @ wk[..., None])[..., 0]).sum(-1) - 2 * (hk * wk).sum(-1)).double().sum())
    return W, e


def energy(D: SSDRData, M: Tensor, W: Tensor) -> float:
    """sum_i |A_i w_i - x_i|^2 for transforms M (T, B, 3, 4) and weights W (V, B), from the normal equations
    (float64 sum; in float32 the cancellation against sum |x|^2 leaves ~0.1 % of the
    residual energy, fine for the iteration history; the final RMSE is measured on the
    reconstruction)."""
    ne = _normal_equations(D, M)
    k = max(1, int((W > 0).sum(-1).max()))
    wk, idx = W.topk(k, dim=-1)
    Gk = _gram(ne, idx)
    e = (wk * (Gk @ wk[..., None])[..., 0]).sum(-1) - 2 * (ne.h.gather(1, idx) * wk).sum(-1)
    return float(e.double().sum() + (D.X * D.X).double().sum())


# --------------------------------------------------------------------------- initialisation


def _label_transforms(D: SSDRData, labels: Tensor, nb: int) -> Tensor:
    """Per-cluster, per-frame Kabsch: labels (V,) -> (T, nb, 3, 4)."""
    T, V = D.X.shape[:2]
    W = torch.nn.functional.one_hot(labels, nb).to(D.P.dtype)
    A = (W[:, :, None] * D.Ph[:, None, :]).reshape(V, 4 * nb)
    Q = (D.Xt @ A).reshape(T, 3, nb, 4).transpose(1, 2)  # as in _moments
    pp = (D.Ph[:, :, None] * D.Ph[:, None, :]).reshape(V, 16)
    Ubb = (W.T @ pp).reshape(nb, 4, 4)  # U[b, b] = sum_{i in b} p~ p~^T (one-hot: no cross terms)
    eye = torch.eye(3, 4, dtype=D.P.dtype, device=D.P.device).expand(T, nb, 3, 4)
    return procrustes(Q, Ubb.expand(T, -1, -1, -1), eye)


def _own_bone_error(D: SSDRData, M: Tensor, labels: Tensor) -> Tensor:
    """e[t, i] residual vector x_ti - M_t,label(i) p~_i, (T, V, 3)."""
    Ml = M[:, labels]  # (T, V, 3, 4)
    return D.X - ((Ml[..., :3] @ D.P[:, :, None])[..., 0] + Ml[..., 3])


def _assign_labels(D: SSDRData, M: Tensor) -> Tensor:
    """Label of each vertex = argmin_b sum_t |M_tb p~_i - x_ti|^2, (V,)."""
    cross = _xm(D, M)  # sum_t x_ti . M_tb p~_i
    # sum_t |M_tb p~|^2 = p~^T (sum_t M_tb^T M_tb) p~
    MtM = torch.einsum("tbjk,tbjl->bkl", M, M)  # (B, 4, 4)
    own = torch.einsum("vk,bkl,vl->vb", D.Ph, MtM, D.Ph)
    return (own - 2 * cross).argmin(-1)


def _dominant_split(F: Tensor, gen: torch.Generator) -> Tensor | None:
    """Split rows of F (n, D) by the sign of their projection on the top principal axis."""
    Fc = F - F.mean(0, keepdim=True)
    scale = Fc.abs().max()
    if not torch.isfinite(scale) or scale <= 1e3 * _eps(F.dtype) * (F.abs().max() + 1):
        return None
    Fc = Fc / scale
    v = torch.randn(F.shape[1], generator=gen, dtype=torch.float64).to(F)
    for _ in range(30):  # power iteration on Fc^T Fc
        v = Fc.T @ (Fc @ v)
        n = v.norm()
        if n <= 0:
            return None
        v = v / n
    s = Fc @ v
    side = s > 0
    if side.all() or (~side).all():
        side = s > s.median()
    if side.all() or (~side).all():
        return None
    return side


def _init_clusters(D: SSDRData, num_bones, init_iters, seed) -> tuple[Tensor, int]:
    """(a) Dem Bones-style initialisation: rigid clusters grown by splitting.

    Returns labels (V,) in [0, nb) and nb <= num_bones.
    """
    P, X = D.P, D.X
    V, T = P.shape[0], X.shape[0]
    gen = torch.Generator().manual_seed(seed)
    prune = 3 if V >= 3 * num_bones else 1
    tol = (100 * _eps(P.dtype)) ** 2  # per vertex-frame squared error that counts as exact
    labels = torch.zeros(V, dtype=torch.long, device=P.device)
    nb = 1
    for _round in range(4 * num_bones):
        if nb >= num_bones:
            break
        # a.1 rigid fit of each cluster, residual trajectories and cluster errors
        M = _label_transforms(D, labels, nb)
        res = _own_bone_error(D, M, labels)  # (T, V, 3)
        e = (res * res).sum((0, 2))  # (V,)
        size = torch.bincount(labels, minlength=nb)
        ce = torch.zeros(nb, dtype=P.dtype, device=P.device).index_add_(0, labels, e)
        avg = ce.sum() / nb
        eligible = (size >= 2 * prune) & (ce > avg / 100) & (ce > tol * size * T)
        order = [int(b) for b in torch.argsort(-ce).tolist() if bool(eligible[b])]
        if not order:
            break
        prev = nb
        # a.2 split the clusters with the largest error, along the dominant direction of
        #     their residual trajectories (fallback: rest positions)
        for b in order[: num_bones - nb]:
            idx = (labels == b).nonzero()[:, 0]
            F = res[:, idx].permute(1, 0, 2).reshape(idx.shape[0], -1)
            side = _dominant_split(F, gen)
            if side is None:
                side = _dominant_split(P[idx], gen)
            if side is None:
                continue
            labels[idx[side]] = nb
            nb += 1
        if nb == prev:
            break
        # a.3 alternate rigid fits and re-assignment, pruning clusters that empty out
        for _ in range(init_iters):
            M = _label_transforms(D, labels, nb)
            labels = _assign_labels(D, M)
            size = torch.bincount(labels, minlength=nb)
            keep = size >= prune
            if not keep.all():
                if not keep.any():
                    keep = size == size.max()
                # drop the small clusters; their vertices go to the best remaining bone
                M = M[:, keep]
                nb = int(keep.sum())
                labels = _assign_labels(D, M)
        if nb <= prev:
            break
    size = torch.bincount(labels, minlength=nb)
    if (size == 0).any():
        keep = size > 0
        remap = torch.cumsum(keep.long(), 0) - 1
        labels = remap[labels]
        nb = int(keep.sum())
    return labels, nb


# --------------------------------------------------------------------------- I/O checks, scaling


def _validate(rest, frames, faces):
    rest = _as_float(rest, "rest")
    if rest.ndim != 2 or rest.shape[1] != 3:
        raise ValueError(f"rest must be (V, 3), got {tuple(rest.shape)}")
    frames = _as_float(frames, "frames", device=rest.device, dtype=rest.dtype)
    if frames.ndim != 3 or frames.shape[1:] != rest.shape:
        raise ValueError(f"frames must be (T, V, 3) with V = {rest.shape[0]}, got {tuple(frames.shape)}")
    if frames.shape[0] == 0:
        raise ValueError("frames is empty (T = 0): nothing to decompose")
    if rest.shape[0] == 0:
        raise ValueError("rest has no vertices (V = 0)")
    _check_finite(rest, "rest")
    _check_finite(frames, "frames")
    edges = None
    if faces is not None:
        faces = torch.as_tensor(faces, device=rest.device).long()
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
        if faces.numel() and (faces.min() < 0 or faces.max() >= rest.shape[0]):
            raise ValueError(f"faces index outside [0, {rest.shape[0]})")
        edges = edges_of_faces(faces) if faces.shape[0] else None
    return rest, frames, edges


def normalise(rest: Tensor, frames: Tensor):
    """Centre the rest pose and every frame, scale to unit RMS model size (precision).

    rest (V, 3), frames (T, V, 3) -> (P (V, 3), X (T, V, 3), c (3,), d (T, 3), s ()) with
    P = (rest - c) / s and X[t] = (frames[t] - d[t]) / s.
    """
    c = rest.mean(0)
    d = frames.mean(1)  # (T, 3)
    s = ((rest - c) ** 2).sum(-1).mean().sqrt()
    if not s > 0:
        s = torch.ones((), dtype=rest.dtype, device=rest.device)
    return (rest - c) / s, (frames - d[:, None]) / s, c, d, s


def _denormalise(M: Tensor, c: Tensor, d: Tensor, s: Tensor) -> Tensor:
    """M' maps (p - c)/s to (x - d)/s; return (T, B, 4, 4) mapping p to x."""
    R, t = M[..., :3], M[..., 3]
    # x = s (R (p - c)/s + t') + d = R p + (s t' + d - R c)
    t = s * t + d[:, None] - (R @ c)
    return make_transform(R, t)


# --------------------------------------------------------------------------- public API


def ssdr(
    rest: Tensor,
    frames: Tensor,
    faces: Tensor | None = None,
    num_bones: int = 25,
    iters: int = 50,
    nnz: int = 8,
    smooth: float = 1e-4,
    init_iters: int = 10,
    seed: int = 0,
    trans_iters: int = 2,
    weights_iters: int = 1,
    init_frames: int = 50,
    progress: bool = False,
) -> RigModel:
    """Smooth Skinning Decomposition with Rigid Bones of ``frames (T, V, 3)`` over ``rest (V, 3)``.

    faces (F, 3) or None: with faces the weights are pulled (``smooth``) towards their
    uniform-Laplacian smoothing; without, towards the previous weights (a proximal term,
    no bias at convergence). ``num_bones`` is clamped to V (with a warning); the
    initialisation only splits clusters whose rigid fit is not already exact, and a
    bone whose weights all vanish is dropped, so the returned rig may have fewer bones
    than asked (``rig.num_bones``, a warning says so). Static and rigid sequences
    therefore give one bone with exact identity/rigid transforms.

    Steps: (a) initialisation by cluster splitting (on at most ``init_frames`` frames),
    (b) bone transforms by weighted Procrustes (``trans_iters`` Gauss-Seidel sweeps),
    (c) weights by a batched simplex-constrained least squares (``weights_iters``
    rounds, each a batched active-set solve on the candidate bones);
    (b) and (c) alternate ``iters`` times.
    """
    rest, frames, edges = _validate(rest, frames, faces)
    V, T = rest.shape[0], frames.shape[0]
    if num_bones < 1:
        raise ValueError(f"num_bones must be >= 1, got {num_bones}")
    if nnz < 1:
        raise ValueError(f"nnz must be >= 1, got {nnz}")
    if num_bones > V:
        warnings.warn(f"ssdr: num_bones={num_bones} > V={V}; clamped to {V}", stacklevel=2)
        num_bones = V
    with torch.no_grad():
        P, X, c, d, s = normalise(rest, frames)
        # (a) initialisation: clusters of rigidly moving vertices, one-hot weights
        # (clustering in float64 on a stride of frames, so that float32 and float64
        # inputs start alike)
        stride = max(1, math.ceil(T / max(1, init_frames)))
        labels, nb = _init_clusters(ssdr_data(P.double(), X[::stride].double()), num_bones, init_iters, seed)
        D = ssdr_data(P, X)
        M = _label_transforms(D, labels, nb)
        W = torch.nn.functional.one_hot(labels, nb).to(P.dtype)
        nbr = _neighbour_mean(edges, V, P.dtype, P.device)
        c_all = float((X * X).double().sum())  # sum |x|^2: the energies below are relative to it

        def rmse_of(e: float) -> float:
            return float(s) * math.sqrt(max(e + c_all, 0.0) / (T * V))

        history = [rmse_of(energy(D, M, W) - c_all)]
        it = range(iters)
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc="ssdr", unit="iter")
        for _ in it:
            # (b) bone transforms: weighted Procrustes on residual targets
            M = update_transforms(D, W, M, trans_iters)
            # (c) weights: convex, <= nnz non-zeros, Laplacian smoothness
            W, e = _update_weights(D, M, W, nbr, nnz, smooth, weights_iters)
            # (d) drop bones that lost all their vertices
            alive = W.max(0).values > 0
            if not alive.all():
                W, M = W[:, alive], M[:, alive]
                W = W / W.sum(-1, keepdim=True)
            history.append(rmse_of(e))
            if progress:
                it.set_postfix(rmse_mm=f"{1e3 * history[-1]:.3f}", bones=W.shape[1])
        if W.shape[1] < num_bones:
            warnings.warn(f"ssdr: {W.shape[1]} bones used of the {num_bones} asked "
                          "(fewer distinct motions, or bones dropped)", stacklevel=2)
        transforms = _denormalise(M, c, d, s)
        wsum = W.sum(0).clamp_min(torch.finfo(W.dtype).tiny)
        centres = (W.T @ rest) / wsum[:, None]
        final = rmse(lbs(rest, W, transforms), frames)
    return RigModel(rest=rest, weights=W, transforms=transforms, bone_centres=centres,
                    rmse=final, history=tuple(history))


def fit_transforms(rig: RigModel, verts: Tensor, iters: int = 20) -> Tensor:
    """Bone transforms (T, B, 4, 4) that best explain new meshes ``verts (T, V, 3)``.

    The inverse problem of AniDress Sec. 3.4 (garment poses from mesh fitting): the
    rig's weights are fixed, the transforms are initialised by a per-bone weighted
    Kabsch (point weights W_ib) and refined by ``iters`` Gauss-Seidel sweeps of the SSDR
    bone update (exact weighted Procrustes per bone, in closed form from moments).
    """
    rest = rig.rest
    verts = _as_float(verts, "verts", device=rest.device, dtype=rest.dtype)
    if verts.ndim == 2:
        verts = verts[None]
    if verts.ndim != 3 or verts.shape[1:] != rest.shape:
        raise ValueError(f"verts must be (T, V, 3) with V = {rest.shape[0]}, got {tuple(verts.shape)}")
    _check_finite(verts, "verts")
    if verts.shape[0] == 0:
        return rest.new_zeros(0, rig.num_bones, 4, 4)
    with torch.no_grad():
        P, X, c, d, s = normalise(rest, verts)
        W = rig.weights.to(rest.dtype)
        T, B = X.shape[0], W.shape[1]
        # initial guess: each bone's own weighted Kabsch (point weights W_ib)
        D = ssdr_data(P, X)
        Q, _ = _moments(D, W)
        Uw = torch.einsum("vb,vk,vl->bkl", W, D.Ph, D.Ph)  # sum_i W_ib p~ p~^T
        eye = torch.eye(3, 4, dtype=P.dtype, device=P.device).expand(T, B, 3, 4)
        M = procrustes(Q, Uw.expand(T, -1, -1, -1), eye)
        M = update_transforms(D, W, M, iters)
        return _denormalise(M, c, d, s)
