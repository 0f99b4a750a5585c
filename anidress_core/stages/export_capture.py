"""Stage ``export-capture``: a synthetic scene written as a user's capture would be (issue 24 item 4).

``anidress export-capture data/<scene> OUT`` takes a synthetic scene (``anidress synth``, rule
synth) and writes ``OUT`` without the crutches a capture does not have, each one a separate
option so that its effect can be measured alone:

* ``image_size`` (``--image-size WxH``; default: the width padded to 4:3, the height kept): every
  image cropped / padded about its centre (the principal point moves by the integer offset);
* ``distort`` (``--distort/--no-distort``): OpenCV radial-tangential lens distortion
  (:data:`DEFAULT_DIST`, varied per camera by :data:`DIST_SPREAD`) applied to the images with
  ``cv2.remap``; ``intri.yml`` gets the coefficients as ``dist_<cam>`` and, as EasyMocap's
  ``write_intri`` and OpenCV write it, no ``H_<cam>`` / ``W_<cam>``;
* ``pose_noise_cm`` (``--pose-noise-cm``): body poses with EasyMocap-level errors
  (:func:`noisy_body`: a slow drift plus frame-to-frame jitter on ``Th``, ``Rh`` and every joint
  rotation, scaled so that the mean joint position error is ``pose_noise_cm``), written as
  EasyMocap >= 0.2 body files (``poses`` of 69 numbers, the root rotation in ``Rh``);
* ``masks`` (``--masks none|parser``): no masks (the pipeline estimates them without background
  plates), or labels 0/1/2 as a human parser gives them (:func:`parser_labels`: a ragged
  silhouette, a grown or shrunk subject, a garment / body border shifted by a few pixels);

* ``flows`` (``--flows``): forward flows as an optical-flow network gives them (:func:`network_flow`: the
  true flows, warped with their vectors remapped through the lens, blurred, filled where the truth has
  none (occlusions) and with smooth noise: a flow at every pixel, as RAFT gives), for
  ``cues/flows/method: files``;
* ``cue_files`` (``--cue-files``, :data:`CUE_FILE_MODES`): the shipped masks, normals and flows in the
  pipeline's formats (``pipeline``: labels, EXR, EXR) or as the tools users run write them:
  ``easymocap_sapiens_raft`` (EasyMocap's ``mask-schp`` layout: a 0 / 255 silhouette per person
  ``masks/<cam>/<frame>_0.png`` and SCHP's CIHP part labels ``masks-parsing/<cam>/<frame>.png``; Sapiens
  ``.npy`` normals; RAFT ``.flo``) or ``lip_png_kitti`` (SCHP LIP palette PNGs, 8-bit (n+1)/2 normal PNGs,
  KITTI 16-bit flow PNGs); the tools' normals in OpenGL axes (x right, y up, z towards the camera),
  scene.yaml ``cues`` naming the formats;

and always: no background plates, no garment texture (nor the body texture), no ``gt/``. The
"predicted" normals are kept (warped like the images; ``normals=False`` drops them): a user runs a
normal predictor.

Written::

    OUT/scene.yaml                synthetic: false, kind, fps, image_size [H, W], cameras, sequences
                                  (no motion), body_model, garment_template / garment_kind,
                                  predicted_normals, source
    OUT/body_model.npz, OUT/garment/template.obj    copies
    OUT/<seq>/intri.yml extri.yml K_ (principal point moved), dist_, no H_/W_; R_, Rot_, T_ unchanged
    OUT/<seq>/images/<cam>/<frame:06d>.png          warped
    OUT/<seq>/smpl/<frame:06d>.json                 noisy, EasyMocap >= 0.2 layout
    OUT/<seq>/masks/<cam>/<frame:06d>.png           (masks=parser) warped, parser-like labels
    OUT/<seq>/normals/<cam>/<frame:06d>.exr         (normals) warped (.npy / .png: cue_files)
    OUT/<seq>/flows/<cam>/<frame:06d>.exr           (flows) frames 1.. (.flo / .png: cue_files)

and, held back beside it for scoring only (``truth``, default ``OUT.truth``)::

    TRUTH/export.json             the options, the distortion of each camera and what each
                                  degradation measured (joint error, angle error, jitter, mask IoU)
    TRUTH/source_scene.yaml       the synthetic scene's scene.yaml
    TRUTH/<seq>/smpl/             the exact body poses (the synthetic scene's files)
    TRUTH/<seq>/gt/masks/<cam>/<frame:06d>.png   the true labels warped to OUT's images
    TRUTH/<seq>/gt/meshes.npz     the true meshes (world coordinates: no warp needed)

The true normals and flows are not carried over.

Image warp (conventions of :mod:`anidress_core.camera`: pixel centres at integers). The source
camera is a pinhole ``K``; the exported one is ``K'`` (``K`` with the principal point moved by the
crop / pad offset ``(ox, oy)``) with distortion ``d``. A world point seen at ``u_o = K x`` in the
source image is seen at ``u_d = K' distort(x, d)`` in the exported one, so exported pixel ``u_d``
takes the source image at ``u_o = K undistort(K'^-1 u_d, d)`` (bilinear for images and normals,
nearest for labels; outside the source image: its edge replicated, a static background).

Everything is checked and computed before OUT is written; OUT and TRUTH are written beside their
targets and renamed into place complete. Errors name the file and the field.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np
import torch
import yaml

from .. import __version__
from ..body.model import BodyModel
from ..camera import Cameras, undistort_normalized
from ..geometry import axis_angle_to_matrix, matrix_to_axis_angle
from ..io import cue_files as cue_io
from ..io import easymocap, files
from ..io.images import image_size_from_header
from ..io.motion import read_easymocap_smpl_dir
from ..io.scene import IMAGE_EXTS, image_path, load_body, read_scene, scene_cameras, scene_image_size
from ..io.scene_info import scene_config_entry

__all__ = ["DEFAULT_DIST", "DIST_SPREAD", "MASK_MODES", "WarpMaps", "parse_image_size", "default_image_size",
           "camera_distortions", "exported_cameras", "warp_maps", "warp_image", "warp_labels", "warp_normals",
           "fold_root_pose", "noisy_body", "BodyNoise", "pose_errors", "parser_labels", "warp_flow", "network_flow",
           "CUE_FILE_MODES", "run_export_capture"]

log = logging.getLogger("anidress.export")

DEFAULT_DIST = (-0.20, 0.05, 4e-4, -6e-4, 0.0)
"""OpenCV ``k1 k2 p1 p2 k3`` of the exported cameras: a moderate barrel distortion (at the corner of a
342 x 256 image with the demo's 38 degree vertical field of view, r = 0.57, the radial factor is 0.94:
about 13 px of displacement), tangential terms of a slightly decentred lens. Monotonic over the image
(d r_d / d r = 1 + 3 k1 r^2 + 5 k2 r^4 > 0 for every r at these values; with the per-camera spread below,
at three sigma, up to r = 1.2, far beyond the image corners)."""
DIST_SPREAD = 0.15
"""Relative spread of each camera's coefficients about :data:`DEFAULT_DIST` (normal, seeded): the
cameras of a rig are not identical."""
CUE_FILE_MODES = ("pipeline", "easymocap_sapiens_raft", "lip_png_kitti")
"""Formats of the shipped cues: the pipeline's own, or two sets of the tools' (module docstring)."""
OPENGL_AXES = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
"""OpenCV camera axes to OpenGL's (x right, y up, z towards the viewer), the axes the tools' normals use here."""
MASK_MODES = ("none", "parser")
"""``none``: no masks (the pipeline estimates them); ``parser``: labels with a human parser's errors."""
NOISE_SLOW_S = 0.15
"""Time scale (s, Gaussian sigma) of the slow part of the body-pose noise (a fit's drift)."""
NOISE_JITTER_SHARE = 0.3
"""Share of the body-pose noise variance that is white frame-to-frame jitter (the rest is slow drift)."""
NOISE_BASE = {"Th_m": 0.01, "Rh_rad": np.deg2rad(1.5), "joint_rad": np.deg2rad(3.0)}
"""Relative sizes of the noise components (per axis) before :func:`noisy_body` scales all of them to
the requested joint error: root translation (m), root rotation, each joint's local rotation (rad)."""


