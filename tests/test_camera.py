"""Cameras: projection vs OpenCV, unprojection and rays, rigs, files."""
import math

import cv2
import numpy as np
import pytest
import torch

from anidress_core import camera as cm
from anidress_core.camera import Cameras

F64 = torch.float64


def _rig(C=3, dtype=F64, seed=0, distortion=True, H=48, W=64):
    """C cameras on a ring of radius ~3 around the origin, random intrinsics/distortion."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.arange(C, dtype=F64) * (2 * math.pi / C) + 0.3
    eye = torch.stack([3 * torch.cos(ang), 3 * torch.sin(ang), 1.0 + 0.5 * torch.rand(C, generator=g, dtype=F64)], -1)
    target = 0.2 * torch.randn(C, 3, generator=g, dtype=F64)
    R, T = cm.look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    K = torch.zeros(C, 3, 3, dtype=F64)
    K[:, 0, 0] = 60 + 10 * torch.rand(C, generator=g, dtype=F64)
    K[:, 1, 1] = 60 + 10 * torch.rand(C, generator=g, dtype=F64)
    K[:, 0, 2] = (W - 1) / 2 + torch.randn(C, generator=g, dtype=F64)
    K[:, 1, 2] = (H - 1) / 2 + torch.randn(C, generator=g, dtype=F64)
    K[:, 2, 2] = 1
    dist = torch.zeros(C, 5, dtype=F64)
    if distortion:
        dist = torch.tensor([-0.2, 0.05, 1e-3, -2e-3, 0.01], dtype=F64) * (1 + 0.3 * torch.randn(C, 5, generator=g, dtype=F64))
    return Cameras([f"{i + 1:02d}" for i in range(C)], K, dist, R, T, H, W).to(dtype=dtype)


def _points(N=50, seed=1):
    g = torch.Generator().manual_seed(seed)
    return 0.6 * torch.randn(N, 3, generator=g, dtype=F64)


def test_project_matches_cv2_project_points():
    cams, X = _rig(), _points()
    proj = cm.project(X, cams)
    assert proj.uv.shape == (3, 50, 2) and proj.depth.shape == (3, 50)
    for c in range(len(cams)):
        rvec = cv2.Rodrigues(cams.R[c].numpy())[0]
        ref, _ = cv2.projectPoints(X.numpy(), rvec, cams.T[c].numpy(), cams.K[c].numpy(), cams.dist[c].numpy())
        assert np.abs(proj.uv[c].numpy() - ref[:, 0]).max() < 1e-6
        ref0, _ = cv2.projectPoints(X.numpy(), rvec, cams.T[c].numpy(), cams.K[c].numpy(), np.zeros(5))
        assert np.abs(cm.project(X, cams, distort=False).uv[c].numpy() - ref0[:, 0]).max() < 1e-6
    # depth is the camera-frame z
    Xc = X @ cams.R[0].T + cams.T[0]
    torch.testing.assert_close(proj.depth[0], Xc[:, 2])


def test_project_per_camera_points_and_float32():
    cams, X = _rig(), _points()
    shared = cm.project(X, cams).uv
    per_cam = cm.project(X.expand(3, -1, -1), cams).uv
    torch.testing.assert_close(shared, per_cam)
    uv32 = cm.project(X.float(), cams.to(dtype=torch.float32)).uv
    assert uv32.dtype == torch.float32
    torch.testing.assert_close(uv32.double(), shared, atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(3, N, 3\).*\(2, 5, 3\)"):
        cm.project(torch.zeros(2, 5, 3, dtype=F64), cams)


def test_project_zero_depth_is_finite():
    cams = _rig(C=1, distortion=False)
    # a point in the camera's own z = 0 plane
    X = cm.unproject(torch.tensor([[[10.0, 10.0]]], dtype=F64), torch.ones(1, 1, dtype=F64), cams)
    X = X[0] - 1.0 * (cams.R[0, 2])  # step back along the optical axis to depth 0
    p = cm.project(X, cams)
    assert torch.isfinite(p.uv).all() and abs(float(p.depth)) < 1e-12


def _undistort_reference(xy, dist, iters):
    """Slow per-point fixed-point loop, written from the OpenCV model."""
    k1, k2, p1, p2, k3 = dist
    out = []
    for x0, y0 in xy:
        x, y = x0, y0
        for _ in range(iters):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = (x0 - dx) / radial, (y0 - dy) / radial
        out.append((x, y))
    return np.array(out)


def test_undistort_matches_cv2_undistort_points():
    cams = _rig()
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(3, 40, 2, generator=g, dtype=F64) * torch.tensor([63.0, 47.0], dtype=F64)
    # distorted normalised coordinates (x, y, 1) = K^-1 (u, v, 1)
    xy_d = torch.linalg.solve(cams.K[:, None], torch.cat([uv, torch.ones_like(uv[..., :1])], -1)[..., None])[..., :2, 0]
    for iters in (5, 20):
        xy = cm.undistort_normalized(xy_d, cams.dist, iters=iters)
        crit = (cv2.TERM_CRITERIA_COUNT, iters, 0.0)
        for c in range(3):
            K, d = cams.K[c].numpy(), cams.dist[c].numpy()
            ref = cv2.undistortPoints(uv[c].numpy()[:, None, :], K, d, criteria=crit)[:, 0]
            assert np.abs(xy[c].numpy() - ref).max() < 1e-9
            slow = _undistort_reference(xy_d[c].numpy(), d, iters)
            assert np.abs(xy[c].numpy() - slow).max() < 1e-12
    # OpenCV's default (5 iterations)
    ref = cv2.undistortPoints(uv[0].numpy()[:, None, :], cams.K[0].numpy(), cams.dist[0].numpy())[:, 0]
    assert np.abs(cm.undistort_normalized(xy_d, cams.dist, iters=5)[0].numpy() - ref).max() < 1e-9
    # converged: distorting again gives back the input
    back = cm.distort_normalized(cm.undistort_normalized(xy_d, cams.dist), cams.dist)
    torch.testing.assert_close(back, xy_d, atol=1e-12, rtol=0)


def test_unproject_inverts_project():
    cams, X = _rig(), _points()
    for distort in (True, False):
        p = cm.project(X, cams, distort=distort)
        Y = cm.unproject(p.uv, p.depth, cams, distorted=distort)
        assert Y.shape == (3, 50, 3)
        torch.testing.assert_close(Y, X.expand(3, -1, -1), atol=1e-10, rtol=0)
    with pytest.raises(ValueError, match="depth must be"):
        cm.unproject(p.uv, p.depth[:, :3], cams)


def test_pixel_rays_hit_their_pixels():
    cams = _rig(H=12, W=16)
    rays = cm.pixel_rays(cams)
    assert rays.origins.shape == rays.directions.shape == (3, 12, 16, 3)
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(3, 12, 16, dtype=F64))
    torch.testing.assert_close(rays.origins, cams.centers[:, None, None].expand(-1, 12, 16, -1))
    # a point 2.5 m along each ray lands on its pixel centre (u = j, v = i)
    pts = (rays.origins + 2.5 * rays.directions).reshape(3, -1, 3)
    uv = cm.project(pts, cams).uv.reshape(3, 12, 16, 2)
    v, u = torch.meshgrid(torch.arange(12, dtype=F64), torch.arange(16, dtype=F64), indexing="ij")
    torch.testing.assert_close(uv, torch.stack([u, v], -1).expand(3, -1, -1, -1), atol=1e-8, rtol=0)
    # rays_for_pixels agrees on a subset; shared (N, 2) pixels work too
    sub = torch.tensor([[3.0, 4.0], [15.0, 0.0]], dtype=F64)
    r = cm.rays_for_pixels(cams, sub)
    torch.testing.assert_close(r.directions[:, 0], rays.directions[:, 4, 3])
    torch.testing.assert_close(r.directions[:, 1], rays.directions[:, 0, 15])
    # a crop: top-left corner only
    assert cm.pixel_rays(cams, height=2, width=3).directions.shape == (3, 2, 3, 3)


def test_project_gradcheck():
    cams = _rig(C=2)
    X = _points(N=6).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: cm.project(x, cams).uv, (X,))
    K, dist, R, T = (t.clone().requires_grad_(True) for t in (cams.K, cams.dist, cams.R, cams.T))

    def f(K, dist, R, T):
        c = Cameras(cams.names, K, dist, R, T, cams.height, cams.width)
        p = cm.project(X.detach(), c)
        return p.uv, p.depth

    assert torch.autograd.gradcheck(f, (K, dist, R, T))


def test_unproject_and_rays_gradcheck():
    cams = _rig(C=2)
    uv = cm.project(_points(N=4), cams).uv.detach().requires_grad_(True)
    depth = torch.full((2, 4), 3.0, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: cm.unproject(a, b, cams), (uv, depth))
    dist = cams.dist.clone().requires_grad_(True)

    def dirs(uv, dist):
        c = Cameras(cams.names, cams.K, dist, cams.R, cams.T, cams.height, cams.width)
        return cm.rays_for_pixels(c, uv).directions

    assert torch.autograd.gradcheck(dirs, (uv, dist))


def test_look_at_is_a_proper_opencv_pose():
    eye = torch.tensor([[2.0, -3.0, 1.5], [0.0, 4.0, 0.2]], dtype=F64)
    target = torch.tensor([0.1, 0.2, 1.0], dtype=F64)
    R, T = cm.look_at(eye, target, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(2, 3, 3))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, dtype=F64))
    # eye -> camera origin; target on the +z axis
    torch.testing.assert_close(torch.einsum("cij,cj->ci", R, eye) + T, torch.zeros(2, 3, dtype=F64))
    t_cam = torch.einsum("cij,j->ci", R, target) + T
    torch.testing.assert_close(t_cam[:, :2], torch.zeros(2, 2, dtype=F64))
    assert (t_cam[:, 2] > 0).all()
    # world up maps to image up (negative camera y)
    assert (R[:, 1, 2] < 0).all()
    with pytest.raises(ValueError, match="parallel to up"):
        cm.look_at(torch.tensor([0.0, 0.0, 5.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))


def test_ring_cameras_look_at_target():
    target = (0.1, -0.2, 0.9)
    cams = cm.ring_cameras(6, radius=3.0, height=1.6, target=target, focal_px=500.0,
                           image_height=480, image_width=640, dtype=F64)
    assert cams.names == ["01", "02", "03", "04", "05", "06"] and len(cams) == 6
    assert (cams.height, cams.width) == (480, 640)
    p = cm.project(torch.tensor([target], dtype=F64), cams)
    torch.testing.assert_close(p.uv[:, 0], torch.tensor([[319.5, 239.5]], dtype=F64).expand(6, 2))
    c = cams.centers
    torch.testing.assert_close(c[:, 2], torch.full((6,), 1.6, dtype=F64))
    torch.testing.assert_close((c[:, :2] - torch.tensor(target[:2], dtype=F64)).norm(dim=-1),
                               torch.full((6,), 3.0, dtype=F64))
    # evenly spaced: first camera on +x from the target, the next 60 degrees on
    torch.testing.assert_close(c[0, :2], torch.tensor([3.1, -0.2], dtype=F64))
    torch.testing.assert_close(c[1, :2] - torch.tensor(target[:2], dtype=F64),
                               3.0 * torch.tensor([0.5, math.sqrt(3) / 2], dtype=F64))
    # a point above the target appears above the image centre
    above = cm.project(torch.tensor([[0.1, -0.2, 1.4]], dtype=F64), cams).uv[:, 0]
    assert (above[:, 1] < 239.5).all()
    assert cm.ring_cameras(2, 1.0, 1.0, (0, 0, 0), 10.0, 4, 4, names=["a", "b"]).K.dtype == torch.float32


def test_cameras_container():
    cams = _rig(C=3)
    torch.testing.assert_close(cams.world_to_cam @ cams.cam_to_world, torch.eye(4, dtype=F64).expand(3, 4, 4))
    torch.testing.assert_close(cams.cam_to_world[:, :3, 3], cams.centers)
    sub = cams.select(["03", "01"])
    assert sub.names == ["03", "01"] and len(sub) == 2
    torch.testing.assert_close(sub.K[0], cams.K[2])
    assert cams.select([1]).names == ["02"] and cams.select("02").names == ["02"]
    assert cams.select(torch.tensor([2, 0])).names == ["03", "01"]
    with pytest.raises(ValueError, match="'zz'"):
        cams.select(["zz"])
    f32 = cams.to(dtype=torch.float32)
    assert f32.R.dtype == f32.T.dtype == torch.float32 and cams.R.dtype == F64
    with pytest.raises(ValueError, match=r"dist must be \(3, 5\).*\(3, 4\)"):
        Cameras(cams.names, cams.K, cams.dist[:, :4], cams.R, cams.T, 48, 64)
    with pytest.raises(ValueError, match="unique"):
        Cameras(["a", "a", "b"], cams.K, cams.dist, cams.R, cams.T, 48, 64)
    with pytest.raises(ValueError, match="height"):
        Cameras(cams.names, cams.K, cams.dist, cams.R, cams.T, 0, 64)
    with pytest.raises(ValueError, match="T is torch.float32"):
        Cameras(cams.names, cams.K, cams.dist, cams.R, cams.T.float(), 48, 64)


def test_scaled_follows_pixel_centre_convention():
    cams, X = _rig(H=48, W=64), _points()
    for factor, (h, w) in ((0.5, (24, 32)), (2.0, (96, 128)), (0.25, (12, 16))):
        s = cams.scaled(factor)
        assert (s.height, s.width) == (h, w)
        # the same world point moves to u' = f (u + 0.5) - 0.5 (image borders stay borders)
        torch.testing.assert_close(cm.project(X, s).uv, factor * (cm.project(X, cams).uv + 0.5) - 0.5)
    with pytest.raises(ValueError, match="factor"):
        cams.scaled(0.0)


def test_save_load_round_trip(tmp_path):
    cams = _rig()
    cm.save_cameras(cams, tmp_path / "intri.yml", tmp_path / "extri.yml")
    back = cm.load_cameras(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert back.names == cams.names and (back.height, back.width) == (48, 64)
    for k in ("K", "dist", "R", "T"):
        assert torch.equal(getattr(back, k), getattr(cams, k)), k
    sub = cm.load_cameras(tmp_path / "intri.yml", tmp_path / "extri.yml", names=["02"], dtype=torch.float32)
    assert sub.names == ["02"] and sub.K.dtype == torch.float32
    with pytest.raises(ValueError, match=r"intri\.yml.*'H_<cam>' is 48 but height=50"):
        cm.load_cameras(tmp_path / "intri.yml", tmp_path / "extri.yml", height=50)


def test_load_without_image_size(tmp_path):
    from anidress_core.io import easymocap as em

    cams = _rig(C=2)
    raw = {n: {"K": cams.K[i].numpy(), "dist": cams.dist[i].numpy(), "R": cams.R[i].numpy(),
               "T": cams.T[i].numpy()} for i, n in enumerate(cams.names)}
    em.write_camera(tmp_path / "intri.yml", tmp_path / "extri.yml", raw)
    with pytest.raises(ValueError, match=r"intri\.yml.*no 'H_<cam>'.*height"):
        cm.load_cameras(tmp_path / "intri.yml", tmp_path / "extri.yml")
    back = cm.load_cameras(tmp_path / "intri.yml", tmp_path / "extri.yml", height=48, width=64)
    assert (back.height, back.width) == (48, 64)
