"""Tests of anidress_core.rig (SSDR garment rigging model) on tiny synthetic rigs."""
import math
import warnings

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from anidress_core import geometry as g
from anidress_core import rig
from anidress_core.rig import decompose as S


@pytest.fixture(autouse=True)
def one_thread():
    # tiny problems: thread start-up dominates, and on a busy machine it is 30x slower
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def tube(nr=20, nh=15, dtype=torch.float64):
    th = torch.arange(nr, dtype=dtype) * 2 * math.pi / nr
    z = torch.linspace(0, 1.5, nh, dtype=dtype)
    Z, TH = torch.meshgrid(z, th, indexing="ij")
    r = 0.3 + 0.1 * Z
    rest = torch.stack([r * torch.cos(TH), r * torch.sin(TH), Z], -1).reshape(-1, 3)
    f = []
    for i in range(nh - 1):
        for j in range(nr):
            a, b = i * nr + j, i * nr + (j + 1) % nr
            c, d = (i + 1) * nr + j, (i + 1) * nr + (j + 1) % nr
            f += [[a, b, d], [a, d, c]]
    return rest, torch.tensor(f)


def known_rig(T=20, B=4, seed=0, dtype=torch.float64):
    """300-vertex tube, B bones along its axis with smooth (squared hat) weights."""
    gen = torch.Generator().manual_seed(seed)
    rest, faces = tube(dtype=dtype)
    centres = torch.linspace(0.0, 1.5, B, dtype=dtype)
    W = (1 - (rest[:, 2:3] - centres[None]).abs() / (1.5 / (B - 1))).clamp_min(0) ** 2
    W = W / W.sum(-1, keepdim=True)
    aa = (torch.rand(T, B, 3, generator=gen, dtype=dtype) - 0.5) * 2.0
    t = torch.rand(T, B, 3, generator=gen, dtype=dtype) - 0.5
    M = g.make_transform(g.axis_angle_to_matrix(aa), t)
    return rest, faces, W, M, g.lbs(rest, W, M)


def _check_weights(W, nnz):
    assert torch.isfinite(W).all()
    assert (W >= 0).all()
    assert torch.allclose(W.sum(-1), torch.ones_like(W[:, 0]), atol=1e-5)
    assert ((W > 0).sum(-1) <= nnz).all()


def _match(M_true, M_est):
    """Hungarian matching of bones by transform distance -> permutation of estimated bones."""
    cost = ((M_true[:, :, None] - M_est[:, None]) ** 2).sum((0, 3, 4))
    r, c = linear_sum_assignment(cost.double().numpy())
    return torch.as_tensor(c[np.argsort(r)])


def test_recovers_known_rig_float64():
    rest, faces, W, M, X = known_rig()
    model = rig.ssdr(rest, X, faces, num_bones=4, iters=500, smooth=0.0)
    assert model.num_bones == 4
    assert model.transforms.shape == (20, 4, 4, 4) and model.weights.shape == (300, 4)
    _check_weights(model.weights, 8)
    # the alternation converges linearly (~x5 per 50 iterations here): 500 iterations reach
    # ~1e-9 m on this 1.5 m tube (from 0.19 m after the initialisation)
    assert model.rmse < 3e-9
    assert model.history[-1] < model.history[0]
    perm = _match(M, model.transforms)
    assert (model.transforms[:, perm] - M).abs().max() < 1e-7
    assert (model.weights[:, perm] - W).abs().max() < 1e-7
    rec = rig.reconstruct(model)
    assert abs(rig.rmse(rec, X) - model.rmse) < 1e-12
    assert torch.allclose(rig.reconstruct(model.rest, model.weights, model.transforms), rec)


