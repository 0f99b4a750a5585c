"""Every loss term of anidress_core.fit.terms: its Gauss-Newton block (H, g) against autograd of its
reference (float64), and its value against the reference's."""
from __future__ import annotations

import inspect

import pytest
import torch

from anidress_core import fit, raster
from anidress_core.fit.images import pixel_ok, sample
from anidress_core.fit.problem import Linearisation, Rendered, System
from anidress_core.fit.terms import collision, stretch
from anidress_core.fit.terms.prior import Reference
from anidress_core.geometry import lbs, vertex_normals
from tests.fit.scenes import PAPER, config, only, pose, render, toy

torch.set_num_threads(1)


def check_system(rig, views, cues, G0, cfg, residuals=None, irls=False, **given):
    """H, g of gauss_newton_system (every term's gauss_newton) against J^T J, J^T r of ``residuals(d, ev)`` (the
    weighted residual vector at the increment d, visibility of ev held fixed; by forward-mode autograd), and 2 g
    against the autograd gradient of loss_terms (every term's reference), float64. ``given``: make_problem's
    inputs of the terms. Returns the evaluation."""
    pb = fit.make_problem(rig, views, cues, cfg, **given)
    ev = fit.evaluate(pb, lbs(rig.rest, rig.weights, G0))
    assert ev.loss > 0
    H, gvec = fit.gauss_newton_system(pb, ev, G0)
    d = torch.zeros(gvec.numel(), dtype=torch.float64, requires_grad=True)
    x = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
    total, terms = fit.loss_terms(pb, x, ev.fragments)
    assert abs(float(total.detach()) - ev.loss) < 1e-10 * ev.loss  # value = reference's value
    for k in fit.TERM_NAMES:
        assert abs(float(terms[k].detach()) - ev.terms[k]) <= 1e-10 * max(ev.terms[k], 1e-300)
    (grad,) = torch.autograd.grad(total, d)  # (for the Cauchy anchor the IRLS gradient is the exact one)
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-5, atol=1e-8 * float(gvec.abs().max()))
    if residuals is not None:
        d0 = torch.zeros(gvec.numel(), dtype=torch.float64)
        r = residuals(d0, pb, ev)
        if irls:  # grid_sample has no forward-mode derivative
            J = torch.autograd.functional.jacobian(lambda dd: residuals(dd, pb, ev), d0)
        else:
            J = torch.func.jacfwd(lambda dd: residuals(dd, pb, ev))(d0)
        if not irls:
            assert abs(float(r @ r) - ev.loss) < 1e-10 * ev.loss
        torch.testing.assert_close(H, J.t() @ J, rtol=1e-6, atol=1e-9 * float(H.abs().max()))
        torch.testing.assert_close(gvec, J.t() @ r, rtol=1e-6, atol=1e-9 * float(gvec.abs().max()))
    return ev


def test_every_term_has_the_one_protocol():
    """Every term of TERMS: NAME and setup, value, gauss_newton, reference with the same parameters."""
    want = {"setup": ["pb", "cues", "given"], "value": ["pb", "st", "r"],
            "gauss_newton": ["pb", "st", "data", "lin", "out"], "reference": ["pb", "st", "verts", "fragments"]}
    for term in fit.TERMS:
        assert term.NAME in fit.TERM_NAMES
        for name, params in want.items():
            assert list(inspect.signature(getattr(term, name)).parameters) == params, (term.NAME, name)


def scene(seed, C=3, H=48, W=48, n_theta=20, n_h=6):
    rig, views = toy(C=C, H=H, W=W, n_theta=n_theta, n_h=n_h)
    g = torch.Generator().manual_seed(seed)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, xt, _ = render(rig, views, Gt)
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    return rig, views, g, Gt, cues, xt, G0


def moved(rig, G0, d):
    return lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))


def test_silhouette():
    rig, views, _, _, cues, _, G0 = scene(2)
    cfg = only("silhouette", 2.0)

    def residuals(d, pb, ev):
        x = moved(rig, G0, d)
        s = raster.silhouette(x, rig.faces, views.K, views.world_to_cam, ev.fragments, rig.edges)
        return (s - cues.mask.double()).reshape(-1) * (2.0 / pb.n_px) ** 0.5

    ev = check_system(rig, views, cues, G0, cfg, residuals)
    assert ev.terms["silhouette"] > 0 and ev.terms["normal"] == 0