# =========================================================================== options
def parse_image_size(spec: str | Sequence[int] | None) -> tuple[int, int] | None:
    """``"WxH"`` (or (W, H)) -> (H, W); None stays None. ValueError naming the option otherwise."""
    if spec is None:
        return None
    try:
        if isinstance(spec, str):
            w, h = (int(x) for x in spec.lower().split("x"))
        else:
            w, h = (int(x) for x in spec)
    except (ValueError, TypeError):
        raise ValueError(f"--image-size {spec!r}: expected WxH in pixels, e.g. 320x240") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"--image-size {spec!r}: width and height must be positive")
    return h, w


def default_image_size(height: int, width: int) -> tuple[int, int]:
    """(H, W) of the exported images: the height kept, the width padded to 4:3 (even), never cropped."""
    return height, max(width, 2 * round(height * 4 / 3 / 2))


# =========================================================================== cameras and the image warp
def camera_distortions(n: int, seed: int, base: Sequence[float] = DEFAULT_DIST,
                       spread: float = DIST_SPREAD) -> np.ndarray:
    """(n, 5) float64 ``k1 k2 p1 p2 k3`` per camera: ``base * (1 + spread * N(0, 1))``, seeded."""
    rng = np.random.default_rng([int(seed), 101])
    b = np.asarray(base, np.float64)
    return b[None] * (1.0 + spread * rng.standard_normal((n, 5)))


def exported_cameras(cams: Cameras, size: tuple[int, int], dist: np.ndarray | None) -> tuple[Cameras, tuple[int, int]]:
    """The exported cameras and the crop / pad offset (ox, oy) in pixels.

    cams: the source pinhole cameras (C); size: (H', W') of the exported images; dist: (C, 5) or
    None (pinhole). The offset centres the source image in the new one (integer, negative = crop);
    ``K'[:, 0, 2] = cx + ox``, ``K'[:, 1, 2] = cy + oy``; R, T unchanged.
    """
    H2, W2 = int(size[0]), int(size[1])
    ox, oy = (W2 - cams.width) // 2, (H2 - cams.height) // 2
    K = cams.K.clone()
    K[:, 0, 2] += ox
    K[:, 1, 2] += oy
    d = torch.zeros_like(cams.dist) if dist is None else torch.as_tensor(dist, dtype=cams.dtype)
    if tuple(d.shape) != (len(cams), 5):
        raise ValueError(f"exported_cameras: dist must be ({len(cams)}, 5), got {tuple(d.shape)}")
    return Cameras(list(cams.names), K, d, cams.R.clone(), cams.T.clone(), H2, W2), (ox, oy)


class WarpMaps(NamedTuple):
    """Per-camera lookup of the source image position of every exported pixel (``cv2.remap``)."""

    map_x: np.ndarray
    """(C, H', W') float32 source column of each exported pixel."""
    map_y: np.ndarray
    """(C, H', W') float32 source row."""