def test_float32_runs_and_decreases():
    rest, faces, W, M, X = known_rig(dtype=torch.float32)
    model = rig.ssdr(rest, X, faces, num_bones=4, iters=20)
    assert model.weights.dtype == torch.float32 and model.transforms.dtype == torch.float32
    _check_weights(model.weights, 8)
    assert math.isfinite(model.rmse) and model.history[-1] < model.history[0]
    R = model.transforms[..., :3, :3]
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-4)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:2]), atol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fit_transforms_recovers_known(dtype):
    rest, faces, W, M, X = known_rig(dtype=dtype)
    model = rig.RigModel(rest=rest, weights=W, transforms=M[:1], bone_centres=rest[:4], rmse=0.0)
    est = rig.fit_transforms(model, X, iters=30)
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert (est - M).abs().max() < tol


def test_nnz_limit_and_convexity():
    rest, faces, W, M, X = known_rig(B=6, T=10)
    model = rig.ssdr(rest, X, faces, num_bones=6, iters=5, nnz=2)
    _check_weights(model.weights, 2)
    assert model.bone_centres.shape == (model.num_bones, 3)


def test_static_sequence_is_exact():
    rest, faces = tube()
    X = rest.expand(5, -1, -1).clone()
    with pytest.warns(UserWarning):
        model = rig.ssdr(rest, X, faces, num_bones=5, iters=3)
    assert model.rmse < 1e-12
    eye = torch.eye(4, dtype=rest.dtype)
    assert torch.allclose(model.transforms, eye.expand_as(model.transforms), atol=1e-10)


def test_rigid_sequence_one_bone_exact():
    rest, faces = tube()
    gen = torch.Generator().manual_seed(1)
    R = g.axis_angle_to_matrix(torch.randn(6, 3, generator=gen, dtype=rest.dtype))
    X = rest @ R.transpose(-1, -2) + torch.randn(6, 1, 3, generator=gen, dtype=rest.dtype)
    with pytest.warns(UserWarning):
        model = rig.ssdr(rest, X, None, num_bones=8, iters=3)
    assert model.rmse < 1e-10


def test_degenerate_inputs_are_finite():
    rest, faces, W, M, X = known_rig(T=5)
    # more bones than distinct motions, duplicated vertices
    rest2 = torch.cat([rest, rest[:50]])
    X2 = torch.cat([X, X[:, :50]], 1)
    for r, x, f, nb in [(rest, X, faces, 12), (rest2, X2, None, 6)]:
        with warnings.catch_warnings():  # may or may not use all bones
            warnings.simplefilter("ignore")
            model = rig.ssdr(r, x, f, num_bones=nb, iters=3)
        assert torch.isfinite(model.transforms).all() and math.isfinite(model.rmse)
        _check_weights(model.weights, 8)
    # collinear points (and B > V: clamped with a warning)
    line = torch.stack([torch.linspace(0, 1, 4, dtype=torch.float64)] + [torch.zeros(4, dtype=torch.float64)] * 2, -1)
    Xl = line @ g.axis_angle_to_matrix(torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)).T
    with pytest.warns(UserWarning):
        model = rig.ssdr(line, Xl[None].repeat(3, 1, 1), None, num_bones=6, iters=3)
    assert torch.isfinite(model.transforms).all() and model.rmse < 1e-6


def test_errors():
    rest, faces, W, M, X = known_rig(T=3)
    bad = X.clone()
    bad[1, 7, 2] = float("nan")
    with pytest.raises(ValueError, match="frames contains NaN"):
        rig.ssdr(rest, bad, faces, num_bones=2, iters=1)
    with pytest.raises(ValueError, match="T = 0"):
        rig.ssdr(rest, X[:0], faces, num_bones=2)
    with pytest.raises(ValueError, match=r"\(T, V, 3\)"):
        rig.ssdr(rest, X[:, :10], faces, num_bones=2)


