"""anidress_core.fit.window: a window of frames fitted jointly, L_flow coupling their poses."""
from __future__ import annotations

import math

import torch

from anidress_core import fit, raster
from anidress_core.fit.window import PairFlow, evaluate_window, pair_flow, window_system
from anidress_core.geometry import lbs
from tests.fit.scenes import PAPER, config, moving, only, pose, render, toy

torch.set_num_threads(1)


def window_scene(cfg, W=3, seed=11):
    """W frames of a cone seen by 3 views: their problems (frame 0 with carried flow targets), random
    coupled targets between consecutive frames, start poses near the truth."""
    rig, views = toy(C=3, H=48, W=48, n_theta=20, n_h=6)
    g = torch.Generator().manual_seed(seed)
    Gt = [pose(rig, g, 0.15, 0.03)]
    Gt += [pose(rig, g, 0.03, 0.01, Gt[-1]) for _ in range(W - 1)]
    frames = [render(rig, views, G) for G in Gt]
    V = rig.rest.shape[0]

    def targets(n):
        c = torch.randint(0, 3, (n,), generator=g)
        v = torch.randint(0, V, (n,), generator=g)
        return c, v, torch.randn(n, 2, generator=g, dtype=torch.float64)

    c, v, e = targets(30)
    uv0, _ = raster.project_vertices(frames[0][1], views.K, views.world_to_cam)
    carried = fit.FlowTargets(c, v, uv0[c, v] + 0.5 * e)
    pbs = [fit.make_problem(rig, views, frames[i][0], cfg, flow=carried if i == 0 else None) for i in range(W)]
    pairs = [None] + [PairFlow(*targets(40)) for _ in range(W - 1)]
    X = torch.stack([pose(rig, g, 0.02, 0.005, G) for G in Gt])
    return rig, views, pbs, pairs, X


def increments(rig, X, d):
    W = X.shape[0]
    return torch.stack([fit.apply_increment(X[i], rig.centres, d.view(W, -1, 6)[i]) for i in range(W)])


def test_window_system_is_the_coupled_flows_gauss_newton_system():
    """L_flow alone (frame 0's carried targets, coupled targets between frames): the window's value is
    r.r and (H, g) = (J^T J, J^T r) of its residuals, J by forward-mode autograd over all W x 6 B
    increments (float64)."""
    cfg = only("flow", 3.0)
    rig, views, pbs, pairs, X = window_scene(cfg)
    wev = evaluate_window(pbs, views, pairs, X)
    H, gvec = window_system(pbs, views, pairs, wev, X)

    def residuals(d):
        x = [lbs(rig.rest, rig.weights, G) for G in increments(rig, X, d)]
        uv = [raster.project_vertices(xi, views.K, views.world_to_cam)[0] for xi in x]
        fl = pbs[0].states["flow"]
        r = [((uv[0][fl.cam, fl.vert] - fl.target) * (3.0 / pbs[0].n_px) ** 0.5).reshape(-1)]
        for i in range(1, len(pbs)):
            p = pairs[i]
            d_i = uv[i][p.cam, p.vert] - uv[i - 1][p.cam, p.vert] - p.flow
            r.append(d_i.reshape(-1) * (3.0 / pbs[i].n_px) ** 0.5)
        return torch.cat(r)

    d0 = torch.zeros(gvec.numel(), dtype=torch.float64)
    r = residuals(d0)
    J = torch.func.jacfwd(residuals)(d0)
    assert abs(float(r @ r) - wev.loss) < 1e-10 * wev.loss
    assert all(p > 0 for p in wev.pair[1:])
    torch.testing.assert_close(H, J.t() @ J, rtol=1e-6, atol=1e-9 * float(H.abs().max()))
    torch.testing.assert_close(gvec, J.t() @ r, rtol=1e-6, atol=1e-9 * float(gvec.abs().max()))
    P = gvec.numel() // 3
    assert float(H[:P, P:2 * P].abs().max()) > 0 and float(H[:P, 2 * P:].abs().max()) == 0  # neighbours only


