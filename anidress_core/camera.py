"""Pinhole cameras with OpenCV distortion: projection, unprojection, rays, camera rigs.

Conventions (OpenCV, as everywhere in ``anidress_core``):

* camera frame: x right, y down, z forward; ``X_cam = R X_world + T`` (metres);
* pixel centres at integer pixel coordinates: pixel (row i, col j) is at ``u = j``,
  ``v = i``; the image covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``;
* intrinsics ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels;
* distortion ``dist = (k1, k2, p1, p2, k3)`` acting on normalised coordinates
  ``(x, y) = (X / Z, Y / Z)``: with ``r^2 = x^2 + y^2``,
  ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)``,
  ``y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y``.

Every function is pure and batched over cameras C; projection and unprojection are
differentiable w.r.t. points and all camera parameters. File I/O lives in
:mod:`anidress_core.io.easymocap`; :func:`load_cameras` / :func:`save_cameras` are thin
wrappers around it.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from .geometry import invert_transform, make_transform
from .io import easymocap

__all__ = [
    "Cameras",
    "scale_intrinsics",
    "scaled_size",
    "scale_calibration",
    "Projection",
    "Rays",
    "project",
    "distort_normalized",
    "undistort_normalized",
    "unproject",
    "pixel_rays",
    "rays_for_pixels",
    "look_at",
    "ring_cameras",
    "load_cameras",
    "save_cameras",
]


# --------------------------------------------------------------------------- Cameras


@dataclass
class Cameras:
    """A rig of C pinhole cameras sharing one image size.

    All tensors share dtype (floating) and device.
    """

    names: list[str]
    """Camera names, unique, e.g. ``["01", "02"]``."""
    K: Tensor
    """(C, 3, 3) intrinsics in pixels, last row ``[0, 0, 1]``."""
    dist: Tensor
    """(C, 5) OpenCV distortion ``k1, k2, p1, p2, k3``."""
    R: Tensor
    """(C, 3, 3) world -> camera rotation."""
    T: Tensor
    """(C, 3) world -> camera translation: ``X_cam = R X_world + T``."""
    height: int
    """Image height H in pixels."""
    width: int
    """Image width W in pixels."""

    def __post_init__(self) -> None:
        self.names = list(self.names)
        C = len(self.names)
        if len(set(self.names)) != C or not all(isinstance(n, str) for n in self.names):
            raise ValueError(f"Cameras: names must be unique strings, got {self.names}")
        for attr, shape in (("K", (C, 3, 3)), ("dist", (C, 5)), ("R", (C, 3, 3)), ("T", (C, 3))):
            t = getattr(self, attr)
            if not isinstance(t, Tensor):
                raise ValueError(f"Cameras: {attr} must be a torch.Tensor, got {type(t).__name__}")
            if tuple(t.shape) != shape:
                raise ValueError(
                    f"Cameras: {attr} must be {shape} for {C} cameras, got {tuple(t.shape)}"
                )
            if not t.is_floating_point():
                raise ValueError(f"Cameras: {attr} must be floating point, got {t.dtype}")
            if t.dtype != self.K.dtype or t.device != self.K.device:
                raise ValueError(
                    f"Cameras: {attr} is {t.dtype} on {t.device}, K is {self.K.dtype} on {self.K.device}"
                )
        for attr in ("height", "width"):
            v = getattr(self, attr)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
                raise ValueError(f"Cameras: {attr} must be a positive int, got {v!r}")
            setattr(self, attr, int(v))

    def __len__(self) -> int:
        return len(self.names)

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def world_to_cam(self) -> Tensor:
        """(C, 4, 4) ``[[R, T], [0, 1]]``."""
        return make_transform(self.R, self.T)

    @property
    def cam_to_world(self) -> Tensor:
        """(C, 4, 4) inverse of :attr:`world_to_cam`: ``[[R^T, -R^T T], [0, 1]]``."""
        return invert_transform(self.world_to_cam)

    @property
    def centers(self) -> Tensor:
        """(C, 3) camera centres in world coordinates: ``-R^T T``."""
        # c[c, i] = -sum_j R[c, j, i] T[c, j]
        return -torch.einsum("cji,cj->ci", self.R, self.T)

    def select(self, which: int | str | Sequence[int] | Sequence[str] | Tensor) -> "Cameras":
        """Sub-rig by indices or names (in the order given); a single index/name gives C = 1."""
        if isinstance(which, (int, np.integer, str)):
            which = [which]
        if isinstance(which, Tensor):
            which = which.reshape(-1).tolist()
        which = list(which)
        idx = []
        for w in which:
            if isinstance(w, str):
                if w not in self.names:
                    raise ValueError(f"Cameras.select: no camera named {w!r} in {self.names}")
                idx.append(self.names.index(w))
            else:
                i = int(w)
                if not -len(self) <= i < len(self):
                    raise ValueError(f"Cameras.select: index {i} out of range for {len(self)} cameras")
                idx.append(i % len(self))
        index = torch.tensor(idx, dtype=torch.long, device=self.device)
        return Cameras(
            names=[self.names[i] for i in idx],
            K=self.K[index], dist=self.dist[index], R=self.R[index], T=self.T[index],
            height=self.height, width=self.width,
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Cameras":
        """Copy with tensors moved to ``device`` and/or cast to ``dtype``."""
        def f(t: Tensor) -> Tensor:
            return t.to(device=device, dtype=dtype)
        return Cameras(list(self.names), f(self.K), f(self.dist), f(self.R), f(self.T), self.height, self.width)

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for the images resized by ``factor`` (e.g. 0.5 halves H and W).

        The new size is ``round(H * factor), round(W * factor)``; per axis the exact
        ratio ``s = W' / W`` (``H' / H``) is used, so that the image borders map onto
        each other (what ``cv2.resize`` does). With pixel centres at integers, a point
        at ``u`` moves to ``u' = s (u + 0.5) - 0.5``: ``fx, skew`` scale by ``s`` and
        ``cx' = s (cx + 0.5) - 0.5``. Distortion (on normalised coordinates) is unchanged.
        """
        if not factor > 0:
            raise ValueError(f"Cameras.scaled: factor must be > 0, got {factor}")
        h, w = round(self.height * factor), round(self.width * factor)
        if h < 1 or w < 1:
            raise ValueError(f"Cameras.scaled: factor {factor} gives an empty image ({h}, {w})")
        sx, sy = w / self.width, h / self.height
        # K' = diag(sx, sy, 1) K + offset, offset moving cx, cy by 0.5 (s - 1)
        row_scale = torch.tensor([sx, sy, 1.0], dtype=self.dtype, device=self.device)
        offset = torch.zeros(3, 3, dtype=self.dtype, device=self.device)
        offset[0, 2], offset[1, 2] = 0.5 * (sx - 1), 0.5 * (sy - 1)
        K = self.K * row_scale[:, None] + offset
        return Cameras(list(self.names), K, self.dist.clone(), self.R.clone(), self.T.clone(), h, w)