def test_simplex_projection_matches_reference():
    v = torch.randn(50, 6, dtype=torch.float64)
    mask = torch.rand(50, 6) > 0.3
    mask[:, 0] = True
    w = S.simplex_project(v, mask)
    assert torch.allclose(w.sum(-1), torch.ones(50, dtype=torch.float64)) and (w[~mask] == 0).all()
    # reference: the projection is optimal, so no feasible point on a random ray is closer
    for _ in range(20):
        u = S.simplex_project(torch.rand(50, 6, dtype=torch.float64), mask)
        assert (((w - v) ** 2 * mask).sum(-1) <= ((u - v) ** 2 * mask).sum(-1) + 1e-12).all()


def _hard_covariances(n=400, dtype=torch.float64, seed=3):
    """Random 3x3 covariances plus the cases cloth produces: flat (rank 2), collinear
    (rank 1), zero, and reflected."""
    gen = torch.Generator().manual_seed(seed)
    H = torch.randn(n, 3, 3, generator=gen, dtype=dtype)
    q = n // 5
    H[:q, :, 2] *= 1e-7  # flat patch
    H[q:2 * q] = torch.randn(q, 3, 1, generator=gen, dtype=dtype) @ torch.randn(q, 1, 3, generator=gen, dtype=dtype)
    H[2 * q:2 * q + 10] = 0
    H[3 * q:4 * q] = -H[3 * q:4 * q]  # det < 0: the Kabsch sign fix matters
    return H


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kabsch_polar_matches_svd(dtype):
    H = _hard_covariances(dtype=dtype)
    R_svd, R_pol = g.nearest_rotation(H), S.kabsch_polar(H)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    eye = torch.eye(3, dtype=dtype)
    for R in (R_svd, R_pol):
        assert torch.allclose(R @ R.transpose(-1, -2), eye.expand_as(R), atol=10 * tol)
        assert torch.allclose(S.det3(R), torch.ones(R.shape[0], dtype=dtype), atol=10 * tol)
    # both maximise tr(R^T H) (the rotation itself is not unique for rank-deficient H)
    scale = H.abs().amax((-2, -1)).clamp_min(1e-30)
    gap = ((R_svd * H).sum((-2, -1)) - (R_pol * H).sum((-2, -1))) / scale
    assert gap.max() < 100 * tol


def _moments_problem(n=300, seed=4):
    gen = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    S_ = torch.rand(n, generator=gen, dtype=torch.float64) + 0.5
    ybar = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    H = _hard_covariances(n)
    K = torch.zeros(n, 3, 4, dtype=torch.float64)
    U = torch.zeros(n, 4, 4, dtype=torch.float64)
    K[:, :, 3] = S_[:, None] * ybar
    K[:, :, :3] = H + S_[:, None, None] * ybar[:, :, None] * p[:, None, :]
    U[:, 3, 3] = S_
    U[:, :3, 3] = S_[:, None] * p
    U[-5:] = 0  # bones without weight keep their transform
    return K, U, H


def test_procrustes_kernel_matches_torch_reference():
    K, U, H = _moments_problem()
    M_old = torch.randn(K.shape[0], 3, 4, dtype=torch.float64)
    a = S.procrustes(K, U, M_old)
    b = S.procrustes_torch(K, U, M_old, exact=True)
    assert torch.isfinite(a).all()
    assert torch.equal(a[-5:], M_old[-5:])
    scale = H.abs().amax((-2, -1)).clamp_min(1e-30)[:-5]
    gap = ((b[:-5, :, :3] * H[:-5]).sum((-2, -1)) - (a[:-5, :, :3] * H[:-5]).sum((-2, -1))) / scale
    assert gap.max() < 1e-10
    # where the rotation is unique (full rank H) rotation and translation agree
    full = torch.linalg.svdvals(H[:-5])[:, -1] / scale > 1e-3
    assert (a[:-5][full] - b[:-5][full]).abs().max() < 1e-9