def test_normal():
    rig, views, _, _, cues, _, G0 = scene(3)
    cfg = only("normal", 0.7)

    def residuals(d, pb, ev):
        x = moved(rig, G0, d)
        n = raster.render_face_normals(x, rig.faces, views.world_to_cam, ev.fragments)
        st = pb.states["normal"]
        sel = (ev.fragments.face_id >= 0) & st.ok
        return (n - st.normals)[sel].reshape(-1) * (0.7 / pb.n_px) ** 0.5

    assert check_system(rig, views, cues, G0, cfg, residuals).terms["normal"] > 0


def test_flow():
    rig, views, g, _, cues, xt, G0 = scene(4)
    uv, _ = raster.project_vertices(xt, views.K, views.world_to_cam)
    c = torch.randint(0, 3, (40,), generator=g)
    v = torch.randint(0, rig.rest.shape[0], (40,), generator=g)
    ft = fit.FlowTargets(c, v, uv[c, v] + 0.3 * torch.randn(40, 2, generator=g, dtype=torch.float64))
    cfg = only("flow", 3.0)

    def residuals(d, pb, ev):
        u, _ = raster.project_vertices(moved(rig, G0, d), views.K, views.world_to_cam)
        return (u[ft.cam, ft.vert] - ft.target).reshape(-1) * (3.0 / pb.n_px) ** 0.5

    assert check_system(rig, views, cues, G0, cfg, residuals, flow=ft).terms["flow"] > 0


def test_paper_loss_sums_its_terms():
    """The three paper terms together: the system is the sum of theirs (all residuals stacked)."""
    rig, views, g, _, cues, xt, G0 = scene(2)
    uv, _ = raster.project_vertices(xt, views.K, views.world_to_cam)
    c = torch.randint(0, 3, (40,), generator=g)
    v = torch.randint(0, rig.rest.shape[0], (40,), generator=g)
    ft = fit.FlowTargets(c, v, uv[c, v] + 0.3 * torch.randn(40, 2, generator=g, dtype=torch.float64))
    cfg = config(PAPER)

    def residuals(d, pb, ev):
        x = moved(rig, G0, d)
        K, E = views.K, views.world_to_cam
        s = raster.silhouette(x, rig.faces, K, E, ev.fragments, rig.edges)
        r1 = (s - cues.mask.double()).reshape(-1) * (2.0 / pb.n_px) ** 0.5
        n = raster.render_face_normals(x, rig.faces, E, ev.fragments)
        st = pb.states["normal"]
        sel = (ev.fragments.face_id >= 0) & st.ok
        r2 = (n - st.normals)[sel].reshape(-1) * (0.1 / pb.n_px) ** 0.5
        u, _ = raster.project_vertices(x, K, E)
        r3 = (u[ft.cam, ft.vert] - ft.target).reshape(-1) * (3.0 / pb.n_px) ** 0.5
        return torch.cat([r1, r2, r3])

    check_system(rig, views, cues, G0, cfg, residuals, flow=ft)


def test_prior():
    rig, views, g, _, cues, _, G0 = scene(5)
    start = lbs(rig.rest, rig.weights, pose(rig, g, 0.02, 0.01, G0))
    cfg = only("prior", 10.0, prior_tangential=False)

    def residuals(d, pb, ev):
        x = moved(rig, G0, d)
        return (x - start).reshape(-1) * (10.0 / x.shape[0]) ** 0.5

    assert check_system(rig, views, cues, G0, cfg, residuals, prior=Reference(start)).terms["prior"] > 0
    # off without a start mesh (frames t > 0)
    assert fit.make_problem(rig, views, cues, cfg).states["prior"] is None


def test_prior_tangential():
    """Only the offset along the reference surface counts: residual sqrt(w / V) (I - n n^T)(x - x_ref)."""
    rig, views, g, _, cues, _, G0 = scene(5)
    ref = lbs(rig.rest, rig.weights, pose(rig, g, 0.02, 0.01, G0))
    cfg = only("prior", 10.0).replace(prior_tangential=True)
    n = vertex_normals(ref, rig.faces)

    def residuals(d, pb, ev):
        off = moved(rig, G0, d) - ref
        tangential = off - (off * n).sum(-1, keepdim=True) * n
        return tangential.reshape(-1) * (10.0 / off.shape[0]) ** 0.5

    ev = check_system(rig, views, cues, G0, cfg, residuals, prior=Reference(ref))
    assert 0 < ev.terms["prior"]
    # a move along the reference's normals costs nothing
    pb = fit.make_problem(rig, views, cues, cfg, prior=Reference(ref))
    assert fit.evaluate(pb, ref + 0.01 * n).terms["prior"] < 1e-20
    along = torch.linalg.cross(n, torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype).expand_as(n))
    assert fit.evaluate(pb, ref + 0.01 * along).terms["prior"] > 1e-6


