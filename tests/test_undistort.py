"""anidress_core.undistort: lookup maps against OpenCV (initUndistortRectifyMap, projectPoints,
undistortPoints) to < 1e-2 px, and the remapping of images, label masks and normal maps."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from anidress_core.camera import Cameras, distort_normalized, project, ring_cameras, undistort_normalized, unproject
from anidress_core.undistort import (distorted_camera_names, undistort_image, undistort_labels, undistort_maps,
                                     undistort_normals, working_cameras)

H, W = 48, 64
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)  # undistortPoints to convergence


def undistort_points(uv: np.ndarray, K, D, P=None) -> np.ndarray:
    """cv2.undistortPoints (N, 2) pixels -> (N, 2), iterated to convergence (its default is 5 steps)."""
    return cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, D, None, P, criteria=CRIT).reshape(-1, 2)
DIST = torch.tensor([[-0.25, 0.08, 1e-3, -5e-4, -0.01],  # barrel, as a wide lens
                     [0.12, -0.03, -8e-4, 6e-4, 0.0],    # pincushion
                     [0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)


def rig(dist=DIST) -> Cameras:
    cams = ring_cameras(3, 3.0, 1.0, (0, 0, 0.9), focal_px=50.0, image_height=H, image_width=W, dtype=torch.float64)
    K = cams.K.clone()
    K[:, 0, 2] += torch.tensor([1.3, -2.1, 0.0])  # principal points off the centre
    K[:, 1, 1] *= torch.tensor([1.02, 0.97, 1.0])
    return Cameras(cams.names, K, dist.clone(), cams.R, cams.T, H, W)


def grid() -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([u, v], -1)  # (H, W, 2) working pixel centres


@pytest.mark.parametrize("new_focal", [1.0, 0.8])
def test_maps_equal_opencv(new_focal):
    cams = rig()
    K_new = cams.K.clone()
    K_new[:, :2, :2] *= new_focal
    maps = undistort_maps(cams.K, cams.dist, H, W, K_new)
    assert maps.map_x.shape == (3, H, W) and maps.map_x.dtype == np.float32 and maps.valid.dtype == bool
    for c in range(3):
        K, D, Kn = cams.K[c].numpy(), cams.dist[c].numpy(), K_new[c].numpy()
        # 1. cv2.initUndistortRectifyMap
        mx, my = cv2.initUndistortRectifyMap(K, D, None, Kn, (W, H), cv2.CV_32FC1)
        assert np.abs(maps.map_x[c] - mx).max() < 1e-2 and np.abs(maps.map_y[c] - my).max() < 1e-2
        # 2. cv2.projectPoints of the working pixels' rays (X = (x, y, 1) in the camera frame)
        q = grid().reshape(-1, 2)
        xy = (q - Kn[:2, 2]) / np.diag(Kn)[:2]
        P = np.concatenate([xy, np.ones((len(xy), 1))], 1)
        proj, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, D)
        src = np.stack([maps.map_x[c], maps.map_y[c]], -1).reshape(-1, 2)
        assert np.abs(src - proj.reshape(-1, 2)).max() < 1e-2
        # 3. cv2.undistortPoints takes the (valid) source positions back to the working pixels
        ok = maps.valid[c].reshape(-1)
        back = undistort_points(src[ok], K, D, Kn)
        assert ok.mean() > 0.5 and np.abs(back - q[ok]).max() < 1e-2


def test_maps_agree_with_camera_projection():
    """A world point seen at working pixel q (working camera) is at map(q) in the source (camera.project)."""
    cams = rig()
    work = working_cameras(cams)
    assert distorted_camera_names(cams) == ["01", "02"] and distorted_camera_names(work) == []
    assert torch.equal(work.K, cams.K) and torch.equal(work.R, cams.R) and (work.height, work.width) == (H, W)
    maps = undistort_maps(cams.K, cams.dist, H, W)
    q = torch.as_tensor(grid()).reshape(-1, 2)[::7]
    depth = torch.full((3, q.shape[0]), 2.5, dtype=torch.float64)
    X = unproject(q, depth, work, distorted=False)  # (C, N, 3)
    uv = project(X, cams).uv  # through the lens model of anidress_core.camera
    qi = q.long()
    for c in range(3):
        m = torch.stack([torch.as_tensor(maps.map_x[c])[qi[:, 1], qi[:, 0]],
                         torch.as_tensor(maps.map_y[c])[qi[:, 1], qi[:, 0]]], -1).double()
        assert float((m - uv[c]).abs().max()) < 1e-3
    with pytest.raises(ValueError, match="K_new must be"):
        working_cameras(cams, torch.eye(3))
    with pytest.raises(ValueError, match=r"K must be \(C, 3, 3\) and dist \(C, 5\)"):
        undistort_maps(cams.K, cams.dist[:, :4], H, W)


def test_zero_distortion_is_the_identity():
    cams = rig(torch.zeros(3, 5, dtype=torch.float64))
    maps = undistort_maps(cams.K, cams.dist, H, W)
    assert maps.valid.all()
    rng = np.random.default_rng(0)
    img = rng.random((H, W, 3)).astype(np.float32)
    lab = rng.integers(0, 3, (H, W)).astype(np.uint8)
    n = rng.normal(size=(H, W, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    assert np.abs(undistort_image(img, maps, 1) - img).max() < 1e-5
    assert np.array_equal(undistort_labels(lab, maps, 1), lab)
    assert np.abs(undistort_normals(n, maps, 1) - n).max() < 1e-5


def _pattern(uv_norm: np.ndarray) -> np.ndarray:
    """A smooth colour pattern of normalised camera coordinates (x, y): (..., 3) in [0, 1]."""
    x, y = uv_norm[..., 0], uv_norm[..., 1]
    return np.stack([0.5 + 0.4 * np.sin(5 * x), 0.5 + 0.4 * np.cos(4 * y), 0.5 + 0.3 * np.sin(3 * (x + y))], -1)


def test_image_labels_normals_of_a_known_scene():
    """Images of a pattern fixed to the rays: the distorted capture, undistorted, is the pinhole image."""
    cams = rig()
    maps = undistort_maps(cams.K, cams.dist, H, W)
    for c in range(2):
        K, D = cams.K[c].numpy(), cams.dist[c].numpy()
        # 1. the capture: each source pixel sees the ray of its undistorted normalised coordinates
        src = undistort_points(grid(), K, D).reshape(H, W, 2)
        captured = _pattern(src).astype(np.float32)
        # 2. the pinhole image of the same pattern
        pin = _pattern((grid() - K[:2, 2]) / np.diag(K)[:2])
        out = undistort_image(captured, maps, c)
        ok = maps.valid[c]
        assert out.dtype == np.float32 and out.shape == (H, W, 3) and (out[~ok] == 0).all()
        assert (~ok).any() == (c == 1)  # barrel: the source covers the working image; pincushion: not
        assert np.abs(out - pin)[ok].max() < 0.02  # bilinear interpolation of a smooth pattern
        u8 = undistort_image((captured * 255).astype(np.uint8), maps, c)
        assert u8.dtype == np.uint8 and np.abs(u8.astype(float) / 255 - pin)[ok].max() < 0.03
        # 3. labels: a disc in ray space; nearest neighbour keeps the label set, invalid -> 0
        lab = ((src ** 2).sum(-1) < 0.1).astype(np.uint8) * 2 + 1
        got = undistort_labels(lab, maps, c)
        want = (((grid() - K[:2, 2]) / np.diag(K)[:2]) ** 2).sum(-1) < 0.1
        assert set(np.unique(got)) <= {0, 1, 3} and (got[~ok] == 0).all()
        assert ((got[ok] == 3) != want[ok]).mean() < 0.02  # only along the disc's boundary
        # 4. normals: unit where valid, zero where not
        nrm = np.concatenate([src, -np.ones((H, W, 1))], -1)
        nrm = (nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)).astype(np.float32)
        nu = undistort_normals(nrm, maps, c)
        pin_n = np.concatenate([(grid() - K[:2, 2]) / np.diag(K)[:2], -np.ones((H, W, 1))], -1)
        pin_n /= np.linalg.norm(pin_n, axis=-1, keepdims=True)
        assert np.allclose(np.linalg.norm(nu[ok], axis=-1), 1, atol=1e-5) and (nu[~ok] == 0).all()
        assert np.abs(nu - pin_n)[ok].max() < 1e-2


def test_bad_inputs_name_the_problem():
    cams = rig()
    maps = undistort_maps(cams.K, cams.dist, H, W)
    with pytest.raises(ValueError, match=r"maps are for \(48, 64\)"):
        undistort_image(np.zeros((10, 10, 3), np.float32), maps, 0)
    with pytest.raises(ValueError, match="out of range"):
        undistort_labels(np.zeros((H, W), np.uint8), maps, 5)
    with pytest.raises(ValueError, match="integer"):
        undistort_labels(np.zeros((H, W), np.float32), maps, 0)
    nan = np.full((H, W, 3), np.nan, np.float32)
    assert (undistort_normals(nan, maps, 0) == 0).all()


def test_fold_radius_is_where_the_lens_polynomial_stops_growing():
    from anidress_core.undistort import fold_radius

    dist = torch.tensor([[0.0, -1.49, 0.0, 0.0, 0.0], [-0.5, 0.05, 0.0, 0.0, 0.0], [0.1, 0.01, 0.0, 0.0, 0.0],
                         [0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    r = fold_radius(dist)
    assert abs(float(r[0]) - (1 / (5 * 1.49)) ** 0.25) < 1e-12
    for c in range(2):  # the derivative of r (1 + k1 r^2 + k2 r^4 + k3 r^6) is zero there, positive before
        k1, k2, _, _, k3 = dist[c].tolist()
        d = lambda x: 1 + 3 * k1 * x**2 + 5 * k2 * x**4 + 7 * k3 * x**6  # noqa: E731
        x = float(r[c])
        assert abs(d(x)) < 1e-9 and all(d(t) > 0 for t in np.linspace(0, x, 50)[:-1])
    assert torch.isinf(r[2:]).all()  # pincushion and pinhole lenses never fold


def test_pixels_past_the_fold_are_invalid_and_the_rest_match_opencv():
    """A strong EasyMocap-like calibration (k2 = -1.49) at 960 x 540: the working image's corners lie past the
    fold, where the lens model sends rays back inward; the maps are float32 within 0.05 px of OpenCV elsewhere."""
    from anidress_core.undistort import fold_radius

    Hh, Ww = 540, 960
    K = torch.tensor([[[600.0, 0.0, 479.5], [0.0, 600.0, 269.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    D = torch.tensor([[0.05, -1.49, 2e-4, -1e-4, 0.0]], dtype=torch.float64)
    maps = undistort_maps(K, D, Hh, Ww)
    v, u = np.mgrid[0:Hh, 0:Ww].astype(np.float64)
    r = np.hypot((u - 479.5) / 600.0, (v - 269.5) / 600.0)
    past = r >= float(fold_radius(D)[0])
    assert past.mean() > 0.01 and not maps.valid[0][past].any()
    mx, my = cv2.initUndistortRectifyMap(K[0].numpy(), D[0].numpy(), None, K[0].numpy(), (Ww, Hh), cv2.CV_32FC1)
    ok = maps.valid[0]
    assert ok.mean() > 0.5
    assert np.abs(maps.map_x[0][ok] - mx[ok]).max() < 0.05 and np.abs(maps.map_y[0][ok] - my[ok]).max() < 0.05


def test_flow_vectors_are_remapped_through_the_lens():
    """A working-image flow G made into the distorted camera's flow F (each source pixel s at working p = U(s)
    moves to p + G(p), seen at D(p + G(p))): undistort_flow(F) gives G back, not G resampled."""
    from anidress_core.undistort import undistort_flow

    H, W = 60, 80
    K = torch.tensor([[70.0, 0, 40.5], [0, 72.0, 29.0], [0, 0, 1]], dtype=torch.float64)
    dist = torch.tensor([-0.3, 0.1, 0.001, -0.002, 0.0], dtype=torch.float64)

    def G(p):  # smooth working-image flow: a rotation about the centre plus a shift
        c = np.array([40.0, 30.0])
        a = 0.05
        d = p - c
        return np.stack([np.cos(a) * d[..., 0] - np.sin(a) * d[..., 1], np.sin(a) * d[..., 0] + np.cos(a) * d[..., 1]],
                        -1) + c + np.array([1.5, -0.7]) - p

    def U(s):  # source pixels -> working pixels
        st = torch.from_numpy(s.reshape(-1, 2))
        xy = torch.stack([(st[:, 0] - K[0, 2]) / K[0, 0], (st[:, 1] - K[1, 2]) / K[1, 1]], -1)
        xu = undistort_normalized(xy, dist)
        return (xu * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]).numpy().reshape(s.shape)

    def D(p):  # working pixels -> source pixels
        pt = torch.from_numpy(p.reshape(-1, 2))
        xy = torch.stack([(pt[:, 0] - K[0, 2]) / K[0, 0], (pt[:, 1] - K[1, 2]) / K[1, 1]], -1)
        xd = distort_normalized(xy, dist)
        return (xd * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]).numpy().reshape(p.shape)

    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    s = np.stack([u, v], -1)
    p = U(s)
    F = (D(p + G(p)) - s).astype(np.float32)
    maps = undistort_maps(K[None], dist[None], H, W)
    out, ok = undistort_flow(F, np.ones((H, W), bool), maps, 0, K, dist)
    wp = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).astype(np.float64)
    inner = ok.copy()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    err = np.linalg.norm(out - G(wp), axis=-1)[inner]
    assert inner.mean() > 0.5 and np.median(err) < 0.01 and err.max() < 0.05
    # resampling alone (the vectors kept) is off by far more: the lens bends the vectors
    resampled = np.stack([cv2.remap(F[..., i], maps.map_x[0], maps.map_y[0], cv2.INTER_LINEAR) for i in range(2)], -1)
    assert np.median(np.linalg.norm(resampled - G(wp), axis=-1)[inner]) > 10 * np.median(err)
    # an invalid source pixel invalidates the working pixels that read it
    bad = np.ones((H, W), bool)
    bad[30, 40] = False
    _, ok2 = undistort_flow(F, bad, maps, 0, K, dist)
    assert ok2.sum() < ok.sum() and not ok2[np.abs(maps.map_x[0] - 40) < 0.5][np.abs(maps.map_y[0] - 30)[
        np.abs(maps.map_x[0] - 40) < 0.5] < 0.5].any()


def test_undistort_memory_follows_the_image_size():
    """rule undistort's mem_mb: at least 2000 MB, twice the measured peak (about 260 MB + 90 MB per megapixel)."""
    from anidress_core.io.scene_info import undistort_mem_mb

    assert undistort_mem_mb(1080, 1920) == 2000 and undistort_mem_mb(256, 342) == 2000
    assert undistort_mem_mb(3000, 4000) == 3000  # 12 MP
    assert undistort_mem_mb(6000, 8000) == 10200  # 48 MP
    assert undistort_mem_mb(6000, 8000) > 2 * (260 + 90 * 48)
