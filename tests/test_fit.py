"""Garment fitting (anidress_core.fit): exact Gauss-Newton systems, pose recovery, robustness."""
from __future__ import annotations

import dataclasses
import logging
import math

import pytest
import torch

from anidress_core import fit, raster
from anidress_core.camera import ring_cameras
from anidress_core.geometry import lbs

torch.set_num_threads(1)


def cone(n_theta=32, n_h=10, r0=0.15, r1=0.35, h=0.5, z0=1.0):
    th = torch.arange(n_theta, dtype=torch.float64) / n_theta * 2 * math.pi
    s = torch.linspace(0, 1, n_h, dtype=torch.float64)
    r = r0 + (r1 - r0) * s
    v = torch.stack([r[:, None] * torch.cos(th), r[:, None] * torch.sin(th), (z0 - h * s)[:, None].expand(-1, n_theta)],
                    -1).reshape(-1, 3)
    f = []
    for i in range(n_h - 1):
        for j in range(n_theta):
            a, b = i * n_theta + j, i * n_theta + (j + 1) % n_theta
            f += [[a, a + n_theta, b], [b, a + n_theta, b + n_theta]]
    return v, torch.tensor(f)


def toy(C=4, H=64, W=64, n_theta=32, n_h=10, nb=3):
    """A cone 'skirt' with 2 nb bones (angular sectors x two bands) seen by C ring cameras."""
    v, f = cone(n_theta, n_h)
    ang = torch.atan2(v[:, 1], v[:, 0])
    a = torch.arange(nb, dtype=torch.float64) * 2 * math.pi / nb
    d = torch.cdist(torch.stack([ang.cos(), ang.sin()], -1), torch.stack([a.cos(), a.sin()], -1))
    wa = torch.softmax(-d / 0.3, -1)
    hw = ((1.0 - v[:, 2]) / 0.5).clamp(0, 1)[:, None]
    Wt = torch.cat([wa * (1 - hw), wa * hw], -1)
    centres = (Wt.t() @ v) / Wt.sum(0)[:, None]
    rig = fit.RigParts.make(v, Wt, centres, f)
    cams = ring_cameras(n=C, radius=2.0, height=1.0, target=(0, 0, 0.8), focal_px=1.1 * H, image_height=H,
                        image_width=W)
    return rig, fit.Views.from_cameras(cams)


def pose(rig, g, rot, trans, base=None):
    B = rig.weights.shape[1]
    d = torch.cat([rot * torch.randn(B, 3, generator=g, dtype=torch.float64),
                   trans * torch.randn(B, 3, generator=g, dtype=torch.float64)], -1)
    G = torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone() if base is None else base
    return fit.apply_increment(G, rig.centres, d)


def render(rig, views, G, occluder=None):
    """Exact cues of the mesh LBS(G): garment mask, face normals; and its fragments."""
    x = lbs(rig.rest, rig.weights, G)
    fr = raster.rasterize(x, rig.faces, views.K, views.world_to_cam, views.height, views.width)
    occ = torch.full(fr.depth.shape, float("inf"), dtype=torch.float64) if occluder is None else occluder
    fr = raster.occlude(fr, occ)
    n = raster.render_face_normals(x, rig.faces, views.world_to_cam, fr)
    return fit.FrameCues(fr.face_id >= 0, n, occ), x, fr


def exact_flow(rig, views, x_prev, fr_prev, x_next):
    """Flow targets that move the previous mesh's visible vertices to their true next positions."""
    vis = raster.visible_vertices(x_prev, views.K, views.world_to_cam, fr_prev)
    uv, _ = raster.project_vertices(x_next, views.K, views.world_to_cam)
    c, v = vis.nonzero(as_tuple=True)
    return fit.FlowTargets(c, v, uv[c, v])


def rmse(a, b):
    return float(((a - b) ** 2).sum(-1).mean().sqrt())


# --------------------------------------------------------------------------------------
# building blocks
# --------------------------------------------------------------------------------------