class Projection(NamedTuple):
    uv: Tensor
    """(C, N, 2) pixel coordinates (u right, v down; pixel centres at integers)."""
    depth: Tensor
    """(C, N) z in the camera frame (negative behind the camera)."""


class Rays(NamedTuple):
    origins: Tensor
    """(C, ..., 3) world ray origins (the camera centres)."""
    directions: Tensor
    """(C, ..., 3) unit world directions."""


# --------------------------------------------------------------------------- distortion


def distort_normalized(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV's radial + tangential distortion to normalised coordinates.

    xy: (..., N, 2) undistorted ``(X/Z, Y/Z)``; dist: (..., 5) ``k1, k2, p1, p2, k3``
    (leading dims broadcast with those of xy). Returns (..., N, 2) distorted coordinates.
    """
    if xy.shape[-1] != 2 or dist.shape[-1] != 5:
        raise ValueError(
            f"distort_normalized expects xy (..., N, 2) and dist (..., 5), got {tuple(xy.shape)}, {tuple(dist.shape)}"
        )
    k1, k2, p1, p2, k3 = (d[..., None] for d in dist.unbind(-1))  # each (..., 1)
    x, y = xy.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort_normalized(xy: Tensor, dist: Tensor, iters: int = 20) -> Tensor:
    """Invert :func:`distort_normalized` by fixed-point iteration (as ``cv2.undistortPoints``).

    xy: (..., N, 2) distorted normalised coordinates; dist: (..., 5). Returns (..., N, 2).

    Iteration (OpenCV's ``cvUndistortPointsInternal``), starting at ``x = x_d``:
    ``x <- (x_d - tangential(x)) / radial(x)``. ``cv2.undistortPoints`` runs 5
    iterations by default; 20 reach double precision for usual lenses. Like OpenCV,
    a point whose radial factor turns negative (outside the lens model's valid range)
    is returned undistorted-as-is (``x = x_d``) from then on.
    """
    if xy.shape[-1] != 2 or dist.shape[-1] != 5:
        raise ValueError(
            f"undistort_normalized expects xy (..., N, 2) and dist (..., 5), got {tuple(xy.shape)}, {tuple(dist.shape)}"
        )
    k1, k2, p1, p2, k3 = (d[..., None] for d in dist.unbind(-1))
    x0, y0 = xy.unbind(-1)
    x, y = x0, y0
    failed = torch.zeros_like(x0, dtype=torch.bool)
    for _ in range(iters):
        # 1. radial factor and tangential offset at the current estimate
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        # 2. OpenCV stops (and resets to the input) where 1 / radial < 0
        failed = failed | (radial < 0)
        safe = torch.where(failed, torch.ones_like(radial), radial)
        x = torch.where(failed, x0, (x0 - dx) / safe)
        y = torch.where(failed, y0, (y0 - dy) / safe)
    return torch.stack([x, y], dim=-1)


# --------------------------------------------------------------------------- projection


def _check_cams(cams: Cameras, fn: str) -> None:
    if not isinstance(cams, Cameras):
        raise ValueError(f"{fn}: cams must be Cameras, got {type(cams).__name__}")


def _points_to_cam(points: Tensor, cams: Cameras, fn: str) -> Tensor:
    """World points (N, 3) or (C, N, 3) -> camera frame (C, N, 3)."""
    C = len(cams)
    if points.ndim == 2 and points.shape[-1] == 3:
        # Xc[c, n, i] = sum_j R[c, i, j] X[n, j] + T[c, i]
        return torch.einsum("cij,nj->cni", cams.R, points) + cams.T[:, None, :]
    if points.ndim == 3 and points.shape[0] == C and points.shape[-1] == 3:
        # Xc[c, n, i] = sum_j R[c, i, j] X[c, n, j] + T[c, i]
        return torch.einsum("cij,cnj->cni", cams.R, points) + cams.T[:, None, :]
    raise ValueError(f"{fn}: points must be (N, 3) or ({C}, N, 3), got {tuple(points.shape)}")


def project(points: Tensor, cams: Cameras, distort: bool = True) -> Projection:
    """Project world points into every camera.

    points: (N, 3) shared by all cameras or (C, N, 3) per camera.
    Returns :class:`Projection` with uv (C, N, 2) pixels and depth (C, N).

    Matches ``cv2.projectPoints`` (which ignores the skew ``K[0, 1]``; we apply it).
    As OpenCV, a point with ``Z == 0`` is divided by 1 instead; points behind the
    camera (depth < 0) get a mirrored uv; mask them with ``depth``.
    """
    _check_cams(cams, "project")
    # 1. world -> camera
    Xc = _points_to_cam(points, cams, "project")  # (C, N, 3)
    z = Xc[..., 2]
    # 2. perspective division (OpenCV: z ? 1/z : 1)
    inv_z = 1 / torch.where(z == 0, torch.ones_like(z), z)
    xy = Xc[..., :2] * inv_z[..., None]  # (C, N, 2)
    # 3. lens distortion on normalised coordinates
    if distort:
        xy = distort_normalized(xy, cams.dist)
    # 4. intrinsics: uv[c, n, i] = sum_j K[c, i, j] xy[c, n, j] + K[c, i, 2]
    uv = torch.einsum("cij,cnj->cni", cams.K[:, :2, :2], xy) + cams.K[:, None, :2, 2]
    return Projection(uv=uv, depth=z)


def _pixels_to_normalized(uv: Tensor, cams: Cameras) -> Tensor:
    """Invert the intrinsics: (C, N, 2) pixels -> (C, N, 2) normalised (distorted) coords."""
    fx, s, cx = cams.K[:, 0, 0, None], cams.K[:, 0, 1, None], cams.K[:, 0, 2, None]
    fy, cy = cams.K[:, 1, 1, None], cams.K[:, 1, 2, None]
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - s * y) / fx
    return torch.stack([x, y], dim=-1)


def _check_uv(uv: Tensor, cams: Cameras, fn: str) -> Tensor:
    C = len(cams)
    if uv.ndim == 2 and uv.shape[-1] == 2:
        return uv.expand(C, *uv.shape)
    if uv.ndim == 3 and uv.shape[0] == C and uv.shape[-1] == 2:
        return uv
    raise ValueError(f"{fn}: uv must be (N, 2) or ({C}, N, 2), got {tuple(uv.shape)}")


def unproject(uv: Tensor, depth: Tensor, cams: Cameras, distorted: bool = True, iters: int = 20) -> Tensor:
    """Inverse of :func:`project`: pixels with depth -> world points.

    uv: (C, N, 2) pixels (or (N, 2) for all cameras); depth: (C, N) camera-frame z.
    ``distorted``: uv are in the distorted image (undistort first, ``iters`` fixed-point
    iterations). Returns (C, N, 3) world points.
    """
    _check_cams(cams, "unproject")
    uv = _check_uv(uv, cams, "unproject")
    if tuple(depth.shape) != tuple(uv.shape[:2]):
        raise ValueError(f"unproject: depth must be {tuple(uv.shape[:2])}, got {tuple(depth.shape)}")
    # 1. pixels -> normalised coordinates, then undo the lens distortion
    xy = _pixels_to_normalized(uv, cams)
    if distorted:
        xy = undistort_normalized(xy, cams.dist, iters=iters)
    # 2. scale by depth: camera-frame points (C, N, 3)
    Xc = torch.cat([xy * depth[..., None], depth[..., None]], dim=-1)
    # 3. camera -> world: X[c, n, i] = sum_j R[c, j, i] (Xc[c, n, j] - T[c, j])
    return torch.einsum("cji,cnj->cni", cams.R, Xc - cams.T[:, None, :])


def rays_for_pixels(cams: Cameras, uv: Tensor, distorted: bool = True, iters: int = 20) -> Rays:
    """World rays through arbitrary pixel positions.

    uv: (C, N, 2) pixels (or (N, 2) for all cameras). Returns :class:`Rays` with
    origins and unit directions (C, N, 3). ``distorted``: undistort uv first.
    """
    _check_cams(cams, "rays_for_pixels")
    uv = _check_uv(uv, cams, "rays_for_pixels")
    # 1. pixel -> undistorted normalised coords -> camera direction (x, y, 1)
    xy = _pixels_to_normalized(uv, cams)
    if distorted:
        xy = undistort_normalized(xy, cams.dist, iters=iters)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)  # (C, N, 3)
    # 2. rotate to world: d[c, n, i] = sum_j R[c, j, i] d_cam[c, n, j]; normalise
    d = torch.einsum("cji,cnj->cni", cams.R, d_cam)
    d = d / d.norm(dim=-1, keepdim=True)
    origins = cams.centers[:, None, :].expand_as(d)
    return Rays(origins=origins, directions=d)


def pixel_rays(cams: Cameras, height: int | None = None, width: int | None = None, iters: int = 20) -> Rays:
    """World rays through every pixel centre: origins, directions (C, H, W, 3).

    Pixel (i, j) is at ``u = j, v = i``. ``height``/``width`` default to the cameras'
    image size; a smaller value casts rays for the top-left crop only (K is not
    rescaled; use :meth:`Cameras.scaled` for another resolution). Undistorts with
    ``cams.dist`` (identity when it is zero).
    """
    _check_cams(cams, "pixel_rays")
    H = cams.height if height is None else int(height)
    W = cams.width if width is None else int(width)
    if H <= 0 or W <= 0:
        raise ValueError(f"pixel_rays: height and width must be positive, got ({H}, {W})")
    v, u = torch.meshgrid(
        torch.arange(H, dtype=cams.dtype, device=cams.device),
        torch.arange(W, dtype=cams.dtype, device=cams.device),
        indexing="ij",
    )
    uv = torch.stack([u, v], dim=-1).reshape(-1, 2)  # (H*W, 2), row-major
    rays = rays_for_pixels(cams, uv, distorted=True, iters=iters)
    C = len(cams)
    return Rays(rays.origins.reshape(C, H, W, 3), rays.directions.reshape(C, H, W, 3))


# --------------------------------------------------------------------------- rigs


def look_at(eye: Tensor, target: Tensor, up: Tensor | Sequence[float] = (0.0, 0.0, 1.0)) -> tuple[Tensor, Tensor]:
    """World -> camera (R, T) of cameras at ``eye`` looking at ``target`` (OpenCV axes).

    eye, target: (..., 3) broadcastable; up: (3,) (or (..., 3)) world up direction.
    Returns R (..., 3, 3) and T (..., 3). Camera z points at the target, x = z x up
    (right in the image), y = z x x (down in the image, i.e. against ``up``).
    """
    eye = torch.as_tensor(eye)
    target = torch.as_tensor(target, dtype=eye.dtype, device=eye.device)
    up = torch.as_tensor(up, dtype=eye.dtype, device=eye.device)
    if eye.shape[-1] != 3 or target.shape[-1] != 3 or up.shape[-1] != 3:
        raise ValueError(
            f"look_at expects eye, target, up (..., 3), got {tuple(eye.shape)}, {tuple(target.shape)}, {tuple(up.shape)}"
        )
    # 1. forward axis
    fwd = target - eye
    fn = fwd.norm(dim=-1, keepdim=True)
    if bool((fn < 1e-12).any()):
        raise ValueError("look_at: eye and target coincide")
    z = fwd / fn
    # 2. right = forward x up; degenerate when looking along up
    z, up = torch.broadcast_tensors(z, up)
    x = torch.cross(z, up, dim=-1)
    xn = x.norm(dim=-1, keepdim=True)
    if bool((xn < 1e-9 * up.norm(dim=-1, keepdim=True)).any()):
        raise ValueError("look_at: viewing direction is parallel to up")
    x = x / xn
    # 3. down = forward x right (so x, y, z is right-handed)
    y = torch.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=-2)  # rows are the camera axes in world coords
    # T = -R eye: T[..., i] = -sum_j R[..., i, j] eye[..., j]
    T = -torch.einsum("...ij,...j->...i", R, eye)
    return R, T


def ring_cameras(
    n: int,
    radius: float,
    height: float,
    target: Sequence[float] | Tensor,
    focal_px: float,
    image_height: int,
    image_width: int,
    names: Sequence[str] | None = None,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    dtype: torch.dtype = torch.float32,
) -> Cameras:
    """n cameras evenly spaced on a horizontal circle, all looking at ``target``.

    The circle lies in the plane perpendicular to ``up`` at ``height`` along ``up``
    (world z = height for the default z-up world), centred above/below ``target``,
    with the given ``radius``. Camera k sits at angle ``2 pi k / n`` measured from +x
    towards +y (for z up). Zero distortion, square pixels, principal point at the image
    centre ``((W - 1) / 2, (H - 1) / 2)``. Names default to "01", "02", ...
    """
    if n < 1 or not radius > 0 or not focal_px > 0:
        raise ValueError(f"ring_cameras: need n >= 1, radius > 0, focal_px > 0; got {n}, {radius}, {focal_px}")
    if names is None:
        names = [f"{k + 1:02d}" for k in range(n)]
    if len(names) != n:
        raise ValueError(f"ring_cameras: {len(names)} names for {n} cameras")
    f64 = torch.float64
    tgt = torch.as_tensor(target, dtype=f64).reshape(3)
    u = torch.as_tensor(up, dtype=f64).reshape(3)
    u = u / u.norm()
    # 1. in-plane basis (a, b) with a x b = up; a = x axis projected (y when up ~ x)
    e = torch.tensor([1.0, 0.0, 0.0], dtype=f64) if abs(float(u[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0], dtype=f64)
    a = e - (e @ u) * u
    a = a / a.norm()
    b = torch.cross(u, a, dim=0)
    # 2. eyes on the circle
    theta = torch.arange(n, dtype=f64) * (2 * math.pi / n)
    centre = tgt - (tgt @ u) * u + height * u
    eye = centre + radius * (torch.cos(theta)[:, None] * a + torch.sin(theta)[:, None] * b)  # (n, 3)
    R, T = look_at(eye, tgt.expand_as(eye), u)
    # 3. intrinsics
    K = torch.tensor(
        [[focal_px, 0.0, (image_width - 1) / 2], [0.0, focal_px, (image_height - 1) / 2], [0.0, 0.0, 1.0]],
        dtype=f64,
    ).expand(n, 3, 3)
    return Cameras(
        names=list(names), K=K.to(dtype).clone(), dist=torch.zeros(n, 5, dtype=dtype),
        R=R.to(dtype), T=T.to(dtype), height=int(image_height), width=int(image_width),
    )


# --------------------------------------------------------------------------- files


def scale_intrinsics(K: np.ndarray, s: float) -> np.ndarray:
    """K (3, 3) of a calibration made for images ``1 / s`` times the size of the ones used: (3, 3) with
    fx, fy times s and c' = s (c + 0.5) - 0.5 on both axes (pixel centres at integer coordinates, OpenCV:
    the image's outer edge, -0.5, stays the outer edge)."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 1] *= s
    K[:2, 2] = s * (K[:2, 2] + 0.5) - 0.5
    return K


def scaled_size(n: float, s: float, what: str) -> int:
    """An image side ``n`` (pixels) of the calibration times ``s``; a whole number or ValueError naming ``what``."""
    v = float(n) * s
    if abs(v - round(v)) > 1e-6:
        raise ValueError(f"{what} = {n:g} times cameras/scale {s:g} is {v:g}, not a whole number of pixels")
    return int(round(v))


def scale_calibration(raw: dict[str, dict], s: float, path: str | os.PathLike) -> dict[str, dict]:
    """EasyMocap camera entries ``{name: {"K", ["H", "W"], ...}}`` (as :mod:`anidress_core.io.easymocap` reads
    them, from file ``path``) for images ``s`` times the calibration's size: K by :func:`scale_intrinsics`,
    ``H``/``W`` by :func:`scaled_size`; changed in place and returned."""
    for c, entry in raw.items():
        if "K" in entry:
            entry["K"] = scale_intrinsics(entry["K"], s)
        for key in ("H", "W"):
            if key in entry:
                entry[key] = scaled_size(entry[key], s, f"{path}: {key}_{c}")
    return raw


def load_cameras(
    intri_path: str | os.PathLike,
    extri_path: str | os.PathLike,
    names: Sequence[str] | None = None,
    height: int | None = None,
    width: int | None = None,
    dtype: torch.dtype = torch.float64,
    scale: float | None = None,
) -> Cameras:
    """Read EasyMocap ``intri.yml`` / ``extri.yml`` into :class:`Cameras`.

    ``names`` selects cameras (default: all, in file order). The image size comes from
    the files' ``H_``/``W_`` when present (all cameras must agree, and ``height``/
    ``width`` if given must match), else from ``height``/``width``. float64 keeps the
    file's values exactly; cast with :meth:`Cameras.to`. ``scale``: the images are this factor of the
    calibration's size (scene.yaml ``cameras/scale``); K and ``H_``/``W_`` are scaled
    (:func:`scale_intrinsics`) before anything else.
    """
    raw = easymocap.read_camera(intri_path, extri_path, names)
    cam_names = list(raw)
    if not cam_names:
        raise ValueError(f"{intri_path}: no cameras")
    if scale is not None:
        scale_calibration(raw, scale, intri_path)
    # 1. image size: from the files (all cameras agree), else from the arguments
    size = []
    for key, arg, what in (("H", height, "height"), ("W", width, "width")):
        in_file = sorted({raw[c][key] for c in cam_names if key in raw[c]})
        if len(in_file) > 1:
            raise ValueError(f"{intri_path}: cameras have different '{key}_<cam>' values {in_file}")
        if in_file:
            if arg is not None and int(arg) != in_file[0]:
                raise ValueError(f"{intri_path}: '{key}_<cam>' is {in_file[0]} but {what}={arg} was given")
            size.append(in_file[0])
        elif arg is not None:
            size.append(int(arg))
        else:
            raise ValueError(f"{intri_path}: no '{key}_<cam>' image size in the file and no {what} given")

    # 2. stack the per-camera arrays
    def stack(key: str) -> Tensor:
        return torch.as_tensor(np.stack([raw[c][key] for c in cam_names]), dtype=dtype)

    return Cameras(cam_names, stack("K"), stack("dist"), stack("R"), stack("T"), size[0], size[1])


def save_cameras(
    cams: Cameras, intri_path: str | os.PathLike, extri_path: str | os.PathLike, decimals: int | None = None
) -> None:
    """Write :class:`Cameras` as EasyMocap ``intri.yml`` / ``extri.yml`` (with ``H_``/``W_``).

    Values are written as exact doubles unless ``decimals`` is given (EasyMocap: 6).
    """
    _check_cams(cams, "save_cameras")

    def np64(t: Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float64).numpy()

    K, dist, R, T = np64(cams.K), np64(cams.dist), np64(cams.R), np64(cams.T)
    raw = {
        name: {"K": K[i], "dist": dist[i], "R": R[i], "T": T[i], "H": cams.height, "W": cams.width}
        for i, name in enumerate(cams.names)
    }
    easymocap.write_camera(intri_path, extri_path, raw, decimals)