def warp_maps(src: Cameras, dst: Cameras) -> WarpMaps:
    """Maps from ``dst`` (exported: K', distortion) pixels to ``src`` (pinhole: K) pixels.

    ``u_o = K undistort(K'^-1 u_d, d)`` for every exported pixel centre u_d (module docstring);
    float64 throughout (20 fixed-point iterations of :func:`undistort_normalized`).
    """
    if src.names != dst.names:
        raise ValueError(f"warp_maps: camera names differ: {src.names} vs {dst.names}")
    H, W = dst.height, dst.width
    C = len(dst)
    K2 = dst.K.to(torch.float64)
    K = src.K.to(torch.float64)
    # 1. exported pixel centres (H'*W', 2)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    uv = torch.stack([u, v], -1).reshape(-1, 2)
    # 2. distorted normalised coordinates: y = (v - cy') / fy', x = (u - cx' - s y) / fx'
    y = (uv[None, :, 1] - K2[:, 1, 2, None]) / K2[:, 1, 1, None]
    x = (uv[None, :, 0] - K2[:, 0, 2, None] - K2[:, 0, 1, None] * y) / K2[:, 0, 0, None]
    xy = undistort_normalized(torch.stack([x, y], -1), dst.dist.to(torch.float64))  # (C, N, 2)
    # 3. source intrinsics: uv_o[c, n, i] = sum_j K[c, i, j] xy[c, n, j] + K[c, i, 2]
    uv_o = torch.einsum("cij,cnj->cni", K[:, :2, :2], xy) + K[:, None, :2, 2]
    return WarpMaps(uv_o[..., 0].reshape(C, H, W).numpy().astype(np.float32),
                    uv_o[..., 1].reshape(C, H, W).numpy().astype(np.float32))