def test_views_make_camera_rotations_orthonormal_and_reject_non_rotations():
    """float32 camera files give rotations orthonormal to ~1e-7 only; the fit's normal term
    needs R^T = R^-1, so from_cameras projects them onto SO(3), and refuses a matrix that is
    not a rotation at all."""
    cams = ring_cameras(n=3, radius=2.0, height=1.0, target=(0, 0, 0.8), focal_px=50.0, image_height=48,
                        image_width=48)  # float32
    R32 = cams.world_to_cam[:, :3, :3].double()
    assert float((R32 @ R32.transpose(1, 2) - torch.eye(3)).abs().max()) > 1e-9
    v = fit.Views.from_cameras(cams)
    R = v.world_to_cam[:, :3, :3]
    assert float((R @ R.transpose(1, 2) - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-14
    assert float((R - R32).abs().max()) < 1e-6  # the nearest rotation: a round-off change
    torch.testing.assert_close(v.world_to_cam[:, :3, 3], cams.world_to_cam[:, :3, 3].double())
    R_bad = cams.R.clone()
    R_bad[1] *= 1.1
    bad = dataclasses.replace(cams, R=R_bad)
    with pytest.raises(ValueError, match="not a rotation"):
        fit.Views.from_cameras(bad)


def test_skin_and_projection_jacobians_match_autograd():
    rig, views = toy()
    g = torch.Generator().manual_seed(0)
    G = pose(rig, g, 0.3, 0.05)
    J = fit.skin_jacobian(rig, G)  # (V, 3, P)
    want = torch.autograd.functional.jacobian(
        lambda d: lbs(rig.rest, rig.weights, fit.apply_increment(G, rig.centres, d.view(-1, 6))),
        torch.zeros(rig.weights.shape[1] * 6, dtype=torch.float64))
    torch.testing.assert_close(J, want)
    x = lbs(rig.rest, rig.weights, G)
    uv, P = fit.projection_jacobian(x, views)
    uv_ref, _ = raster.project_vertices(x, views.K, views.world_to_cam)
    torch.testing.assert_close(uv, uv_ref)
    Pref = torch.autograd.functional.jacobian(lambda y: raster.project_vertices(y[None], views.K[:1],
                                                                              views.world_to_cam[:1])[0][0, 0], x[5])
    torch.testing.assert_close(P[0, 5], Pref)


def test_apply_increment_rotates_about_the_bone_centre():
    rig, _ = toy()
    g = torch.Generator().manual_seed(1)
    G = pose(rig, g, 0.4, 0.1)
    B = G.shape[0]
    torch.testing.assert_close(fit.apply_increment(G, rig.centres, torch.zeros(B, 6, dtype=torch.float64)), G)
    cw = lambda M: torch.einsum("bij,bj->bi", M[:, :3, :3], rig.centres) + M[:, :3, 3]  # noqa: E731
    rot = torch.zeros(B, 6, dtype=torch.float64)
    rot[:, :3] = torch.tensor([0.0, 0.0, math.pi])  # a half turn: still finite, centre fixed
    G2 = fit.apply_increment(G, rig.centres, rot)
    torch.testing.assert_close(cw(G2), cw(G))
    R = G2[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(B, 3, 3))
    tr = torch.zeros(B, 6, dtype=torch.float64)
    tr[:, 3:] = 0.2
    torch.testing.assert_close(cw(fit.apply_increment(G, rig.centres, tr)), cw(G) + 0.2)


def test_gauss_newton_system_is_exact():
    """g and H of the Levenberg-Marquardt step equal autograd's J^T r and J^T J (float64)."""
    rig, views = toy(C=3, H=48, W=48, n_theta=20, n_h=6)
    g = torch.Generator().manual_seed(2)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, xt, _ = render(rig, views, Gt)
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    uv, _ = raster.project_vertices(xt, views.K, views.world_to_cam)
    c = torch.randint(0, 3, (40,), generator=g)
    v = torch.randint(0, rig.rest.shape[0], (40,), generator=g)
    ft = fit.FlowTargets(c, v, uv[c, v] + 0.3 * torch.randn(40, 2, generator=g, dtype=torch.float64))
    cfg = fit.FitConfig()
    pb = fit._make_problem(rig, views, cues, ft, cfg)
    ev = fit._evaluate(pb, lbs(rig.rest, rig.weights, G0))
    H, gvec = fit._gauss_newton(pb, ev, G0)

    def residuals(d):  # the weighted residual vector, visibility of ev held fixed
        x = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
        K, E = views.K, views.world_to_cam
        s = raster.silhouette(x, rig.faces, K, E, ev.fragments, rig.edges)
        r1 = (s - cues.mask.double()).reshape(-1) * (cfg.w_mask / pb.n_mask) ** 0.5
        n = raster.render_face_normals(x, rig.faces, E, ev.fragments)
        sel = (ev.fragments.face_id >= 0) & pb.normal_ok
        r2 = (n - pb.normals)[sel].reshape(-1) * (cfg.w_normal / pb.n_normal) ** 0.5
        u, _ = raster.project_vertices(x, K, E)
        r3 = (u[ft.cam, ft.vert] - ft.target).reshape(-1) * (cfg.w_flow / pb.n_flow) ** 0.5
        return torch.cat([r1, r2, r3])

    d0 = torch.zeros(H.shape[0], dtype=torch.float64)
    r = residuals(d0)
    J = torch.stack([torch.func.jvp(residuals, (d0,), (e,))[1] for e in torch.eye(d0.numel(), dtype=torch.float64)], 1)
    assert abs(float(r @ r) - ev.loss) < 1e-10 * ev.loss
    torch.testing.assert_close(H, J.t() @ J, rtol=1e-6, atol=1e-9 * float(H.abs().max()))
    torch.testing.assert_close(gvec, J.t() @ r, rtol=1e-6, atol=1e-9 * float(gvec.abs().max()))
    # and the differentiable loss used by the vertex ablation has the same gradient (2 J^T r)
    d = d0.clone().requires_grad_(True)
    x = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
    total, _ = fit.loss_terms(rig, views, cues, x, ft, cfg, fragments=ev.fragments)
    (grad,) = torch.autograd.grad(total, d)
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-6, atol=1e-9 * float(gvec.abs().max()))


def textured(rig, views, G, colour_of):
    """Exact cues of LBS(G) plus colour images: per-vertex colours colour_of(rest) (V, 3)
    interpolated with the barycentrics (background grey)."""
    cues, x, fr = render(rig, views, G)
    col = colour_of(rig.rest)
    fid = fr.face_id.clamp_min(0)
    img = (fr.bary[..., None] * col[rig.faces[fid]]).sum(-2)
    img = torch.where((fr.face_id >= 0)[..., None], img, torch.full_like(img, 0.5))
    return cues._replace(image=img), x


def test_photo_features_and_photo_consistency_gradient():
    """The derivative channels of photo_features are exact on a linear image; the Gauss-Newton
    gradient of L_ph equals autograd's (quadratic regime, a linear image: bilinear sampling exact)."""
    C, H, W = 4, 64, 64
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    lin = torch.stack([0.01 * xx, 0.02 * yy, 0.005 * xx + 0.01 * yy], -1)  # (H, W, 3)
    feat = fit.photo_features(lin[None].expand(C, -1, -1, -1), blur=0.0)
    torch.testing.assert_close(feat[:, 3:6], torch.tensor([0.01, 0.0, 0.005], dtype=torch.float64)[None, :, None, None]
                               .expand(C, 3, H, W))
    torch.testing.assert_close(feat[:, 6:9], torch.tensor([0.0, 0.02, 0.01], dtype=torch.float64)[None, :, None, None]
                               .expand(C, 3, H, W))
    blurred = fit.photo_features(lin[None], blur=1.0)[0, :3, 8:-8, 8:-8]  # a Gaussian keeps a linear image
    torch.testing.assert_close(blurred, lin.permute(2, 0, 1)[:, 8:-8, 8:-8])

    rig, views = toy(C=C, H=H, W=W, n_theta=40, n_h=12)
    g = torch.Generator().manual_seed(12)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, _, _ = render(rig, views, Gt)
    cues = cues._replace(image=lin[None].expand(C, -1, -1, -1).clone())
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    cfg = fit.FitConfig(w_mask=0.0, w_normal=0.0, w_flow=0.0, w_photo=5.0, photo_blur=0.0, photo_scale=1e3)
    pb = fit._make_problem(rig, views, cues, None, cfg)
    ev = fit._evaluate(pb, lbs(rig.rest, rig.weights, G0))
    assert ev.pho is not None and ev.pho.cam.numel() > 40 and ev.loss > 0
    _, gvec = fit._gauss_newton(pb, ev, G0)
    d = torch.zeros(gvec.numel(), dtype=torch.float64, requires_grad=True)
    x = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
    total, terms = fit.loss_terms(rig, views, cues, x, None, cfg, fragments=ev.fragments)
    assert abs(float(total) - ev.loss) < 1e-10 * ev.loss
    (grad,) = torch.autograd.grad(total, d)
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-5, atol=1e-8 * float(gvec.abs().max()))