def test_prior_scaled_per_vertex():
    """With a factor s_v per vertex (fit/prior_spread_floor): residual sqrt(w s_v / V) (I - n n^T)(x - x_ref)."""
    rig, views, g, _, cues, _, G0 = scene(6)
    ref = lbs(rig.rest, rig.weights, pose(rig, g, 0.02, 0.01, G0))
    cfg = only("prior", 10.0).replace(prior_tangential=True)
    n = vertex_normals(ref, rig.faces)
    s = torch.rand(ref.shape[0], generator=g, dtype=torch.float64)

    def residuals(d, pb, ev):
        off = moved(rig, G0, d) - ref
        tangential = off - (off * n).sum(-1, keepdim=True) * n
        return (tangential * (10.0 * s[:, None] / off.shape[0]) ** 0.5).reshape(-1)

    scaled = check_system(rig, views, cues, G0, cfg, residuals, prior=Reference(ref, s)).terms["prior"]
    whole = fit.evaluate(fit.make_problem(rig, views, cues, cfg, prior=Reference(ref)), lbs(rig.rest, rig.weights, G0))
    assert 0 < scaled < whole.terms["prior"]
    with pytest.raises(ValueError, match="factor per vertex"):
        fit.make_problem(rig, views, cues, cfg, prior=Reference(ref, -s))


def test_prior_spread_scale():
    """spread_scale: mean 1 over each frame's vertices, lower where the ensemble's members disagree more, s0
    the floor times the median spread (a uniform spread or none at all: 1 everywhere); a bad spread raises."""
    from anidress_core.fit.terms.prior import spread_scale

    sig = torch.tensor([[0.0, 0.01, 0.02, 0.04], [0.03, 0.03, 0.03, 0.03]], dtype=torch.float64)
    s = spread_scale(sig, 1.0)
    torch.testing.assert_close(s.mean(1), torch.ones(2, dtype=torch.float64))
    assert bool((s[0, 1:] < s[0, :-1]).all())  # more spread, less weight
    torch.testing.assert_close(s[1], torch.ones(4, dtype=torch.float64))
    s0 = float(sig.median())  # 0.03: the ratio of two vertices' factors is (sig_j^2 + s0^2) / (sig_i^2 + s0^2)
    assert float(s[0, 0] / s[0, 3]) == pytest.approx((0.04 ** 2 + s0 ** 2) / s0 ** 2)
    assert float(spread_scale(sig, 2.0)[0, 0] / spread_scale(sig, 2.0)[0, 3]) < float(s[0, 0] / s[0, 3])  # softer
    torch.testing.assert_close(spread_scale(torch.zeros(3, 5), 1.0), torch.ones(3, 5, dtype=torch.float64))
    for bad in (torch.full((2, 3), float("nan")), -torch.ones(2, 3)):
        with pytest.raises(ValueError, match="finite"):
            spread_scale(bad, 1.0)
    with pytest.raises(ValueError, match="floor"):
        spread_scale(sig, 0.0)


def test_anchor():
    """L_anchor on an image whose chromaticity is linear (r + g + b constant, no blur): the bilinear
    sample and the central differences of image_features are exact, so H is the IRLS J^T W J."""
    C, H, W = 4, 64, 64
    rig, views, g, _, cues, _, G0 = scene(13, C=C, H=H, W=W, n_theta=40, n_h=12)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    img = torch.stack([0.3 + 0.004 * xx, 0.3 + 0.003 * yy, 0.3 - 0.004 * xx - 0.003 * yy], -1)
    img = img[None].expand(C, -1, -1, -1)
    cues = cues._replace(image=img.clone())
    ref = fit.AnchorRef(0.33 + 0.05 * torch.rand(rig.rest.shape[0], 3, generator=g, dtype=torch.float64),
                        torch.rand(rig.rest.shape[0], generator=g) < 0.8)
    cfg = only("anchor", 50.0, image_blur=0.0, anchor_scale=0.02)

    def residuals(d, pb, ev):
        x = moved(rig, G0, d)
        uv, _ = raster.project_vertices(x, views.K, views.world_to_cam)
        x0 = ev.verts
        uv0, _ = raster.project_vertices(x0, views.K, views.world_to_cam)
        vis = raster.visible_vertices(x0, views.K, views.world_to_cam, ev.fragments, cfg.visibility_depth_tol)
        st = pb.states["anchor"]
        vis = vis & pixel_ok(st.region, uv0) & ref.seen[None]
        r = (sample(st.feat[:, :3], uv) - ref.chroma[None])[vis]  # (N, 3), IRLS weights held fixed
        w = ev.data["anchor"].weight
        return (r * (w[:, None] * 50.0 / pb.n_px) ** 0.5).reshape(-1)

    ev = check_system(rig, views, cues, G0, cfg, residuals, irls=True, anchor=ref)
    assert ev.terms["anchor"] > 0 and ev.data["anchor"].cam.numel() > 40


