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
label 0 in masks, the zero vector in normal maps (``valid`` in :class:`UndistortMaps`).

Images are interpolated bilinearly, label masks by nearest neighbour (labels never blend),
normal maps bilinearly and renormalised (the camera rotation is unchanged, so camera-space
normals keep their frame). Pure functions: arrays in, arrays out; files are written by the stage.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .camera import Cameras, distort_normalized
from .io.scene import DIST_EPS

__all__ = ["UndistortMaps", "undistort_maps", "working_cameras", "undistort_image", "undistort_labels",
           "undistort_normals", "distorted_camera_names", "DIST_EPS"]

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


def undistort_maps(K: Tensor, dist: Tensor, height: int, width: int, K_new: Tensor | None = None) -> UndistortMaps:
    """Lookup maps of C cameras (see the module docstring).

    K: (C, 3, 3) source intrinsics; dist: (C, 5) ``k1 k2 p1 p2 k3``; height, width: H, W of
    both images; K_new: (C, 3, 3) working intrinsics (default K). Computed in float64.
    Equals ``cv2.initUndistortRectifyMap(K, dist, None, K_new, (W, H), cv2.CV_32FC1)`` for
    cameras without skew (OpenCV ignores the source camera's skew; it is applied here).
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
    # 1. working pixel centres (u, v), row-major: (H*W, 3) homogeneous
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    uv1 = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    # 2. normalised working coordinates: xy1[c, n, i] = sum_j inv(K_new)[c, i, j] uv1[n, j]
    xy1 = torch.einsum("cij,nj->cni", torch.linalg.inv(K_new), uv1)
    xy = xy1[..., :2] / xy1[..., 2:]
    # 3. source lens distortion, then source intrinsics: uv_s[c, n, i] = sum_j K[c, i, j] xy_d[c, n, j] + K[c, i, 2]
    xy_d = distort_normalized(xy, dist)
    uv_s = torch.einsum("cij,cnj->cni", K[:, :2, :2], xy_d) + K[:, None, :2, 2]
    mx = uv_s[..., 0].reshape(C, H, W)
    my = uv_s[..., 1].reshape(C, H, W)
    # 4. inside the source image (pixel areas: [-0.5, W - 0.5] x [-0.5, H - 0.5])
    valid = (mx >= -0.5) & (mx <= W - 0.5) & (my >= -0.5) & (my <= H - 0.5) & torch.isfinite(mx) & torch.isfinite(my)
    return UndistortMaps(mx.numpy().astype(np.float32), my.numpy().astype(np.float32), valid.numpy())


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