def test_sample_blurred_matches_filtering_the_whole_image():
    """_sample_blurred (the stencil at the points only, used by update_anchor) equals the
    reference: blur the whole image (_blurred), then sample it bilinearly (_sample) -- inside,
    on and beyond the border, and with a NaN pixel."""
    g = torch.Generator().manual_seed(21)
    C, H, W = 3, 17, 23
    img = torch.rand(C, H, W, 3, generator=g, dtype=torch.float64)
    img[1, 4, 5, 0] = float("nan")
    uv = torch.rand(C, 40, 2, generator=g, dtype=torch.float64) * torch.tensor([W + 3.0, H + 3.0]) - 1.5
    uv[0, :3] = torch.tensor([[W - 1.0, H - 1.0], [0.0, 0.0], [W - 1.0, 3.5]], dtype=torch.float64)
    cam = torch.arange(C).repeat_interleave(uv.shape[1])
    for blur in (0.0, 0.5, 1.3):
        ref = fit._sample(fit._blurred(img, blur), uv)  # (C, V, 3)
        got = fit._sample_blurred(img, cam, uv.reshape(-1, 2), blur).view(C, -1, 3)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)


def test_smooth_transforms_keeps_steady_motion_and_damps_jitter():
    """The temporal filter of the bone transforms: a rotation at constant angular velocity plus a
    translation at constant velocity pass unchanged (the end frames always); alternating noise
    on top is damped; rotations stay rotations; the skinned vertices match filtering the
    vertices themselves up to the rotation projection (second order in the frame-to-frame spread)."""
    from anidress_core.geometry import axis_angle_to_matrix

    T, B = 9, 3
    g = torch.Generator().manual_seed(31)
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=torch.float64), dim=-1)
    t = torch.arange(T, dtype=torch.float64)[:, None, None]
    G = torch.eye(4, dtype=torch.float64).expand(T, B, 4, 4).clone()
    G[..., :3, :3] = axis_angle_to_matrix(0.05 * t * axis[None])  # constant angular velocity
    G[..., :3, 3] = 0.01 * t * torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    torch.testing.assert_close(fit.smooth_transforms(G, 2), G, rtol=0, atol=1e-12)
    noisy = G.clone()
    sign = (-1.0) ** torch.arange(T, dtype=torch.float64)[:, None, None]
    noisy[..., :3, 3] += 0.004 * sign
    noisy[..., :3, :3] = axis_angle_to_matrix(0.02 * sign * axis[None]) @ noisy[..., :3, :3]
    sm = fit.smooth_transforms(noisy, 1)
    torch.testing.assert_close(sm[[0, -1]], noisy[[0, -1]])
    R = sm[..., :3, :3]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(T, B, 3, 3))
    assert bool((torch.linalg.det(R) > 0).all())
    err = lambda X: float((X[1:-1] - G[1:-1]).abs().max())  # noqa: E731
    assert err(sm) < 0.1 * err(noisy)  # alternating noise: (1, 2, 1)/4 removes it (to second order)
    rig, _ = toy(C=1, H=8, W=8, n_theta=12, n_h=4)
    Gr = noisy[:, :1].expand(T, rig.weights.shape[1], 4, 4)
    x = torch.stack([lbs(rig.rest, rig.weights, m) for m in Gr])
    xs = torch.stack([lbs(rig.rest, rig.weights, m) for m in fit.smooth_transforms(Gr, 1)])
    torch.testing.assert_close(xs[1:-1], 0.25 * x[:-2] + 0.5 * x[1:-1] + 0.25 * x[2:], rtol=0, atol=2e-3)
    with pytest.raises(ValueError, match="T, B, 4, 4"):
        fit.smooth_transforms(G[0])


def test_photo_consistency_sharpens_the_first_frame_shape():
    """On a textured garment, multi-view photo-consistency pins the shape better than masks and
    normals alone (the first frame, no flow): mean vertex error over three random starts."""
    rig, views = toy(C=4, H=80, W=80)

    def colour_of(p):
        th = torch.atan2(p[:, 1], p[:, 0])
        return torch.stack([0.5 + 0.4 * torch.sin(4 * th), 0.5 + 0.4 * torch.cos(3 * th + 8 * p[:, 2]),
                            0.5 + 0.3 * torch.sin(2 * th - 12 * p[:, 2])], -1)

    plain, photo = [], []
    for seed in (4, 5, 6):
        g = torch.Generator().manual_seed(seed)
        Gt = pose(rig, g, 0.15, 0.03)
        cues, xt = textured(rig, views, Gt, colour_of)
        G0 = pose(rig, g, 0.06, 0.015, Gt)
        e0 = rmse(lbs(rig.rest, rig.weights, G0), xt)
        plain.append(rmse(fit.fit_frame(rig, views, cues, G0, fit.FitConfig(), first=True).verts, xt) / e0)
        r = fit.fit_frame(rig, views, cues, G0, fit.FitConfig(w_photo=1000.0), first=True)
        assert r.terms["photo"] > 0 and torch.isfinite(r.transforms).all()
        photo.append(rmse(r.verts, xt) / e0)
    assert sum(photo) < 0.85 * sum(plain), (photo, plain)