def test_collision():
    """L_collision (point-to-plane at the frame's start): exact J^T J of the active residuals."""
    pytest.importorskip("warp")
    from tests.sim.skirt import sphere_body

    rig, views = toy(C=4, H=64, W=64, n_theta=32, n_h=10)
    G = torch.eye(4, dtype=torch.float64).expand(rig.weights.shape[1], 4, 4).clone()
    x = lbs(rig.rest, rig.weights, G)
    bv, bf, _ = (torch.as_tensor(a) for a in sphere_body(0.1, (0.33, 0.0, 0.75)))
    cfg = only("collision", 1e3, collision_clearance=0.005)
    contacts = fit.body_contacts(x, bv, bf, cfg.collision_radius)
    cues = fit.FrameCues(torch.zeros(4, 64, 64, dtype=torch.bool), None, None, (bv, bf))
    G0 = pose(rig, torch.Generator().manual_seed(4), 0.02, 0.005, G)

    def residuals(d, pb, ev):
        xx = moved(rig, G0, d)
        return collision.residual(contacts, xx, cfg.collision_clearance) * (1e3 / xx.shape[0]) ** 0.5

    assert check_system(rig, views, cues, G0, cfg, residuals, collision=contacts).terms["collision"] > 0


def test_stretch():
    """L_stretch: exact J^T J, J^T r of the edges' relative stretch, and zero at the rest pose."""
    rig, views, _, _, cues, _, G0 = scene(7)
    cfg = only("stretch", 30.0)
    edges = stretch.rest_edges(rig.rest, *rig.edges, rig.faces, rig.layout)
    assert edges.a.numel() == rig.edges[0].shape[0]
    assert torch.allclose(edges.rest, (rig.rest[edges.a] - rig.rest[edges.b]).norm(dim=-1), rtol=0, atol=1e-15)

    def residuals(d, pb, ev):
        s, _ = stretch.residual(edges, moved(rig, G0, d))
        return s * (30.0 / s.numel()) ** 0.5

    assert check_system(rig, views, cues, G0, cfg, residuals).terms["stretch"] > 0
    pb = fit.make_problem(rig, views, cues, cfg)
    assert fit.evaluate(pb, rig.rest).terms["stretch"] < 1e-24


def test_stretch_of_a_collapsed_mesh_is_finite():
    """Every vertex at one point: stretch -1 on every edge, no NaN in the value or the Gauss-Newton block."""
    rig, views, _, _, cues, _, _ = scene(8)
    pb = fit.make_problem(rig, views, cues, only("stretch", 30.0))
    st = pb.states["stretch"]
    x = torch.zeros_like(rig.rest)
    s, _ = stretch.residual(st, x)
    assert torch.equal(s, -torch.ones_like(s))
    assert stretch.value(pb, st, Rendered(x, None, None, None))[0] == 1.0
    out = System(None, None, torch.zeros(rig.layout.perm.numel() // 9, 3, 3, dtype=torch.float64), torch.zeros_like(x))
    assert stretch.gauss_newton(pb, st, None, Linearisation(x, None, None, None, torch.float64), out)
    assert bool(torch.isfinite(out.blocks).all() and torch.isfinite(out.gx).all())


def test_total_is_the_weighted_sum_of_the_terms():
    rig, views, _, _, cues, _, G0 = scene(6)
    cfg = config(dict(PAPER, prior=10.0))
    pb = fit.make_problem(rig, views, cues, cfg, prior=Reference(lbs(rig.rest, rig.weights, G0) + 0.001))
    ev = fit.evaluate(pb, lbs(rig.rest, rig.weights, G0))
    assert set(ev.terms) == set(fit.TERM_NAMES)
    want = sum(getattr(cfg.weights, k) * v for k, v in ev.terms.items())
    assert abs(ev.loss - want) <= 1e-12 * ev.loss and ev.loss == fit.total_loss(cfg.weights, ev.terms)