def _remap(a: np.ndarray, maps: WarpMaps, cam: int, interp: int) -> np.ndarray:
    import cv2

    out = cv2.remap(np.ascontiguousarray(a), maps.map_x[cam], maps.map_y[cam], interp,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(maps.map_x.shape[1:] + a.shape[2:])


def warp_image(image: np.ndarray, maps: WarpMaps, cam: int) -> np.ndarray:
    """Bilinear warp of an image (H, W[, Ch]) of camera ``cam`` to (H', W'[, Ch]), same dtype."""
    import cv2

    return _remap(image, maps, cam, cv2.INTER_LINEAR)


def warp_labels(labels: np.ndarray, maps: WarpMaps, cam: int) -> np.ndarray:
    """Nearest-neighbour warp of a label mask (H, W) integer to (H', W') (labels never blend)."""
    import cv2

    if labels.ndim != 2 or labels.dtype.kind not in "ui":
        raise ValueError(f"warp_labels: a label mask is (H, W) integer, got {labels.shape} {labels.dtype}")
    return _remap(labels, maps, cam, cv2.INTER_NEAREST)


def warp_normals(normals: np.ndarray, maps: WarpMaps, cam: int, eps: float = 1e-6) -> np.ndarray:
    """Bilinear warp of a camera-space normal map (H, W, 3), renormalised (zero where the blend is
    shorter than ``eps``: background or opposite normals). The camera's rotation is unchanged, so the
    normals keep their frame. Returns (H', W', 3) float32."""
    import cv2

    n = _remap(np.asarray(normals[..., :3], np.float32), maps, cam, cv2.INTER_LINEAR)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = np.isfinite(norm) & (norm > eps)
    return np.where(ok, n / np.where(ok, norm, 1.0), 0.0).astype(np.float32)


def warp_flow(flow: np.ndarray, valid: np.ndarray, maps: WarpMaps, cam: int, src: Cameras,
              dst: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """A forward flow (H, W, 2) of camera ``cam`` with validity (H, W) as the exported camera sees it, the
    vectors remapped (:func:`anidress_core.undistort.remap_flow`: source pixel s goes to ``K' distort(K^-1 s)``,
    :func:`anidress_core.undistort.pixel_map`). Returns (flow (H', W', 2) float32, valid (H', W') bool)."""
    from ..undistort import pixel_map, remap_flow

    H, W = flow.shape[:2]
    mx, my = maps.map_x[cam], maps.map_y[cam]
    inside = (mx >= -0.5) & (mx <= W - 0.5) & (my >= -0.5) & (my <= H - 0.5)
    return remap_flow(flow, valid, mx, my, inside, pixel_map(src.select(cam), dst.select(cam)))


def network_flow(flow: np.ndarray, valid: np.ndarray, rng: np.random.Generator, scale: float = 1.0,
                 blur_px: float = 1.5, noise_px: float = 0.3, fill_px: float = 8.0) -> np.ndarray:
    """A true flow (H, W, 2) with validity (H, W) degraded as an optical-flow network's, dense like RAFT's
    (which gives a flow at every pixel, occluded ones included): blurred across motion boundaries (Gaussian,
    ``blur_px`` sigma, normalised over the valid pixels), the pixels without a true flow filled from their
    neighbourhood (normalised Gaussian of ``fill_px`` sigma; 0 where none is near), plus smooth noise (sigma 6 px
    in space, ``noise_px`` per component); lengths in pixels of 256-px images times ``scale``.
    Returns (H, W, 2) float32, every pixel a flow."""
    import cv2

    w = valid.astype(np.float32)
    f = np.where(valid[..., None], flow, 0).astype(np.float32)

    def smooth(sigma: float) -> tuple[np.ndarray, np.ndarray]:
        return cv2.GaussianBlur(f * w[..., None], (0, 0), sigma * scale), cv2.GaussianBlur(w, (0, 0), sigma * scale)

    num, den = smooth(blur_px)
    num_f, den_f = smooth(fill_px)
    near = den > 0.05
    out = np.where(near[..., None], num / np.maximum(den, 1e-6)[..., None],
                   np.where((den_f > 1e-4)[..., None], num_f / np.maximum(den_f, 1e-6)[..., None], 0.0))
    out = out + noise_px * np.stack([_smooth_noise(rng, valid.shape, 6 * scale) for _ in range(2)], -1)
    return out.astype(np.float32)


# =========================================================================== body poses
def fold_root_pose(poses: np.ndarray, Rh: np.ndarray, Th: np.ndarray, J0: np.ndarray) -> tuple[np.ndarray, ...]:
    """Move the root joint's rotation ``poses[:, :3]`` (about the root joint J0) into ``Rh`` / ``Th``.

    poses (T, 72), Rh, Th (T, 3), J0 (3,) or (T, 3) the shaped rest root joint. The body
    ``R_h (R_0 (x - J0) + J0) + T_h`` equals ``R_h' x + T_h'`` with ``R_h' = R_h R_0`` and
    ``T_h' = T_h + R_h J0 - R_h R_0 J0``. Returns (poses with zero root, Rh', Th'), float64.
    """
    P = np.array(poses, np.float64)
    Rh_m = axis_angle_to_matrix(torch.as_tensor(Rh, dtype=torch.float64))
    R0 = axis_angle_to_matrix(torch.as_tensor(P[:, :3]))
    J = torch.as_tensor(np.broadcast_to(np.asarray(J0, np.float64), np.shape(Th)).copy())
    R = Rh_m @ R0
    # T'[t, i] = Th[t, i] + sum_j Rh[t, i, j] J[t, j] - sum_j R[t, i, j] J[t, j]
    T2 = torch.as_tensor(Th, dtype=torch.float64) + torch.einsum("tij,tj->ti", Rh_m - R, J)
    P[:, :3] = 0.0
    return P, matrix_to_axis_angle(R).numpy(), T2.numpy()


class BodyNoise(NamedTuple):
    """Noisy body parameters and what the noise measured."""

    poses: np.ndarray
    """(T, 72) axis-angle, root zero (its rotation is in Rh)."""
    Rh: np.ndarray
    """(T, 3) global rotation (axis-angle)."""
    Th: np.ndarray
    """(T, 3) global translation (m)."""
    scale: float
    """The factor applied to :data:`NOISE_BASE` to reach the requested joint error."""
    errors: dict
    """:func:`pose_errors` of the noisy against the true poses."""


def _noise_field(rng: np.random.Generator, T: int, D: int, fps: float) -> np.ndarray:
    """(T, D) unit-variance noise: a slow part (white noise smoothed over :data:`NOISE_SLOW_S`,
    renormalised) plus white jitter, mixed by :data:`NOISE_JITTER_SHARE`."""
    sigma = max(NOISE_SLOW_S * fps, 1e-6)
    r = int(np.ceil(3 * sigma))
    pad = rng.standard_normal((T + 2 * r, D))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= np.sqrt((k ** 2).sum())  # unit variance of the smoothed stationary noise
    slow = np.stack([np.convolve(pad[:, d], k, mode="valid") for d in range(D)], -1)  # (T, D)
    white = rng.standard_normal((T, D))
    return np.sqrt(1 - NOISE_JITTER_SHARE) * slow + np.sqrt(NOISE_JITTER_SHARE) * white


def _perturb(poses, Rh, Th, unit: dict, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    T = poses.shape[0]
    P = torch.as_tensor(poses, dtype=torch.float64).reshape(T, 24, 3)
    dj = torch.as_tensor(unit["joint"] * s * NOISE_BASE["joint_rad"]).reshape(T, 23, 3)
    # local joint rotations 1..23: R_j' = R_j exp(delta_j)
    Rj = axis_angle_to_matrix(P[:, 1:]) @ axis_angle_to_matrix(dj)
    P2 = torch.cat([P[:, :1], matrix_to_axis_angle(Rj)], 1).reshape(T, 72)
    # global rotation: R_h' = exp(delta_h) R_h (a world-frame error); translation: Th + delta_t
    Rg = axis_angle_to_matrix(torch.as_tensor(unit["Rh"] * s * NOISE_BASE["Rh_rad"])) @ \
        axis_angle_to_matrix(torch.as_tensor(Rh, dtype=torch.float64))
    Th2 = np.asarray(Th, np.float64) + unit["Th"] * s * NOISE_BASE["Th_m"]
    return P2.numpy(), matrix_to_axis_angle(Rg).numpy(), Th2


def _joints(body: BodyModel, poses, Rh, Th, shapes) -> np.ndarray:
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return body.pose(t(poses), t(Rh), t(Th), None if shapes is None else t(shapes)).joints.double().numpy()


def pose_errors(body: BodyModel, true: dict, noisy: dict) -> dict:
    """Errors of ``noisy`` body parameters against ``true`` (dicts of poses (T, 72), Rh, Th (T, 3), shapes).

    Returns joint_error_cm (mean over frames and the 24 joints of the position error), joint_angle_deg
    (mean geodesic angle of joints 1..23's local rotations), root_angle_deg (of the global orientation
    Rh with the root pose), root_translation_cm (Th), jitter_cm (mean norm of the error's frame-to-frame
    change of the joint positions, i.e. of the joint velocity error per frame; 0 for one frame).
    """
    Jt = _joints(body, true["poses"], true["Rh"], true["Th"], true.get("shapes"))
    Jn = _joints(body, noisy["poses"], noisy["Rh"], noisy["Th"], noisy.get("shapes"))
    E = Jn - Jt  # (T, 24, 3)
    T = E.shape[0]

    def rot(p):
        return axis_angle_to_matrix(torch.as_tensor(np.asarray(p, np.float64).reshape(T, -1, 3)))

    def angle(Ra, Rb):
        c = ((Ra.transpose(-1, -2) @ Rb).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
        return torch.rad2deg(torch.arccos(c.clamp(-1, 1)))

    def glob(d):  # global orientation: R(Rh) R(root pose)
        return axis_angle_to_matrix(torch.as_tensor(np.asarray(d["Rh"], np.float64))) @ rot(d["poses"])[:, 0]

    dT = np.asarray(noisy["Th"]) - np.asarray(true["Th"])
    return {
        "joint_error_cm": float(100 * np.linalg.norm(E, axis=-1).mean()),
        "joint_angle_deg": float(angle(rot(true["poses"])[:, 1:], rot(noisy["poses"])[:, 1:]).mean()),
        "root_angle_deg": float(angle(glob(true), glob(noisy)).mean()),
        "root_translation_cm": float(100 * np.linalg.norm(dT, axis=-1).mean()),
        "jitter_cm": float(100 * np.linalg.norm(np.diff(E, axis=0), axis=-1).mean()) if T > 1 else 0.0,
    }


def noisy_body(body: BodyModel, poses: np.ndarray, Rh: np.ndarray, Th: np.ndarray, shapes: np.ndarray | None,
               target_cm: float, fps: float, seed: int, tol: float = 0.02) -> BodyNoise:
    """Body parameters with EasyMocap-like errors whose mean joint position error is ``target_cm``.

    poses (T, 72) (root zero: :func:`fold_root_pose` first), Rh, Th (T, 3), shapes (S,) or None.
    Noise (seeded by ``seed``; :func:`_noise_field` per component: slow drift + jitter) of relative
    sizes :data:`NOISE_BASE` on Th, on Rh (a world-frame rotation) and on each joint's local rotation,
    all scaled by one factor s, found by secant steps on the measured error (relative ``tol``).
    target_cm = 0 returns the input unchanged.
    """
    T = poses.shape[0]
    true = {"poses": poses, "Rh": Rh, "Th": Th, "shapes": shapes}
    if target_cm <= 0:
        return BodyNoise(np.array(poses, np.float64), np.array(Rh, np.float64), np.array(Th, np.float64), 0.0,
                         pose_errors(body, true, true))
    rng = np.random.default_rng([int(seed), 202])
    unit = {"Th": _noise_field(rng, T, 3, fps), "Rh": _noise_field(rng, T, 3, fps),
            "joint": _noise_field(rng, T, 69, fps)}

    def err(s):
        P, R, Tt = _perturb(poses, Rh, Th, unit, s)
        return pose_errors(body, true, {"poses": P, "Rh": R, "Th": Tt, "shapes": shapes})

    # the error grows about linearly with s (small rotations): secant steps from s = 1
    s = 1.0
    for _ in range(8):
        e = err(s)["joint_error_cm"]
        if abs(e - target_cm) <= tol * target_cm:
            break
        s *= target_cm / max(e, 1e-12)
    P, R, Tt = _perturb(poses, Rh, Th, unit, s)
    return BodyNoise(P, R, Tt, float(s), pose_errors(body, true, {"poses": P, "Rh": R, "Th": Tt, "shapes": shapes}))


def write_easymocap_02(path: Path, poses: np.ndarray, Rh: np.ndarray, Th: np.ndarray, shapes: np.ndarray) -> None:
    """One frame as EasyMocap >= 0.2 writes a SMPL body (``use_root_rot=False``): a list of people, each
    ``{"id", "Rh": [[3]], "Th": [[3]], "poses": [[69]], "shapes": [[S]]}``; poses (72,) with a zero root."""
    import json

    p = np.asarray(poses, np.float64).reshape(-1)
    if p.size != 72 or np.any(p[:3] != 0):
        raise ValueError(f"{path}: poses must be 72 numbers with a zero root rotation (fold it into Rh first)")
    person = {"id": 0, "Rh": [np.asarray(Rh, float).tolist()], "Th": [np.asarray(Th, float).tolist()],
              "poses": [p[3:].tolist()], "shapes": [np.asarray(shapes, float).reshape(-1).tolist()]}
    files.write_text(path, json.dumps([person]) + "\n")


# =========================================================================== parser-like masks
def _signed_distance(m: np.ndarray) -> np.ndarray:
    """(H, W) float32: distance to the region's border in pixels, positive inside ``m``, negative outside."""
    import cv2

    m8 = m.astype(np.uint8)
    inside = cv2.distanceTransform(m8, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 5)
    return np.where(m, inside - 0.5, 0.5 - outside).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, shape, sigma: float) -> np.ndarray:
    import cv2

    n = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
    return n / max(float(n.std()), 1e-6)


def parser_labels(labels: np.ndarray, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """Labels 0/1/2 (H, W) uint8 with a human parser's typical errors (for 256-px images; ``scale``
    multiplies every length in pixels):

    1. the subject grown or shrunk by a per-image offset (normal, sigma 1 px) plus a ragged border
       (smooth noise, sigma 3 px in space, amplitude 1.5 px);
    2. the garment / body border moved by a per-image offset (normal, sigma 2 px: hem pixels given to
       the legs or leg pixels to the skirt) plus its own ragged border (amplitude 2 px);
    3. the labels inside the new subject: garment where the moved garment region is, body elsewhere.
    """
    lab = np.asarray(labels)
    if lab.ndim != 2 or lab.dtype.kind not in "ui" or (lab.size and lab.max() > 2):
        raise ValueError(f"parser_labels: labels are (H, W) integers 0/1/2, got {lab.shape} {lab.dtype}")
    person = lab > 0
    garment = lab == 2
    if not person.any():
        return np.zeros_like(lab, dtype=np.uint8)
    # 1. subject border
    d = _signed_distance(person) + scale * (rng.normal(0, 1.0) + 1.5 * _smooth_noise(rng, lab.shape, 3 * scale))
    person2 = d > 0
    out = person2.astype(np.uint8)
    # 2. garment / body border
    if garment.any():
        dg = _signed_distance(garment) + scale * (rng.normal(0, 2.0) + 2.0 * _smooth_noise(rng, lab.shape, 3 * scale))
        out[person2 & (dg > 0)] = 2
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


# =========================================================================== the stage
def _check_source(src: Path, masks: str, flows: bool = False) -> dict:
    info = read_scene(src)
    yml = src / "scene.yaml"
    if info.get("synthetic") is not True:
        raise ValueError(f"{yml}: 'synthetic' is {info.get('synthetic')!r}: export-capture takes a synthetic scene "
                         "(written by anidress synth), whose ground truth it holds back")
    seqs = info.get("sequences")
    if not isinstance(seqs, list) or not seqs or not all(isinstance(s, dict) and s.get("name") for s in seqs):
        raise ValueError(f"{yml}: 'sequences' must be a list of {{name, frames, role}}")
    cams = info.get("cameras") or {}
    if not cams.get("train"):
        raise ValueError(f"{yml}: 'cameras/train' is missing or empty")
    for s in seqs:
        sdir = src / s["name"]
        for need in (("intri.yml", "extri.yml", "smpl", "gt/meshes.npz") + (("gt/masks",) if masks == "parser" else ())
                     + (("gt/flows",) if flows else ())):
            if not (sdir / need).exists():
                raise FileNotFoundError(f"{sdir / need}: not found (sequence '{s['name']}' of {yml})")
    return info


def run_export_capture(src: str | os.PathLike, out: str | os.PathLike, distort: bool = True,
                       pose_noise_cm: float = 2.0, masks: str = "none", image_size: str | Sequence[int] | None = None,
                       seed: int = 0, normals: bool = True, truth: str | os.PathLike | None = None,
                       threads: int = 2, flows: bool = False, cue_files: str = "pipeline") -> dict:
    """Write the synthetic scene ``src`` as a capture into ``out`` and its truth into ``truth``
    (default ``<out>.truth``); see the module doc. image_size: ``"WxH"`` (default
    :func:`default_image_size`); masks: :data:`MASK_MODES`; flows: ship network-like flows; cue_files:
    :data:`CUE_FILE_MODES`; seed: every random choice (distortion spread, body noise, mask and flow errors). Returns the export record (also ``truth/export.json``).
    """
    t0 = time.perf_counter()
    src, out = Path(src), Path(out)
    truth = Path(truth) if truth is not None else out.parent / f"{out.name}.truth"
    if masks not in MASK_MODES:
        raise ValueError(f"masks must be one of {list(MASK_MODES)}, got {masks!r}")
    if cue_files not in CUE_FILE_MODES:
        raise ValueError(f"cue_files must be one of {list(CUE_FILE_MODES)}, got {cue_files!r}")
    if not (isinstance(pose_noise_cm, (int, float)) and np.isfinite(pose_noise_cm) and pose_noise_cm >= 0):
        raise ValueError(f"pose_noise_cm must be a number >= 0, got {pose_noise_cm!r}")
    size_arg = parse_image_size(image_size)
    for d in (out, truth):
        if d.exists() and (not d.is_dir() or any(d.iterdir())):
            raise ValueError(f"{d}: exists and is not empty (export-capture writes a new folder)")
    if out.resolve() == src.resolve() or truth.resolve() == out.resolve():
        raise ValueError(f"{out}: the output must differ from the source scene and from the truth folder")
    # 1. read and check everything before writing
    info = _check_source(src, masks, flows)
    body = load_body(src, info)
    seq_names = [s["name"] for s in info["sequences"]]
    used = list(info["cameras"]["train"]) + list(info["cameras"].get("test") or [])
    plan = []
    for k, seq in enumerate(seq_names):
        in_file = easymocap.read_names(src / seq / "intri.yml")
        missing = [c for c in used if c not in in_file]
        if missing:
            raise ValueError(f"{src / seq / 'intri.yml'}: cameras {missing} of scene.yaml 'cameras' are not in "
                             "the file")
        cams = scene_cameras(src, seq, [c for c in in_file if c in used], info)
        H, W = scene_image_size(src, seq, info)
        size = size_arg or default_image_size(H, W)
        dist = camera_distortions(len(cams), seed) if distort else None
        cams2, offset = exported_cameras(cams, size, dist)
        sm = read_easymocap_smpl_dir(src / seq / "smpl")
        T = len(sm["frames"])
        if sm["frames"] != list(range(T)):
            raise ValueError(f"{src / seq / 'smpl'}: body files must be numbered 0..{T - 1}, got {sm['frames'][:5]}...")
        for cam in used:
            for t in (0, T - 1):
                p = image_path(src / seq, cam, t)
                if not p.is_file():
                    raise FileNotFoundError(f"{p}: image of camera '{cam}', frame {t} not found")
                if image_size_from_header(p) != (H, W):
                    raise ValueError(f"{p}: image is {image_size_from_header(p)[::-1]} (WxH), scene.yaml "
                                     f"image_size is {W}x{H}")
        _, J = body.shaped(torch.as_tensor(sm["shapes"][0], dtype=torch.float32))
        P, Rh, Th = fold_root_pose(sm["poses"], sm["Rh"], sm["Th"], J[0].double().numpy())
        noise = noisy_body(body, P, Rh, Th, sm["shapes"][0], float(pose_noise_cm), float(info["fps"]),
                           seed * 1000 + k)
        plan.append(dict(seq=seq, cams=cams, cams2=cams2, offset=offset, size=size, T=T, sm=sm, noise=noise))
    # 2. write OUT and TRUTH beside their targets
    for d in (out, truth):
        d.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    tmp_t = Path(tempfile.mkdtemp(prefix=f".{truth.name}.partial-", dir=truth.parent))
    record = {"format": "anidress-export-capture", "source": str(src.resolve()), "scene_dir": str(out),
              "truth_dir": str(truth), "options": {"distort": bool(distort), "pose_noise_cm": float(pose_noise_cm),
                                                   "masks": masks, "image_size": None, "seed": int(seed),
                                                   "normals": bool(normals), "flows": bool(flows),
                                                   "cue_files": cue_files},
              "dropped": ["backgrounds/", "gt/", "garment/texture.png", "body_texture.png"], "sequences": {},
              "code_version": __version__}
    try:
        shutil.copyfile(src / info["body_model"]["file"], tmp / info["body_model"]["file"])
        if info.get("garment_template"):
            (tmp / info["garment_template"]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / info["garment_template"], tmp / info["garment_template"])
        shutil.copyfile(src / "scene.yaml", tmp_t / "source_scene.yaml")
        with ThreadPoolExecutor(max_workers=max(1, int(threads))) as pool:
            for k, p in enumerate(plan):
                record["sequences"][p["seq"]] = _export_sequence(src, tmp, tmp_t, p, info, used, masks, normals,
                                                                 seed * 1000 + k, pool, flows, cue_files)
        H2, W2 = plan[0]["size"]
        record["options"]["image_size"] = f"{W2}x{H2}"
        scene = {"name": out.name, "synthetic": False, "kind": info.get("kind", "tight"), "fps": float(info["fps"]),
                 "units": "metres", "up": info.get("up", [0.0, 0.0, 1.0]), "image_size": [int(H2), int(W2)],
                 "cameras": {"train": list(info["cameras"]["train"]), "test": list(info["cameras"].get("test") or [])},
                 "sequences": [{"name": s["name"], "role": s.get("role", "train"), "frames": int(s["frames"])}
                               for s in info["sequences"]],
                 "body_model": dict(info["body_model"])}
        if info.get("garment_template"):
            scene.update(garment_template=info["garment_template"], garment_kind=info.get("garment_kind"))
        if normals and info.get("predicted_normals"):
            scene["predicted_normals"] = "normals"
        if cue_files == "easymocap_sapiens_raft":
            scene["cues"] = {"masks": {"format": "schp", "label_set": "cihp", "person": 0},
                             "normals": {"format": "sapiens"}, "flows": {"format": "raft"}}
        elif cue_files == "lip_png_kitti":
            scene["cues"] = {"masks": {"format": "schp", "label_set": "lip"}, "normals": {"format": "png"},
                             "flows": {"format": "kitti"}}
        scene["source"] = {"format": "anidress-export-capture", "path": str(src.resolve())}
        record["config_entry"] = scene_config_entry(scene)
        record["wall_s"] = round(time.perf_counter() - t0, 3)
        files.write_json(tmp_t / "export.json", record)
        files.write_text(tmp / "scene.yaml", yaml.safe_dump(scene, sort_keys=False))
        os.replace(tmp_t, truth)
        os.replace(tmp, out)
    finally:
        for d in (tmp, tmp_t):
            if d.exists():
                shutil.rmtree(d, ignore_errors=True)
    log.info("export-capture %s -> %s (truth %s): %s, distortion %s, body noise %.2f cm, masks %s (%.1f s)", src, out,
             truth, record["options"]["image_size"], "on" if distort else "off", float(pose_noise_cm), masks,
             record["wall_s"])
    return record


def _parser_indices(labels: np.ndarray, label_set: str, garment_kind: str | None) -> np.ndarray:
    """Labels 0/1/2 as a human parser's label indices of ``label_set``: the garment its Skirt or Dress, the body
    Upper-clothes above the garment's top row and Left-leg below it."""
    from ..io.cue_files import SCHP_LABEL_SETS

    names = [n.lower() for n in SCHP_LABEL_SETS[label_set]]
    out = np.zeros(labels.shape, np.uint8)
    rows = np.nonzero((labels == 2).any(1))[0]
    top = rows[0] if rows.size else labels.shape[0]
    body = labels == 1
    upper = np.zeros_like(body)
    upper[:top] = True
    out[body & upper] = names.index("upper-clothes")
    out[body & ~upper] = names.index("left-leg")
    out[labels == 2] = names.index("dress" if garment_kind == "dress" else "skirt")
    return out


def _export_sequence(src: Path, dst: Path, truth: Path, p: dict, info: dict, used: list[str], masks: str,
                     normals: bool, seed: int, pool: ThreadPoolExecutor, flows: bool = False,
                     cue_files: str = "pipeline") -> dict:
    """Write one sequence into ``dst`` (the capture) and ``truth``; returns its record."""
    seq, cams, cams2, T = p["seq"], p["cams"], p["cams2"], p["T"]
    sdir, odir, tdir = src / seq, dst / seq, truth / seq
    # 1. cameras: K', dist, no H_/W_ (as EasyMocap's write_intri)
    K2, d2, R, Tc = (cams2.K.numpy(), cams2.dist.numpy(), cams2.R.numpy(), cams2.T.numpy())
    easymocap.write_camera(odir / "intri.yml", odir / "extri.yml",
                           {n: {"K": K2[c], "dist": d2[c], "R": R[c], "T": Tc[c]} for c, n in enumerate(cams2.names)})
    # 2. body: noisy, EasyMocap >= 0.2 files; the truth keeps the source files
    nz, shapes = p["noise"], p["sm"]["shapes"]
    for t in range(T):
        write_easymocap_02(odir / "smpl" / f"{t:06d}.json", nz.poses[t], nz.Rh[t], nz.Th[t], shapes[t])
    shutil.copytree(sdir / "smpl", tdir / "smpl")
    (tdir / "gt").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(sdir / "gt" / "meshes.npz", tdir / "gt" / "meshes.npz")
    # 3. images, truth masks, parser masks, normals: warped per camera
    maps = warp_maps(cams, cams2)
    has_gt_masks = (sdir / "gt" / "masks").is_dir()
    has_normals = normals and (sdir / "normals").is_dir()
    scale = cams2.height / 256.0
    ious = {"person": [], "garment": []}

    def one(c: int, cam: str, t: int):
        name = f"{t:06d}"
        files.write_png(odir / "images" / cam / f"{name}.png",
                        warp_image(files.read_image(image_path(sdir, cam, t)), maps, c))
        res = None
        if has_gt_masks:
            lab = warp_labels(files.read_mask(sdir / "gt" / "masks" / cam / f"{name}.png"), maps, c)
            files.write_mask(tdir / "gt" / "masks" / cam / f"{name}.png", lab)
            if masks == "parser":
                rng = np.random.default_rng([int(seed), 303, c, t])
                pl = parser_labels(lab, rng, scale)
                if cue_files == "pipeline":
                    files.write_mask(odir / "masks" / cam / f"{name}.png", pl)
                elif cue_files == "easymocap_sapiens_raft":  # EasyMocap's mask-schp: silhouettes + CIHP parsing
                    files.write_png(odir / "masks" / cam / f"{name}_0.png", np.where(pl > 0, 255, 0).astype(np.uint8))
                    cue_io.write_schp_png(odir / "masks-parsing" / cam / f"{name}.png",
                                          _parser_indices(pl, "cihp", info.get("garment_kind")))
                else:
                    cue_io.write_schp_png(odir / "masks" / cam / f"{name}.png",
                                          _parser_indices(pl, "lip", info.get("garment_kind")))
                res = (_iou(pl > 0, lab > 0), _iou(pl == 2, lab == 2) if (lab == 2).any() else None)
        if has_normals:
            n = warp_normals(files.read_exr(sdir / "normals" / cam / f"{name}.exr"), maps, c)
            if cue_files == "pipeline":
                files.write_exr(odir / "normals" / cam / f"{name}.exr", n, None, True)
            elif cue_files == "easymocap_sapiens_raft":
                cue_io.write_sapiens_normals(odir / "normals" / cam / f"{name}.npy", n @ OPENGL_AXES.T)
            else:
                cue_io.write_normal_image(odir / "normals" / cam / f"{name}.png", n @ OPENGL_AXES.T, bits=8)
        if flows and t > 0:
            g = files.read_exr(sdir / "gt" / "flows" / cam / f"{name}.exr")
            fl, ok = warp_flow(g[..., :2], g[..., 2] > 0.5, maps, c, cams, cams2)
            fl = network_flow(fl, ok, np.random.default_rng([int(seed), 505, c, t]), scale)  # dense: all valid
            if cue_files == "pipeline":
                files.write_exr(odir / "flows" / cam / f"{name}.exr",
                                np.concatenate([fl, np.ones_like(fl[..., :1])], -1), ("X", "Y", "valid"))
            elif cue_files == "easymocap_sapiens_raft":
                cue_io.write_flo(odir / "flows" / cam / f"{name}.flo", fl)
            else:  # as RAFT's writeFlowKITTI: valid 1 everywhere
                cue_io.write_kitti_flow(odir / "flows" / cam / f"{name}.png", fl)
        return res

    jobs = [pool.submit(one, c, cam, t) for t in range(T) for c, cam in enumerate(cams.names)]
    for j in jobs:  # the first failure in order raises
        r = j.result()
        if r is not None:
            ious["person"].append(r[0])
            if r[1] is not None:
                ious["garment"].append(r[1])
    rec = {"frames": T, "cameras": list(cams.names), "offset_px": list(p["offset"]),
           "image_size": [cams2.height, cams2.width],
           "dist": {n: [float(x) for x in d2[c]] for c, n in enumerate(cams.names)},
           "body_noise": {"scale": nz.scale, **nz.errors}}
    if masks == "parser":
        rec["mask_iou"] = {k: float(np.mean(v)) if v else None for k, v in ious.items()}
    return rec