def test_anchor_reference_and_gradient():
    """update_anchor gives each vertex the chromaticity of the first frame it is seen in and keeps
    it; the Gauss-Newton gradient of L_an equals autograd's (an image with a linear chromaticity:
    r + g + b constant)."""
    C, H, W = 4, 64, 64
    rig, views = toy(C=C, H=H, W=W, n_theta=40, n_h=12)
    G = torch.eye(4, dtype=torch.float64).expand(rig.weights.shape[1], 4, 4).clone()
    cues, x, fr = render(rig, views, G)
    cfg = fit.FitConfig(photo_blur=0.0)
    flat = torch.tensor([0.6, 0.3, 0.1], dtype=torch.float64).expand(C, H, W, 3)
    a = fit.update_anchor(None, x, views, fr, flat, cues.mask, cfg)
    vis = raster.visible_vertices(x, views.K, views.world_to_cam, fr, cfg.vis_depth_tol).any(0)
    assert 0 < int(a.seen.sum()) <= int(vis.sum()) and not bool((a.seen & ~vis).any())
    torch.testing.assert_close(a.chroma[a.seen], (flat[0, 0, 0] / (1.0 + fit.CHROMA_EPS)).expand(int(a.seen.sum()), 3))
    # a later frame: the seen vertices keep their reference, newly seen ones get this frame's
    b = fit.update_anchor(a._replace(seen=a.seen & (torch.arange(a.seen.numel()) % 2 == 0)), x, views, fr,
                          flat.flip(-1), cues.mask, cfg)
    even = torch.arange(a.seen.numel()) % 2 == 0
    torch.testing.assert_close(b.chroma[a.seen & even], a.chroma[a.seen & even])
    torch.testing.assert_close(b.chroma[a.seen & ~even], (flat[0, 0, 0].flip(-1) / (1.0 + fit.CHROMA_EPS))
                               .expand(int((a.seen & ~even).sum()), 3))
    assert torch.equal(b.seen, a.seen)

    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    img = torch.stack([0.3 + 0.004 * xx, 0.3 + 0.003 * yy, 0.3 - 0.004 * xx - 0.003 * yy], -1)[None].expand(C, -1, -1, -1)
    g = torch.Generator().manual_seed(13)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, _, _ = render(rig, views, Gt)
    cues = cues._replace(image=img.clone())
    ref = fit.AnchorRef(0.33 + 0.05 * torch.rand(rig.rest.shape[0], 3, generator=g, dtype=torch.float64),
                        torch.rand(rig.rest.shape[0], generator=g) < 0.8)
    G0 = pose(rig, g, 0.03, 0.01, Gt)
    cfg = fit.FitConfig(w_mask=0.0, w_normal=0.0, w_flow=0.0, w_anchor=50.0, photo_blur=0.0, anchor_scale=0.02)
    pb = fit._make_problem(rig, views, cues, None, cfg, anchor=ref)
    ev = fit._evaluate(pb, lbs(rig.rest, rig.weights, G0))
    assert ev.anc is not None and ev.anc.cam.numel() > 40 and ev.loss > 0
    _, gvec = fit._gauss_newton(pb, ev, G0)
    d = torch.zeros(gvec.numel(), dtype=torch.float64, requires_grad=True)
    xd = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
    total, terms = fit.loss_terms(rig, views, cues, xd, None, cfg, fragments=ev.fragments, anchor=ref)
    assert abs(float(total.detach()) - ev.loss) < 1e-10 * ev.loss and float(terms["anchor"].detach()) > 0
    (grad,) = torch.autograd.grad(total, d)  # Cauchy: the IRLS gradient is the exact gradient
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-5, atol=1e-8 * float(gvec.abs().max()))


def test_texture_anchor_samples_the_blurred_texture_chromaticity_at_the_uvs():
    """texture_anchor: each vertex's reference is the chromaticity of the (blurred) texture at the
    UV of its first face corner; with no blur, a texel-centre UV reads that texel exactly."""
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(16, 20, 3, generator=g, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [2, 1, 3]])
    rows, cols = torch.tensor([3, 7, 12, 0]), torch.tensor([5, 19, 2, 11])
    uv_v = torch.stack([(cols + 0.5) / 20, 1 - (rows + 0.5) / 16], -1).double()  # texel centres (OBJ v up)
    face_uv = uv_v[faces].clone()
    face_uv[1, 0] = torch.tensor([0.9, 0.9])  # vertex 2 on a "seam": its first face's UV counts
    ref = fit.texture_anchor(faces, face_uv, tex, 0.0)
    assert ref.seen.all() and ref.chroma.shape == (4, 3)
    torch.testing.assert_close(ref.chroma, fit.chromaticity(tex[rows, cols]))
    # blurred: a constant texture is unchanged, a varying one is smoothed
    flat = fit.texture_anchor(faces, face_uv, torch.full((16, 20, 3), 0.4, dtype=torch.float64), 2.0)
    torch.testing.assert_close(flat.chroma, torch.full((4, 3), 0.4 / 1.25, dtype=torch.float64))
    blur = fit.texture_anchor(faces, face_uv, tex, 2.0)
    assert float(blur.chroma.std()) < float(ref.chroma.std())
    with pytest.raises(ValueError):
        fit.texture_anchor(faces, face_uv[:, :2], tex, 1.0)
    with pytest.raises(ValueError, match="no face"):  # a fifth vertex that no face uses
        fit.texture_anchor(faces, face_uv, tex, 1.0, num_vertices=5)


def test_texture_blur_matches_the_pixel_footprint():
    """A unit square textured over the whole texture, seen head-on from 2 m with focal 100 px:
    one pixel covers 2 cm = 0.02 * 512 texels; times sqrt(1/12 + blur^2)."""
    rest = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    face_uv = rest[:, :2][faces]
    K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]], dtype=torch.float64)
    E = torch.eye(4, dtype=torch.float64)[None].clone()
    E[0, 2, 3] = 2.0
    views = fit.Views(K, E, 100, 100)
    b = fit.texture_blur_texels(rest, faces, face_uv, (512, 512), rest, views, 0.5)
    assert abs(b - math.sqrt(1 / 12 + 0.25) * 0.02 * 512) < 1e-9


def test_anchor_sees_a_garment_sliding_about_its_axis():
    """A textured cone turning about its own axis: masks and normals do not change, so without
    flow the paper's loss cannot follow it; the chromaticity anchor (references from frame 0)
    does. Frame 0 starts at the truth."""
    rig, views = toy(C=4, H=80, W=80)

    def colour_of(p):
        th = torch.atan2(p[:, 1], p[:, 0])
        return torch.stack([0.5 + 0.4 * torch.sin(4 * th), 0.5 + 0.4 * torch.cos(3 * th + 8 * p[:, 2]),
                            0.5 + 0.3 * torch.sin(2 * th - 12 * p[:, 2])], -1)

    B = rig.weights.shape[1]

    def turned(a):
        R = torch.eye(4, dtype=torch.float64)
        R[0, 0], R[0, 1], R[1, 0], R[1, 1] = math.cos(a), -math.sin(a), math.sin(a), math.cos(a)
        return R.expand(B, 4, 4).clone()

    angles = [0.0, 0.06, 0.12, 0.18]
    frames = [textured(rig, views, turned(a), colour_of) for a in angles]
    G0 = turned(0.0)
    err = {}
    for name, cfg in (("paper", fit.FitConfig()), ("anchor", fit.FitConfig(w_anchor=fit.ANCHOR_WEIGHT))):
        res = fit.fit_sequence(rig, views, len(angles), lambda t: frames[t][0], lambda t: None, G0, cfg,
                               progress=False)
        err[name] = [rmse(r.verts, frames[t][1]) for t, r in enumerate(res)]
        assert all(torch.isfinite(r.transforms).all() for r in res)
    assert res[-1].terms["anchor"] > 0
    # the paper's loss stays near the start (the turn is 0.18 rad x ~0.25 m = ~45 mm at the hem)
    assert err["paper"][-1] > 0.03, err  # measured: 47 mm
    assert err["anchor"][-1] < 0.2 * err["paper"][-1], err  # measured: 3.5 mm