def test_bone_sweeps_kernel_matches_torch_reference():
    rest, faces, W, M, X = known_rig(T=6, B=5)
    P, Xn, c, d, s = S.normalise(rest, X)
    D = S.ssdr_data(P, Xn)
    Wp = W.clone()
    Wp[Wp < 0.05] = 0
    Wp = Wp / Wp.sum(-1, keepdim=True)
    gen = torch.Generator().manual_seed(5)
    M0 = torch.eye(3, 4, dtype=torch.float64).expand(6, 5, 3, 4) + 0.01 * torch.randn(6, 5, 3, 4, generator=gen,
                                                                                          dtype=torch.float64)
    for sweeps in (1, 3):
        a = S.update_transforms(D, Wp, M0, sweeps)
        b = S.update_transforms_torch(D, Wp, M0, sweeps)
        assert torch.isfinite(a).all()
        # the kernel sweeps bones in index order, the reference by colour groups: after a full
        # sweep both decrease the same energy; compare energies, not transforms
        e0, ea, eb = (S.energy(D, m, Wp) for m in (M0, a, b))
        assert ea < e0 and eb < e0
        assert abs(ea - eb) <= 0.05 * e0


@pytest.mark.parametrize("k", [1, 3, 8])
def test_simplex_qp_kernel_matches_torch_and_kkt(k):
    gen = torch.Generator().manual_seed(k)
    V = 500
    A = torch.randn(V, k, k, generator=gen, dtype=torch.float64)
    G = A @ A.transpose(1, 2) * 0.1 + 1e-3 * torch.eye(k, dtype=torch.float64)
    h = torch.randn(V, k, generator=gen, dtype=torch.float64)
    w0 = S.simplex_project(torch.rand(V, k, generator=gen, dtype=torch.float64))
    a, b = S.simplex_qp(G, h, w0), S.simplex_qp_torch(G, h, w0)
    _check_weights(a, k)
    assert (a - b).abs().max() < 1e-8
    # KKT on the simplex: gradient components equal on the support, not smaller off it
    g = (G @ a[..., None])[..., 0] - h
    on = a > 1e-12
    mu = -(g * on).sum(-1) / on.sum(-1)
    assert ((g + mu[:, None]).abs() * on).max() < 1e-8
    assert ((g + mu[:, None]) * ~on).min() > -1e-8
    # slow reference for k = 3: the optimum is no worse than a dense grid of the simplex
    if k == 3:
        t = torch.linspace(0, 1, 41, dtype=torch.float64)
        g1, g2 = torch.meshgrid(t, t, indexing="ij")
        m = (g1 + g2) <= 1
        grid = torch.stack([g1[m], g2[m], 1 - g1[m] - g2[m]], -1)  # (Ng, 3)
        og = (torch.einsum("gi,vij,gj->vg", grid, G, grid) - 2 * h @ grid.T).min(-1).values
        oa = (a * (G @ a[..., None])[..., 0]).sum(-1) - 2 * (h * a).sum(-1)
        assert (oa <= og + 1e-12).all()


def test_progress_and_history_rmse_agree():
    rest, faces, W, M, X = known_rig(T=8)
    model = rig.ssdr(rest, X, faces, num_bones=4, iters=6, progress=True)
    assert len(model.history) == 7
    # the history is computed from normal equations; the last entry matches the reconstruction
    assert abs(model.history[-1] - model.rmse) <= 1e-6 + 1e-3 * model.rmse


def test_energy_from_normal_equations_matches_reconstruction():
    rest, faces, W, M, X = known_rig(T=5, B=4)
    P, Xn, c, d, s = S.normalise(rest, X)
    D = S.ssdr_data(P, Xn)
    Mn = M[..., :3, :] + 0.01  # not the exact rig: a non-zero residual
    W2 = W.clone()
    W2[W2 < 0.1] = 0
    W2 = W2 / W2.sum(-1, keepdim=True)
    rec = g.lbs(P, W2, torch.cat([Mn, torch.tensor([0, 0, 0, 1.0], dtype=Mn.dtype).expand(*Mn.shape[:2], 1, 4)], -2))
    assert S.energy(D, Mn, W2) == pytest.approx(float(((rec - Xn) ** 2).sum()), rel=1e-9)
