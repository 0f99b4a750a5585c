"""Undistortion to pinhole working cameras: lookup maps and the remapping of images, label masks, normals.

The rasteriser (:mod:`anidress_core.raster`), the cue estimators and the metrics model pinhole
cameras only; a capture whose ``intri.yml`` has non-zero ``dist_<cam>`` is undistorted once, at
the edge (rule ``undistort``, :mod:`anidress_core.stages.undistort`), and every stage then reads
the undistorted images with the *working* cameras: the same rotation, translation, intrinsics
``K_new`` (default: the capture's ``K``) and image size, zero distortion.

Model: OpenCV's (``cv2.initUndistortRectifyMap`` with ``R = I``), conventions of
:mod:`anidress_core.camera` (pixel centres at integers, ``dist = k1 k2 p1 p2 k3``). Working
pixel ``(u, v)`` looks up the source image at

    ``(x, y) = K_new^-1 (u, v, 1)``,   ``(x_d, y_d) = distort(x, y)``,   ``(u_s, v_s) = K (x_d, y_d, 1)``,

i.e. ``project(ray(u, v))`` of the source camera. A working pixel whose ``(u_s, v_s)`` lies
outside the source image ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` is *invalid*: black in images,
label 0 in masks, the zero vector in normal maps (``valid`` in :class:`UndistortMaps`). So is a
pixel past the lens polynomial's fold: beyond the radius where ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)``
stops growing (:func:`fold_radius`; strong EasyMocap calibrations have one inside the image), the
model maps farther rays back inward and the source position belongs to another ray.

Images are interpolated bilinearly, label masks by nearest neighbour (labels never blend),
normal maps bilinearly and renormalised (the camera rotation is unchanged, so camera-space
normals keep their frame). A flow field's *vectors* are remapped, not only resampled
(:func:`undistort_flow`): a flow is a displacement between two source pixels, and the working
flow is the displacement between where those two points lie in the working image. Pure functions: arrays in, arrays out; files are written by the stage.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .camera import Cameras, distort_normalized, project, unproject
from .io.scene import DIST_EPS

__all__ = ["UndistortMaps", "undistort_maps", "fold_radius", "working_cameras", "undistort_image", "undistort_labels",
           "undistort_normals", "remap_flow", "pixel_map", "undistort_flow", "distorted_camera_names", "DIST_EPS"]

class UndistortMaps(NamedTuple):
    """Per-camera lookup maps from the working (pinhole) image into the source (distorted) image."""

    map_x: np.ndarray
    """(C, H, W) float32 source column ``u_s`` of each working pixel (``cv2.remap``'s map1)."""
    map_y: np.ndarray
    """(C, H, W) float32 source row ``v_s`` (``cv2.remap``'s map2)."""
    valid: np.ndarray
    """(C, H, W) bool: the source position lies inside the source image."""


def distorted_camera_names(cams: Cameras, eps: float = DIST_EPS) -> list[str]:
    """Names of the cameras with a non-zero distortion coefficient (``|d| > eps``)."""
    bad = (cams.dist.abs() > eps).any(-1).tolist()
    return [n for n, b in zip(cams.names, bad) if b]


def working_cameras(cams: Cameras, K_new: Tensor | None = None) -> Cameras:
    """The pinhole working cameras of ``cams``: same names, R, T, image size; ``K_new`` (default
    ``cams.K``) (C, 3, 3); distortion zero."""
    K = cams.K.clone() if K_new is None else torch.as_tensor(K_new, dtype=cams.dtype, device=cams.device)
    if tuple(K.shape) != (len(cams), 3, 3):
        raise ValueError(f"working_cameras: K_new must be ({len(cams)}, 3, 3), got {tuple(K.shape)}")
    return Cameras(list(cams.names), K, torch.zeros_like(cams.dist), cams.R.clone(), cams.T.clone(),
                   cams.height, cams.width)


def fold_radius(dist: Tensor) -> Tensor:
    """(C,) the normalised radius where the radial lens polynomial ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` of
    dist (C, 5) ``k1 k2 p1 p2 k3`` stops growing: the smallest positive root of its derivative
    ``1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3`` in s = r^2 (inf where there is none). The tangential terms are
    left out of this bound."""
    out = []
    for k1, k2, _, _, k3 in torch.as_tensor(dist, dtype=torch.float64).tolist():
        coef = np.trim_zeros(np.array([7 * k3, 5 * k2, 3 * k1, 1.0]), "f")
        roots = np.roots(coef) if coef.size > 1 else np.array([])
        pos = [r.real for r in roots if abs(r.imag) <= 1e-12 * max(1.0, abs(r)) and r.real > 0]
        out.append(math.sqrt(min(pos)) if pos else math.inf)
    return torch.tensor(out, dtype=torch.float64)


def undistort_maps(K: Tensor, dist: Tensor, height: int, width: int, K_new: Tensor | None = None) -> UndistortMaps:
    """Lookup maps of C cameras (see the module docstring).

    K: (C, 3, 3) source intrinsics; dist: (C, 5) ``k1 k2 p1 p2 k3``; height, width: H, W of
    both images; K_new: (C, 3, 3) working intrinsics (default K). Computed one camera at a time in
    float32; rule undistort calls it per camera (peak of the process, interpreter included: six 1920 x 1080
    cameras 0.44 GB, 23 of 1024 x 1024 0.35 GB; in float64 for all at once, before, 1.38 and 2.36 GB). Within
    0.05 px of
    ``cv2.initUndistortRectifyMap(K, dist, None, K_new, (W, H), cv2.CV_32FC1)`` for cameras without
    skew (OpenCV ignores the source camera's skew; it is applied here); pixels past the lens's fold are
    invalid (:func:`fold_radius`).
    """
    K = torch.as_tensor(K, dtype=torch.float64)
    dist = torch.as_tensor(dist, dtype=torch.float64)
    if K.ndim != 3 or K.shape[1:] != (3, 3) or tuple(dist.shape) != (K.shape[0], 5):
        raise ValueError(f"undistort_maps: K must be (C, 3, 3) and dist (C, 5), got {tuple(K.shape)}, "
                         f"{tuple(dist.shape)}")
    K_new = K if K_new is None else torch.as_tensor(K_new, dtype=torch.float64)
    if K_new.shape != K.shape:
        raise ValueError(f"undistort_maps: K_new must be {tuple(K.shape)}, got {tuple(K_new.shape)}")
    H, W = int(height), int(width)
    if H <= 0 or W <= 0:
        raise ValueError(f"undistort_maps: height and width must be positive, got ({H}, {W})")
    C = K.shape[0]
    map_x = np.empty((C, H, W), np.float32)
    map_y = np.empty((C, H, W), np.float32)
    valid = np.empty((C, H, W), bool)
    fold2 = fold_radius(dist) ** 2
    f32 = torch.float32
    v, u = torch.meshgrid(torch.arange(H, dtype=f32), torch.arange(W, dtype=f32), indexing="ij")
    for c in range(C):
        # 1. normalised working coordinates of the pixel centres: K_new^-1 (u, v, 1) (no skew in K_new here:
        #    the inverse's entries, computed in float64, applied in float32)
        Ki = torch.linalg.inv(K_new[c]).to(f32)
        w = Ki[2, 0] * u + Ki[2, 1] * v + Ki[2, 2]
        xy = torch.stack([(Ki[0, 0] * u + Ki[0, 1] * v + Ki[0, 2]) / w,
                          (Ki[1, 0] * u + Ki[1, 1] * v + Ki[1, 2]) / w], -1)
        # 2. the source lens, then the source intrinsics
        xy_d = distort_normalized(xy.reshape(1, -1, 2), dist[c:c + 1].to(f32))[0].view(H, W, 2)
        Kc = K[c].to(f32)
        mx = Kc[0, 0] * xy_d[..., 0] + Kc[0, 1] * xy_d[..., 1] + Kc[0, 2]
        my = Kc[1, 0] * xy_d[..., 0] + Kc[1, 1] * xy_d[..., 1] + Kc[1, 2]
        # 3. inside the source image (pixel areas: [-0.5, W - 0.5] x [-0.5, H - 0.5]) and before the lens's fold
        ok = (mx >= -0.5) & (mx <= W - 0.5) & (my >= -0.5) & (my <= H - 0.5) & torch.isfinite(mx) & torch.isfinite(my)
        if math.isfinite(float(fold2[c])):
            ok &= xy.square().sum(-1) < float(fold2[c])
        map_x[c], map_y[c], valid[c] = mx.numpy(), my.numpy(), ok.numpy()
    return UndistortMaps(map_x, map_y, valid)


def _check(arr: np.ndarray, maps: UndistortMaps, cam: int, fn: str) -> None:
    if not 0 <= cam < maps.map_x.shape[0]:
        raise ValueError(f"{fn}: camera index {cam} out of range for {maps.map_x.shape[0]} cameras")
    if tuple(arr.shape[:2]) != tuple(maps.map_x.shape[1:]):
        raise ValueError(f"{fn}: array is {tuple(arr.shape)}, the maps are for "
                         f"{tuple(maps.map_x.shape[1:])} (H, W) images")


def undistort_image(image: np.ndarray, maps: UndistortMaps, cam: int) -> np.ndarray:
    """Bilinear remap of image (H, W) or (H, W, Ch) (any dtype cv2.remap takes) of camera ``cam``.

    Invalid pixels are 0; a position in the half-pixel border of the source takes the edge value.
    Returns the same shape and dtype.
    """
    import cv2

    _check(image, maps, cam, "undistort_image")
    out = cv2.remap(np.ascontiguousarray(image), maps.map_x[cam], maps.map_y[cam], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(image.shape)
    out[~maps.valid[cam]] = 0
    return out


def undistort_labels(labels: np.ndarray, maps: UndistortMaps, cam: int) -> np.ndarray:
    """Nearest-neighbour remap of a label mask (H, W) integer of camera ``cam``; invalid pixels 0."""
    import cv2

    _check(labels, maps, cam, "undistort_labels")
    if labels.ndim != 2 or labels.dtype.kind not in "ui":
        raise ValueError(f"undistort_labels: a label mask is (H, W) integer, got {labels.shape} {labels.dtype}")
    out = cv2.remap(np.ascontiguousarray(labels), maps.map_x[cam], maps.map_y[cam], cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_REPLICATE)
    out[~maps.valid[cam]] = 0
    return out


def undistort_normals(normals: np.ndarray, maps: UndistortMaps, cam: int, eps: float = 1e-6) -> np.ndarray:
    """Bilinear remap of a normal map (H, W, 3) float of camera ``cam``, renormalised to unit length.

    Pixels that are invalid, non-finite in the source neighbourhood or whose interpolated normal is
    shorter than ``eps`` (opposite normals averaged) are the zero vector. Returns (H, W, 3) float32.
    """
    import cv2

    _check(normals, maps, cam, "undistort_normals")
    if normals.ndim != 3 or normals.shape[-1] < 3:
        raise ValueError(f"undistort_normals: a normal map is (H, W, 3), got {normals.shape}")
    n = np.ascontiguousarray(normals[..., :3], dtype=np.float32)
    out = cv2.remap(n, maps.map_x[cam], maps.map_y[cam], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    norm = np.linalg.norm(out, axis=-1, keepdims=True)
    ok = maps.valid[cam][..., None] & np.isfinite(norm) & (norm > eps)
    return np.where(ok, out / np.where(ok, norm, 1.0), 0.0).astype(np.float32)


def remap_flow(flow: np.ndarray, valid: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, map_valid: np.ndarray,
               to_target) -> tuple[np.ndarray, np.ndarray]:
    """A forward flow field moved to another camera model of the same camera: the vectors remapped.

    flow: (H, W, 2) source-image flow ``F`` from frame t-1 to t on frame t-1's source pixel grid; valid:
    (H, W) bool; map_x, map_y: (H', W') float32, the source pixel ``s`` of each target pixel ``p``;
    map_valid: (H', W') bool; to_target: (N, 2) float64 source pixels -> (N, 2) target pixels (the inverse
    of the maps). The point at ``s`` moves to ``s + F(s)`` (F bilinear) in the source image, i.e. to
    ``p' = to_target(s + F(s))``; the target flow is ``p' - p``. Valid where ``map_valid`` is, the four source
    neighbours of ``s`` are valid and ``p'`` is finite. Returns (flow (H', W', 2) float32, valid (H', W')
    bool); invalid pixels hold 0.
    """
    import cv2

    if flow.ndim != 3 or flow.shape[-1] != 2 or valid.shape != flow.shape[:2]:
        raise ValueError(f"remap_flow: flow must be (H, W, 2) with valid (H, W), got {flow.shape}, {valid.shape}")
    H, W = map_x.shape
    f = np.where(valid[..., None], flow, 0).astype(np.float32)
    fs = cv2.remap(np.ascontiguousarray(f), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # every bilinear neighbour valid: the minimum of the validity over the 2 x 2 neighbourhood of s
    nb = cv2.erode(valid.astype(np.uint8), np.ones((2, 2), np.uint8), anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    ok = map_valid & (cv2.remap(nb, np.floor(map_x), np.floor(map_y), cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0)
    s1 = np.stack([map_x + fs[..., 0], map_y + fs[..., 1]], -1).reshape(-1, 2).astype(np.float64)
    p1 = np.asarray(to_target(s1), np.float64).reshape(H, W, 2)
    v, u = np.mgrid[0:H, 0:W]
    out = (p1 - np.stack([u, v], -1)).astype(np.float32)
    ok &= np.isfinite(out).all(-1)
    out[~ok] = 0
    return out, ok


def pixel_map(src: Cameras, dst: Cameras):
    """The map of one camera's pixels from the image model ``src`` to ``dst`` (each a single camera, same pose):
    (N, 2) float64 source pixels -> (N, 2) target pixels, through the camera's own :func:`unproject` (lens
    undone) and :func:`project` (lens applied): the rays are the same, only intrinsics and distortion differ."""
    src, dst = src.to(dtype=torch.float64), dst.to(dtype=torch.float64)

    def to_target(s: np.ndarray) -> np.ndarray:
        uv = torch.from_numpy(np.asarray(s, np.float64))
        X = unproject(uv, torch.ones(1, len(uv), dtype=torch.float64), src)
        return project(X, dst).uv[0].numpy()

    return to_target


def undistort_flow(flow: np.ndarray, valid: np.ndarray, maps: UndistortMaps, cam: int, K: Tensor, dist: Tensor,
                   K_new: Tensor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A forward flow field of camera ``cam`` (source camera K (3, 3), dist (5,)) in the working camera
    (K_new, default K): :func:`remap_flow` with ``to_target(s) = K_new undistort(K^-1 s)`` (:func:`pixel_map`).
    flow: (H, W, 2), valid: (H, W) bool -> (flow (H, W, 2) float32, valid (H, W) bool)."""
    _check(flow, maps, cam, "undistort_flow")
    K = torch.as_tensor(K, dtype=torch.float64).reshape(1, 3, 3)
    Kn = K if K_new is None else torch.as_tensor(K_new, dtype=torch.float64).reshape(1, 3, 3)
    d = torch.as_tensor(dist, dtype=torch.float64).reshape(1, 5)
    H, W = flow.shape[:2]
    R, T = torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64)
    src = Cameras(["src"], K, d, R, T, H, W)
    work = Cameras(["src"], Kn, torch.zeros_like(d), R, T, H, W)
    return remap_flow(flow, valid, maps.map_x[cam], maps.map_y[cam], maps.valid[cam], pixel_map(src, work))