def test_flow_targets_follow_the_flow_and_skip_invalid_pixels():
    rig, views = toy(C=2, H=48, W=48)
    g = torch.Generator().manual_seed(3)
    G = pose(rig, g, 0.1, 0.02)
    cues, x, fr = render(rig, views, G)
    C, H, W = cues.mask.shape
    flow = torch.zeros(C, H, W, 2, dtype=torch.float64)
    flow[..., 0] = 1.5
    flow[..., 1] = -0.5
    valid = torch.ones(C, H, W, dtype=torch.bool)
    valid[0, :, : W // 2] = False
    flow[1, H // 2:, :, 0] = float("nan")
    ft = fit.flow_targets(x, views, fr, flow, valid, cues.mask)
    uv, _ = raster.project_vertices(x, views.K, views.world_to_cam)
    assert ft.cam.numel() > 30 and torch.isfinite(ft.target).all()
    assert fit.flow_targets(x, views, fr, flow, valid, cues.mask, margin=0).cam.numel() > ft.cam.numel()
    d = ft.target - uv[ft.cam, ft.vert]
    assert torch.allclose(d, torch.tensor([1.5, -0.5], dtype=torch.float64).expand_as(d))
    # no target from invalid or NaN pixels
    assert not bool(((ft.cam == 0) & (uv[ft.cam, ft.vert][:, 0].round() < W // 2)).any())
    assert not bool(((ft.cam == 1) & (uv[ft.cam, ft.vert][:, 1].round() >= H // 2)).any())
    vis = raster.visible_vertices(x, views.K, views.world_to_cam, fr)
    assert bool(vis[ft.cam, ft.vert].all())


# --------------------------------------------------------------------------------------
# recovery and robustness
# --------------------------------------------------------------------------------------


def test_recovers_known_bone_transforms_from_a_perturbed_start():
    rig, views = toy(C=4, H=80, W=80)
    g = torch.Generator().manual_seed(4)
    Gt = pose(rig, g, 0.15, 0.03)
    cues, xt, _ = render(rig, views, Gt)
    G0 = pose(rig, g, 0.06, 0.015, Gt)
    x0 = lbs(rig.rest, rig.weights, G0)
    e0 = rmse(x0, xt)
    # flow targets say where the visible vertices of the start went (as at frame t > 0)
    fr0 = raster.occlude(raster.rasterize(x0, rig.faces, views.K, views.world_to_cam, 80, 80), cues.occluder)
    ft = exact_flow(rig, views, x0, fr0, xt)
    r = fit.fit_frame(rig, views, cues, G0, fit.FitConfig(), flow=ft)
    assert rmse(r.verts, xt) < 0.1 * e0, (rmse(r.verts, xt), e0)  # binary masks: +-0.5 px per crossing
    assert r.converged and r.iterations <= fit.FitConfig().max_iters
    Rerr = (r.transforms[:, :3, :3] @ Gt[:, :3, :3].transpose(1, 2)).diagonal(dim1=1, dim2=2).sum(-1)
    assert float(torch.arccos(((Rerr - 1) / 2).clamp(-1, 1)).max()) < 0.02  # bone rotations within ~1 degree
    # silhouettes + normals alone (the first frame) lower the loss but pin the shape only loosely:
    # at 2.3 cm per pixel many bone configurations fit 4 binary masks as well as the truth
    r0 = fit.fit_frame(rig, views, cues, G0, fit.FitConfig(), first=True)
    start = fit._evaluate(fit._make_problem(rig, views, cues, None, fit.FitConfig()), x0).loss
    assert r0.loss < 0.7 * start and torch.isfinite(r0.transforms).all()
    assert rmse(r0.verts, xt) < e0


def test_empty_masks_nan_cues_and_missing_flow_give_finite_poses(caplog):
    rig, views = toy(C=4, H=48, W=48)
    g = torch.Generator().manual_seed(5)
    Gs = [pose(rig, g, 0.1, 0.02)]
    Gs += [pose(rig, g, 0.02, 0.005, Gs[-1]) for _ in range(2)]
    frames = [render(rig, views, G) for G in Gs]

    def cues_of(t):
        c, _, _ = frames[t]
        mask = c.mask.clone()
        mask[1:3] = False  # empty masks in two views
        n = c.normals.clone()
        n[0, :10] = float("nan")  # NaN in a cue
        return fit.FrameCues(mask, n, c.occluder)

    def flow_of(t):
        if t == 1:
            return None  # a frame without flow
        C, H, W = frames[0][0].mask.shape
        f = torch.zeros(C, H, W, 2, dtype=torch.float64)
        f[0, 5:9] = float("nan")
        return f, None

    start = pose(rig, g, 0.03, 0.01, Gs[0])
    with caplog.at_level(logging.WARNING, logger="anidress.test"):
        res = fit.fit_sequence(rig, views, 3, cues_of, flow_of, start, fit.FitConfig(max_iters=5, max_iters_first=5),
                               progress=False, log=logging.getLogger("anidress.test"))
    assert len(res) == 3
    assert "frame 1 has no flow" in caplog.text
    assert res[1].terms["flow_targets"] == 0 and res[2].terms["flow_targets"] > 0
    for r in res:
        assert torch.isfinite(r.transforms).all() and torch.isfinite(r.verts).all() and math.isfinite(r.loss)
    # with the temporal filter on: the same per-frame fits, then smooth_transforms over the sequence
    sm = fit.fit_sequence(rig, views, 3, cues_of, flow_of, start,
                          fit.FitConfig(max_iters=5, max_iters_first=5, smooth_passes=1), progress=False)
    want = fit.smooth_transforms(torch.stack([r.transforms for r in res]), 1)
    torch.testing.assert_close(torch.stack([r.transforms for r in sm]), want)
    torch.testing.assert_close(sm[1].verts, lbs(rig.rest, rig.weights, want[1]))
    # all masks empty: still finite (the silhouette pushes the garment out of the views or stays)
    empty = fit.FrameCues(torch.zeros_like(frames[0][0].mask), None, frames[0][0].occluder)
    r = fit.fit_frame(rig, views, empty, start, fit.FitConfig(max_iters_first=5), first=True)
    assert torch.isfinite(r.transforms).all()
    # a NaN start is refused with a clear error
    bad = start.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        fit.fit_frame(rig, views, frames[0][0], bad)
    with pytest.raises(ValueError, match="mask must be"):
        fit.fit_frame(rig, views, fit.FrameCues(frames[0][0].mask[:, :10], None, frames[0][0].occluder), start)


def test_body_occlusion_is_respected():
    """A garment pixel hidden by an occluder is not garment: fitting to occluded masks keeps the pose."""
    rig, views = toy(C=2, H=64, W=64)
    g = torch.Generator().manual_seed(6)
    Gt = pose(rig, g, 0.1, 0.02)
    x = lbs(rig.rest, rig.weights, Gt)
    fr = raster.rasterize(x, rig.faces, views.K, views.world_to_cam, 64, 64)
    occ = torch.full_like(fr.depth, float("inf"))
    occ[:, :, 20:34] = 1.0  # a vertical bar in front of the garment ("an arm")
    cues, _, _ = render(rig, views, Gt, occluder=occ)
    assert not bool(cues.mask[:, :, 20:34].any()) and bool(cues.mask.any())
    pb = fit._make_problem(rig, views, cues, None, fit.FitConfig())
    ev = fit._evaluate(pb, x)
    # at the true pose the silhouette residual is only the sub-pixel coverage of crossed pixels
    assert ev.terms["mask"] < 0.5
    un = fit._make_problem(rig, views, fit.FrameCues(cues.mask, cues.normals, torch.full_like(occ, float("inf"))),
                           None, fit.FitConfig())
    assert fit._evaluate(un, x).terms["mask"] > 5 * ev.terms["mask"]  # ignoring the occluder is much worse


def test_ablation_names_agree_everywhere():
    """The rule fit_ablation, the config schema and the CLI accept exactly fit.ABLATIONS."""
    import argparse
    import re
    from pathlib import Path

    import yaml

    from anidress_core.cli import build_parser

    root = Path(__file__).resolve().parents[1]
    smk = re.search(r"^FIT_ABLATIONS = (\[.*?\])$", (root / "workflow/rules/fit.smk").read_text(), re.M)
    assert smk is not None and sorted(yaml.safe_load(smk.group(1))) == sorted(fit.ABLATIONS)
    schema = yaml.safe_load((root / "workflow/schemas/config.schema.yaml").read_text())
    assert sorted(schema["properties"]["fit"]["properties"]["ablations"]["items"]["enum"]) == sorted(fit.ABLATIONS)
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    opt = next(a for a in sub.choices["fit"]._actions if "--ablation" in a.option_strings)
    assert sorted(opt.choices) == sorted(fit.ABLATIONS)


def test_ablation_configs_and_vertex_fit():
    base = fit.FitConfig()
    assert fit.config_for(base, None) == base and fit.config_for(base, "full") == base
    assert fit.config_for(base, "no_flow").w_flow == 0 and fit.config_for(base, "no_flow").w_normal == 0.1
    nf = fit.config_for(base, "no_normal_flow")
    assert nf.w_flow == 0 and nf.w_normal == 0 and nf.w_mask == 2.0
    assert fit.config_for(base, "vertex").method == "vertex"
    ph = fit.FitConfig(w_photo=10.0)
    assert fit.config_for(ph, "photo") == ph and fit.config_for(base, "photo").w_photo == fit.PHOTO_WEIGHT
    assert fit.config_for(ph, "no_flow").w_photo == 0 and fit.config_for(ph, "no_normal_flow").w_photo == 0
    an = fit.FitConfig(w_anchor=10.0, w_photo=5.0)
    assert fit.config_for(an, "anchor") == an and fit.config_for(base, "anchor").w_anchor == fit.ANCHOR_WEIGHT
    col = fit.config_for(base, "collision")
    assert col.w_collision == fit.COLLISION_WEIGHT and col.w_anchor == fit.ANCHOR_WEIGHT and col.smooth_passes == 1
    mine = fit.FitConfig(w_anchor=10.0, w_collision=5.0)
    assert fit.config_for(mine, "collision").w_collision == 5.0 and fit.config_for(mine, "collision").w_anchor == 10.0
    for abl in ("vertex", "no_flow", "no_normal_flow"):  # the paper's ablations: the paper's loss, no term of ours
        c = fit.config_for(fit.FitConfig(w_anchor=10.0, w_photo=5.0, w_collision=5.0), abl)
        assert c.w_anchor == 0 and c.w_photo == 0 and c.w_collision == 0
    with pytest.raises(ValueError):
        fit.config_for(base, "nope")
    rig, views = toy(C=3, H=48, W=48, n_theta=20, n_h=6)
    g = torch.Generator().manual_seed(7)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, _ = render(rig, views, Gt)
    G0 = pose(rig, g, 0.04, 0.01, Gt)
    r = fit.fit_frame(rig, views, cues, G0, fit.config_for(fit.FitConfig(vertex_max_iters=10), "vertex"))
    assert torch.equal(r.transforms, G0)  # the vertex method does not move bones
    assert r.loss < r.curve[0] and torch.isfinite(r.verts).all() and r.iterations <= 10


# --------------------------------------------------------------------------------------
# stage: a tiny synthetic skirt scene end to end (rig from its own ground truth)
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_skirt(tmp_path_factory):
    import numpy as np
    import yaml

    from anidress_core import rig as R
    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.io import files
    from anidress_core.io.mesh import read_mesh
    from anidress_core.metrics.mesh import barycentric_transfer
    from anidress_core.stages.fit import gt_correspondence
    from anidress_core.io.scene import load_body, read_scene
    from anidress_core.stages.synth import run_synth
    from anidress_core.stages.template import run_template

    root = tmp_path_factory.mktemp("fitscene")
    scene = {"kind": "skirt", "image_size": [64, 64], "cameras": {"count": 6, "train": 4},
             "sequences": [{"name": "walk", "motion": "walk", "frames": 4}],
             "garment": {"vertices": 500, "cloth": {"settle_frames": 4}},
             "render": {"texture_size": 64, "noise_std": 0.0, "supersample": 1}}
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": scene}}, yaml.safe_load(default_schema_path().read_text()))
    data = run_synth(cfg["scenes"]["s"], "s", root / "data" / "s", threads=1, progress=False)
    info = read_scene(data)
    res = root / "results"
    tpl = run_template(data / "garment" / "template.obj", "skirt", load_body(data, info), 500, res / "template.ply",
                       res / "template.npz")
    # a 6-bone rig decomposed from the ground truth carried onto the template (stands in for rule rig)
    a, _ = files.load_npz(data / "walk" / "gt" / "meshes.npz")
    rv, rf, _ = read_mesh(data / "garment" / "template.obj")
    face, bary, _ = gt_correspondence(tpl.verts, rv, rf)
    Y = barycentric_transfer(torch.as_tensor(a["garment_vertices"]).double(), torch.as_tensor(rf),
                             torch.as_tensor(face), torch.as_tensor(bary))
    model = R.ssdr(torch.as_tensor(tpl.verts).double(), Y, torch.as_tensor(tpl.faces), num_bones=6, iters=5, nnz=4)
    files.save_npz(res / "rig.npz", {
        "rest": tpl.verts.astype(np.float32), "faces": tpl.faces.astype(np.int64),
        "weights": model.weights.float().numpy(), "bone_centres": model.bone_centres.float().numpy(),
        "transforms": model.transforms.float().numpy(), "sequences": np.asarray(["seq-walk"]),
        "offsets": np.asarray([0, Y.shape[0]], np.int64), "rmse_per_sequence": np.asarray([model.rmse]),
        "rmse": np.float64(model.rmse)})
    return data, res


def test_stage_fit_and_eval_on_a_tiny_scene(tiny_skirt):
    import csv

    import numpy as np

    from anidress_core.stages.fit import FIT_METRIC_COLUMNS, load_garment_poses, run_fit, run_fit_eval

    data, res = tiny_skirt
    seq = data / "walk"
    params = {"views": 3, "max_iters": 4, "max_iters_first": 6}
    meta = run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
                   seq / "normals", params, res / "walk" / "garment_poses.npz", progress=False)
    a, h = load_garment_poses(res / "walk" / "garment_poses.npz")
    assert a["transforms"].shape == (4, 6, 4, 4) and a["transforms"].dtype == np.float32
    assert a["verts"].shape == (4, 500, 3) and np.isfinite(a["verts"]).all()
    assert a["curve"].shape[0] == 4 and a["iterations"].shape == (4,) and (a["flow_targets"][1:] > 0).all()
    assert a["flow_targets"][0] == 0 and len(meta["cameras"]) == 3
    assert meta["config"]["w_photo"] == 0.0 and (a["loss_photo"] == 0).all()  # the paper's loss by default
    assert meta["config"]["w_anchor"] == 0.0 and (a["loss_anchor"] == 0).all()
    assert h["meta"]["first_frame_start"].startswith("rig transforms of the simulated sequence seq-walk")
    # the fitted transforms reproduce the fitted vertices through the rig (the field stage's contract)
    from anidress_core.io.rig import read_rig
    from anidress_core.geometry import lbs

    art = read_rig(res / "rig.npz", dtype=torch.float64)
    x = lbs(art.model.rest, art.model.weights, torch.as_tensor(a["transforms"]).double())
    assert float((x - torch.as_tensor(a["verts"]).double()).abs().max()) < 1e-4
    # the photo variant reads the images; the no-flow ablation; the evaluation
    meta = run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
                   seq / "normals", params, res / "walk" / "photo.npz", ablation="photo", progress=False)
    assert meta["config"]["w_photo"] == fit.PHOTO_WEIGHT
    assert (load_garment_poses(res / "walk" / "photo.npz")[0]["loss_photo"] > 0).all()
    meta = run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
                   seq / "normals", params, res / "walk" / "anchor.npz", ablation="anchor", progress=False)
    an = load_garment_poses(res / "walk" / "anchor.npz")[0]["loss_anchor"]
    assert meta["config"]["w_anchor"] == fit.ANCHOR_WEIGHT and an[0] == 0 and (an[1:] > 0).all()  # refs from frame 0
    # references from the garment texture: L_an is on from frame 0; without a texture, a clear error
    meta = run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
                   seq / "normals", params, res / "walk" / "anchor_texture.npz", ablation="anchor_texture",
                   progress=False)
    an = load_garment_poses(res / "walk" / "anchor_texture.npz")[0]["loss_anchor"]
    assert (an > 0).all() and "texture.png" in meta["anchor_reference"]
    assert meta["config"]["smooth_passes"] == 1
    tex = data / "garment" / "texture.png"
    tex.rename(tex.with_suffix(".bak"))
    try:
        with pytest.raises(FileNotFoundError, match="texture"):
            run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
                    seq / "normals", dict(params, anchor_reference="texture", weights={"anchor": 1.0e5}),
                    res / "walk" / "x.npz", progress=False)
    finally:
        tex.with_suffix(".bak").rename(tex)
    run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "gt" / "masks", seq / "gt" / "flows",
            None, params, res / "walk" / "no_flow.npz", ablation="no_flow", progress=False)
    summ = run_fit_eval(data, "walk", res / "rig.npz", {"full": res / "walk" / "garment_poses.npz",
                                                         "no_flow": res / "walk" / "no_flow.npz"},
                        res / "walk" / "fit_metrics.csv", samples=500)
    with open(res / "walk" / "fit_metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == FIT_METRIC_COLUMNS and len(rows) == 8
    assert summ["correspondence_max_m"] < 0.01
    for r in rows:
        assert 0 <= float(r["vertex_rmse_m"]) < 0.1 and 0 < float(r["normal_consistency"]) <= 1
        assert float(r["rig_floor_rmse_m"]) < 0.05
        assert 0 <= float(r["rig_floor_chamfer_m"]) < 0.1
    # the floor's Chamfer (with its sampling bias) is one reference per frame, the same for every method
    per_frame = {}
    for r in rows:
        per_frame.setdefault(r["frame"], set()).add(r["rig_floor_chamfer_m"])
    assert all(len(v) == 1 for v in per_frame.values())
    # a missing mask is named in the error
    with pytest.raises(FileNotFoundError, match="mask"):
        run_fit(data, "walk", res / "rig.npz", res / "template.npz", seq / "nope", None, None, params,
                res / "walk" / "x.npz", progress=False)


def test_crop_windows_and_pyramid_keep_the_loss():
    """Rendering windows around the garment gives the loss of the whole images; a reduced
    level's soft masks are the block means."""
    rig, views = toy(C=3, H=64, W=72)
    g = torch.Generator().manual_seed(8)
    Gt = pose(rig, g, 0.1, 0.02)
    cues, xt, fr = render(rig, views, Gt)
    x = lbs(rig.rest, rig.weights, pose(rig, g, 0.03, 0.01, Gt))
    uv, _ = raster.project_vertices(xt, views.K, views.world_to_cam)
    ft = fit.FlowTargets(torch.tensor([0, 1, 2]), torch.tensor([3, 40, 100]), uv[[0, 1, 2], [3, 40, 100]])
    cfg = fit.FitConfig()
    whole = fit._evaluate(fit._make_problem(rig, views, cues, ft, cfg), x)
    win = fit.crop_window(views, cues.mask, x, 4)
    assert win.height < 64 and win.width < 72
    v2, c2, f2 = fit.crop_frame(views, cues, ft, win)
    part = fit._evaluate(fit._make_problem(rig, v2, c2, f2, cfg), x)
    assert abs(part.loss - whole.loss) < 1e-9 * whole.loss
    back = fit.uncrop_fragments(part.fragments, win, 64, 72, cues.occluder)
    assert torch.equal(back.face_id, whole.fragments.face_id)
    v4, c4, f4 = fit.downsample(views, cues, ft, 4)
    assert (v4.height, v4.width) == (16, 18) and c4.mask.dtype == torch.float64
    torch.testing.assert_close(c4.mask[0, 3, 5], cues.mask[0, 12:16, 20:24].double().mean())
    # a pixel centre maps to the centre of its block: fine (u, v) -> ((u - 1.5) / 4, (v - 1.5) / 4)
    uv4, _ = raster.project_vertices(xt, v4.K, v4.world_to_cam)
    torch.testing.assert_close(uv4, (uv - 1.5) / 4)
    torch.testing.assert_close(f4.target, (ft.target - 1.5) / 4)


def test_collision_term_gradient_is_exact_and_pushes_the_garment_out():
    """L_col (body collision, point-to-plane at the frame's start): the Gauss-Newton gradient equals
    autograd's; a fit with it moves the vertices that a sphere 'body' pokes through back out to the
    clearance, a fit without it leaves them inside; without the body mesh it is a clear error."""
    pytest.importorskip("warp")
    from anidress_core.sim.metrics import penetration_depth

    rig, views = toy(C=4, H=64, W=64, n_theta=32, n_h=10)
    G = torch.eye(4, dtype=torch.float64).expand(rig.weights.shape[1], 4, 4).clone()
    x = lbs(rig.rest, rig.weights, G)
    from tests.sim.skirt import sphere_body

    bv, bf, _ = (torch.as_tensor(a) for a in sphere_body(0.1, (0.33, 0.0, 0.75)))  # pokes through the
    # cone's side, at most 3 cm deep
    inside = penetration_depth(x[None], bv[None], bf)[0] > 0
    assert int(inside.sum()) >= 5
    cfg = fit.FitConfig(w_mask=0.0, w_normal=0.0, w_flow=0.0, w_collision=1e3, collision_eps=0.005)
    contacts = fit.body_contacts(x, bv, bf, cfg.collision_radius)
    cues = fit.FrameCues(torch.zeros(4, 64, 64, dtype=torch.bool), None, None, (bv, bf))
    g = torch.Generator().manual_seed(4)
    G0 = pose(rig, g, 0.02, 0.005, G)
    pb = fit._make_problem(rig, views, cues, None, cfg, contacts=contacts)
    ev = fit._evaluate(pb, lbs(rig.rest, rig.weights, G0))
    assert ev.terms["collision"] > 0
    H, gvec = fit._gauss_newton(pb, ev, G0)
    d = torch.zeros(gvec.numel(), dtype=torch.float64, requires_grad=True)
    xd = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, d.view(-1, 6)))
    total, terms = fit.loss_terms(rig, views, cues, xd, None, cfg, fragments=ev.fragments, contacts=contacts)
    assert abs(float(total.detach()) - ev.loss) < 1e-10 * ev.loss
    (grad,) = torch.autograd.grad(total, d)
    torch.testing.assert_close(grad, 2 * gvec, rtol=1e-6, atol=1e-9 * float(gvec.abs().max()))
    # the Gauss-Newton matrix is J^T J of the active residuals (sqrt(w / V) (eps - d)): exact here
    def residuals(dd):
        xx = lbs(rig.rest, rig.weights, fit.apply_increment(G0, rig.centres, dd.view(-1, 6)))
        r = fit._collision_residual(contacts, xx, cfg.collision_eps)
        return r * (cfg.w_collision / xx.shape[0]) ** 0.5
    d0 = torch.zeros(gvec.numel(), dtype=torch.float64)
    J = torch.func.jacfwd(residuals)(d0)
    torch.testing.assert_close(H, J.t() @ J, rtol=1e-6, atol=1e-9 * float(H.abs().max()))

    # fits of the cone's own silhouette and normals from its pose: L_col pushes the poked vertices out
    seen = render(rig, views, G)[0]._replace(occluder_mesh=(bv, bf))
    full = fit.FitConfig(w_flow=0.0, w_collision=1e6, collision_eps=0.005)
    out = fit.fit_frame(rig, views, seen, G, full)
    depth = penetration_depth(out.verts[None], bv[None], bf)[0]
    assert float(depth.max()) < 2e-3 and int((depth > 0).sum()) < int(inside.sum()) // 2
    still = fit.fit_frame(rig, views, seen, G, dataclasses.replace(full, w_collision=0.0))
    assert int((penetration_depth(still.verts[None], bv[None], bf)[0] > 0).sum()) >= int(inside.sum()) - 1
    with pytest.raises(ValueError, match="occluder_mesh"):
        fit.fit_frame(rig, views, cues._replace(occluder_mesh=None), G, cfg)