def test_window_gradient_with_every_image_term():
    """Silhouette, normals, carried and coupled flow: 2 g is the autograd gradient of the sum of the
    frames' reference losses (visibility held fixed) plus the coupled L_flow (float64)."""
    cfg = config(dict(PAPER, normal=300.0))
    rig, views, pbs, pairs, X = window_scene(cfg, seed=12)
    wev = evaluate_window(pbs, views, pairs, X)
    _, gvec = window_system(pbs, views, pairs, wev, X)
    d = torch.zeros(gvec.numel(), dtype=torch.float64, requires_grad=True)
    Xd = increments(rig, X, d)
    total, uvs = 0.0, []
    for i, pb in enumerate(pbs):
        x = lbs(rig.rest, rig.weights, Xd[i])
        t, _ = fit.loss_terms(pb, x, wev.frames[i].fragments)
        total = total + t
        uvs.append(raster.project_vertices(x, views.K, views.world_to_cam)[0])
    for i in range(1, len(pbs)):
        p = pairs[i]
        e = uvs[i][p.cam, p.vert] - uvs[i - 1][p.cam, p.vert] - p.flow
        total = total + 3.0 * (e * e).sum() / pbs[i].n_px
    assert abs(float(total.detach()) - wev.loss) < 1e-9 * wev.loss
    (grad,) = torch.autograd.grad(total, d)
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-5, atol=1e-8 * float(gvec.abs().max()))


def test_pair_flow_is_the_targets_minus_the_previous_projection():
    rig, views = toy(C=2, H=48, W=48)
    x = lbs(rig.rest, rig.weights, pose(rig, torch.Generator().manual_seed(2), 0.1, 0.02))
    uv, _ = raster.project_vertices(x, views.K, views.world_to_cam)
    c, v = torch.tensor([0, 1, 1]), torch.tensor([3, 5, 40])
    p = pair_flow(fit.FlowTargets(c, v, uv[c, v] + torch.tensor([1.0, -2.0], dtype=torch.float64)), x, views)
    torch.testing.assert_close(p.flow, torch.tensor([1.0, -2.0], dtype=torch.float64).expand(3, 2))
    assert pair_flow(None, x, views) is None
    assert pair_flow(fit.FlowTargets(c[:0], v[:0], uv[c, v][:0]), x, views) is None


def test_fit_sequence_refines_windows_jointly():
    """Five frames with (zero) flow, windows of 3: frames 0-2 and 3-4 are refined jointly; the window's
    loss never rises above the chain's, equals the sum of its frames' results, and the poses stay finite;
    the problems are not kept."""
    rig, views = toy(C=3, H=48, W=48)
    g, Gs, frames = moving(rig, views, 5, seed=9)
    C, H, W = frames[0][0].mask.shape
    flow_of = lambda t: (torch.zeros(C, H, W, 2, dtype=torch.float64), None)  # noqa: E731
    cfg = config(dict(PAPER, normal=300.0), max_iters=3, max_iters_first=5, smooth_passes=0)
    start = pose(rig, g, 0.03, 0.01, Gs[0])
    chain = fit.fit_sequence(fit.FitPlan(cfg.replace(window=0), rig, views, 5, start), lambda t: frames[t][0], flow_of,
                             progress=False)
    res = fit.fit_sequence(fit.FitPlan(cfg.replace(window=3), rig, views, 5, start), lambda t: frames[t][0], flow_of,
                           progress=False)
    assert all("window" not in r.notes and r.problem is None for r in chain)
    assert [("window" in r.notes) for r in res] == [False, False, True, False, True]
    for lo, hi in ((0, 3), (3, 5)):
        rec = res[hi - 1].notes["window"]
        assert rec["frames"] == hi - lo and rec["loss"] <= rec["chain_loss"] and rec["iterations"] >= 1
        assert abs(sum(r.loss for r in res[lo:hi]) - rec["loss"]) <= 1e-9 * rec["loss"]
    assert res[3].terms["flow"] > 0 and res[4].terms["flow"] > 0
    for r in res:
        assert r.problem is None and r.crop is None
        assert torch.isfinite(r.transforms).all() and math.isfinite(r.loss)
