"""Dense forward optical flow t-1 -> t with OpenCV, restricted to the subject's region.

The paper (AniDress §3.2) uses RAFT flow for its optical-flow loss; RAFT's weights
cannot be downloaded here, so the cue comes from the classical estimators of
OpenCV (main module and opencv-contrib ``optflow``):

* ``dis_ultrafast`` / ``dis_fast`` / ``dis_medium``: DIS, Kroeger et al., "Fast
  Optical Flow using Dense Inverse Search", ECCV 2016 (``cv2.DISOpticalFlow``
  presets, which include the variational refinement);
* ``deepflow``: Weinzaepfel et al., "DeepFlow", ICCV 2013
  (``cv2.optflow.createOptFlow_DeepFlow``);
* ``tvl1``: Zach, Pock, Bischof, "A duality based approach for realtime TV-L1
  optical flow", DAGM 2007 (``cv2.optflow.DualTVL1OpticalFlow_create``);
* ``farneback``: Farnebäck, "Two-frame motion estimation based on polynomial
  expansion", SCIA 2003 (``cv2.calcOpticalFlowFarneback``).

Conventions (anidress_core): flow (H, W, 2) in pixels, (dx, dy), forward from
frame t-1 to frame t, on frame t-1's pixel grid, the same as the synthetic ground
truth (:func:`anidress_core.synth.forward_flow`). Only the dilated bounding box of
the subject (union of both frames' masks) is processed, so the background costs
nothing; ``valid`` marks the processed pixels.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["FLOW_METHODS", "REFINE_METHODS", "Region", "FlowEstimate", "flow_region", "to_gray8", "estimate_flow",
           "make_estimator", "refine_lk", "mesh_flow", "extend_flow"]

FLOW_METHODS = ("dis_ultrafast", "dis_fast", "dis_medium", "deepflow", "tvl1", "farneback")
"""Names accepted by :func:`estimate_flow` (config ``cues/flows/method``)."""

REFINE_METHODS = ("none", "lk")
"""Names accepted by config ``cues/flows/refine`` (:func:`refine_lk`)."""

# cv2.DISOpticalFlow presets by name
_DIS_PRESETS = {"dis_ultrafast": "DISOPTICAL_FLOW_PRESET_ULTRAFAST", "dis_fast": "DISOPTICAL_FLOW_PRESET_FAST",
                "dis_medium": "DISOPTICAL_FLOW_PRESET_MEDIUM"}


class Region(NamedTuple):
    """Pixel box ``[y0, y1) x [x0, x1)`` of an (H, W) image."""

    y0: int
    y1: int
    x0: int
    x1: int


class FlowEstimate(NamedTuple):
    flow: np.ndarray  # (H, W, 2) float32 pixels (dx, dy), 0 outside the region
    valid: np.ndarray  # (H, W) bool, True inside the processed region
    region: Region | None  # None: nothing processed (no subject in either frame)
    compute_s: float  # wall time of the OpenCV call alone (seconds)


def flow_region(mask0: np.ndarray, mask1: np.ndarray, margin: int, min_size: int = 32) -> Region | None:
    """Dilated bounding box of the subject in either frame.

    mask0, mask1: (H, W) labels or booleans (subject where > 0). margin: pixels added
    on every side (the subject may move beyond its frame t-1 box by its motion).
    min_size: the box grows about its centre to at least this many pixels on each
    side (the estimators' pyramids need some support), clamped to the image.
    Returns None when neither frame has subject pixels.
    """
    if mask0.shape != mask1.shape or mask0.ndim != 2:
        raise ValueError(f"flow_region: masks must be two (H, W) arrays, got {mask0.shape} and {mask1.shape}")
    H, W = mask0.shape
    fg = (mask0 > 0) | (mask1 > 0)
    rows, cols = np.flatnonzero(fg.any(1)), np.flatnonzero(fg.any(0))
    if rows.size == 0:
        return None

    def span(lo: int, hi: int, n: int) -> tuple[int, int]:
        lo, hi = max(0, lo - margin), min(n, hi + margin)
        size = min(n, max(min_size, hi - lo))
        if hi - lo < size:  # grow about the centre, then shift back inside the image
            lo = min(max(0, (lo + hi - size) // 2), n - size)
            hi = lo + size
        return lo, hi

    y0, y1 = span(int(rows[0]), int(rows[-1]) + 1, H)
    x0, x1 = span(int(cols[0]), int(cols[-1]) + 1, W)
    return Region(y0, y1, x0, x1)


def to_gray8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB float in [0, 1] or uint8 -> (H, W) uint8 luma (what the estimators take)."""
    import cv2

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"to_gray8: expected an (H, W, 3) image, got {img.shape}")
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)


def make_estimator(method: str):
    """A fresh OpenCV estimator object for ``method`` (estimators are not thread-safe:
    one per call or per thread). Farnebäck is a plain function: returns None."""
    import cv2

    if method in _DIS_PRESETS:
        return cv2.DISOpticalFlow_create(getattr(cv2, _DIS_PRESETS[method]))
    if method == "deepflow":
        return cv2.optflow.createOptFlow_DeepFlow()
    if method == "tvl1":
        return cv2.optflow.DualTVL1OpticalFlow_create()
    if method == "farneback":
        return None
    raise ValueError(f"unknown flow method {method!r}; expected one of {FLOW_METHODS}")


def estimate_flow(img0: np.ndarray, img1: np.ndarray, method: str, region: Region | None = None,
                  estimator=None, init: np.ndarray | None = None) -> FlowEstimate:
    """Forward flow from ``img0`` (frame t-1) to ``img1`` (frame t) inside ``region``.

    img0, img1: (H, W, 3) RGB (float in [0, 1] or uint8) or (H, W) uint8 grey.
    region: the box to process (default: the whole image); flow is 0 and ``valid``
    False outside it. estimator: a reusable object from :func:`make_estimator`.
    init: optional (H, W, 2) initial flow (e.g. :func:`mesh_flow` of the posed body
    and skinned garment): ``img1`` is warped back by it, the method estimates the
    residual r between ``img0`` and the warped image, and the flow is the composition
    r(x) + init(x + r(x)). Large motions of a periodic texture (a twirling plaid
    dress) that the coarse-to-fine estimators alias are then only residuals.
    """
    import cv2

    if method not in FLOW_METHODS:
        raise ValueError(f"unknown flow method {method!r}; expected one of {FLOW_METHODS}")
    g0 = img0 if img0.ndim == 2 else to_gray8(img0)
    g1 = img1 if img1.ndim == 2 else to_gray8(img1)
    if g0.shape != g1.shape or g0.dtype != np.uint8 or g1.dtype != np.uint8:
        raise ValueError(f"estimate_flow: images must match and be uint8, got {g0.shape} {g0.dtype} "
                         f"and {g1.shape} {g1.dtype}")
    H, W = g0.shape
    if init is not None and init.shape != (H, W, 2):
        raise ValueError(f"estimate_flow: init must be ({H}, {W}, 2), got {init.shape}")
    flow = np.zeros((H, W, 2), np.float32)
    valid = np.zeros((H, W), bool)
    if region is None:
        region = Region(0, H, 0, W)
    y0, y1, x0, x1 = region
    if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
        raise ValueError(f"estimate_flow: region {tuple(region)} outside the {H}x{W} image")
    est = estimator if estimator is not None else make_estimator(method)
    t0 = time.perf_counter()
    if init is not None:
        # 1. warp frame t back by the initial flow: g1w(x) = g1(x + init(x))
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
        init = init.astype(np.float32)
        g1 = cv2.remap(g1, xs + init[..., 0], ys + init[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    a = np.ascontiguousarray(g0[y0:y1, x0:x1])
    b = np.ascontiguousarray(g1[y0:y1, x0:x1])
    # 2. the method on the box
    if method == "farneback":
        # OpenCV's documented example parameters (pyramid 0.5, 3 levels, window 15)
        f = cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 15, 3, 5, 1.2, 0)
    else:
        f = est.calc(a, b, None)
    if init is not None:
        # 3. compose: x -> x + r(x) in the warped frame is x + r(x) + init(x + r(x)) in frame t
        ib = np.ascontiguousarray(init[y0:y1, x0:x1])
        yy, xx = ys[y0:y1, x0:x1] - y0, xs[y0:y1, x0:x1] - x0
        f = f + cv2.remap(ib, xx + f[..., 0], yy + f[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    dt = time.perf_counter() - t0
    flow[y0:y1, x0:x1] = f
    valid[y0:y1, x0:x1] = True
    return FlowEstimate(flow, valid, region, dt)


def refine_lk(img0: np.ndarray, img1: np.ndarray, flow: np.ndarray, where: np.ndarray, window: int = 7,
              levels: int = 0, max_change: float = 2.0) -> tuple[np.ndarray, int]:
    """Re-estimate the flow at the pixels ``where`` by Lucas-Kanade, started from ``flow``.

    The dense estimators regularise: DIS averages overlapping patches and smooths them
    (variational refinement), TV-L1 / DeepFlow / Farneback smooth by construction. That
    shrinks the motion: at the fit's flow targets dis_medium (with the body prior)
    under-estimates it by 5 % on the skirt walk (8 % on the hem, which swings most) and
    by 26-31 % on the slow skirt dance and dress sway (0.4-0.5 px per frame), which the
    chained fit integrates into drift. Each pixel's own small window (Lucas & Kanade,
    IJCAI 1981; OpenCV's pyramidal implementation, Bouguet 2001:
    ``cv2.calcOpticalFlowPyrLK``), started at the dense flow, has no smoothness term:
    window 7 leaves 2 / 9 / 10 % at about the same mean end-point error; smaller windows
    less bias and more noise (studies/cues/flow_refine.md).

    img0, img1: (H, W) uint8 grey (or (H, W, 3) RGB, converted); flow: (H, W, 2) float
    pixels (dx, dy) from img0 to img1; where: (H, W) bool, the pixels to refine;
    window: odd window size (pixels); levels: pyramid levels above the image (0: the
    image alone -- the start is within a pixel or two of the answer); max_change: a
    refined vector further than this from the start is rejected (LK locked onto another
    period of a repeating texture, or lost the pixel), and the start kept.
    Returns (the refined flow (H, W, 2) float32, the number of pixels changed).
    """
    import cv2

    g0 = img0 if img0.ndim == 2 else to_gray8(img0)
    g1 = img1 if img1.ndim == 2 else to_gray8(img1)
    if g0.shape != g1.shape or g0.dtype != np.uint8 or g1.dtype != np.uint8:
        raise ValueError(f"refine_lk: images must match and be uint8, got {g0.shape} {g0.dtype} and {g1.shape} "
                         f"{g1.dtype}")
    if flow.shape != g0.shape + (2,) or where.shape != g0.shape:
        raise ValueError(f"refine_lk: flow must be {g0.shape + (2,)} and where {g0.shape}, got {flow.shape} and "
                         f"{where.shape}")
    if window < 3 or window % 2 == 0 or levels < 0 or not max_change > 0:
        raise ValueError(f"refine_lk: window must be odd and >= 3, levels >= 0, max_change > 0; got {window}, "
                         f"{levels}, {max_change}")
    out = np.array(flow, dtype=np.float32, copy=True)
    ys, xs = np.nonzero(where & np.isfinite(out).all(-1))
    if xs.size == 0:
        return out, 0
    p0 = np.stack([xs, ys], -1).astype(np.float32)
    start = p0 + out[ys, xs]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.003)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0.reshape(-1, 1, 2), start.reshape(-1, 1, 2).copy(),
                                             winSize=(window, window), maxLevel=levels, criteria=crit,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1 = p1.reshape(-1, 2)
    ok = (status.reshape(-1) == 1) & np.isfinite(p1).all(-1) & (np.abs(p1 - start).max(-1) <= max_change)
    out[ys[ok], xs[ok]] = p1[ok] - p0[ok]
    return out, int(ok.sum())


def mesh_flow(face_id: Tensor, bary: Tensor, verts_next: Tensor, faces: Tensor, K: Tensor,
              world_to_cam: Tensor) -> Tensor:
    """Flow (C, H, W, 2) of a moving mesh: each covered pixel of frame t-1 follows its surface point.

    face_id (C, H, W) and bary (C, H, W, 3): the rasterised mesh at frame t-1
    (:func:`anidress_core.raster.rasterize`); verts_next: (V, 3) world vertices at
    frame t; K (C, 3, 3), world_to_cam (C, 4, 4). X_t = sum_k b_k V_t[f_k] is projected
    into each camera; flow = pi(X_t) - pixel. 0 where the mesh does not cover the pixel
    (no visibility test: it is an initialisation, not ground truth).
    """
    C, H, W = face_id.shape
    hit = face_id >= 0
    tri = verts_next[faces[face_id.clamp_min(0)]]  # (C, H, W, 3 corners, 3)
    X = (bary[..., :, None].to(tri.dtype) * tri).sum(-2)  # (C, H, W, 3)
    w2c = world_to_cam.to(X.dtype)
    # Xc[c, h, w, i] = sum_j R[c, i, j] X[c, h, w, j] + t[c, i]
    Xc = torch.einsum("cij,chwj->chwi", w2c[:, :3, :3], X) + w2c[:, None, None, :3, 3]
    z = Xc[..., 2].clamp_min(1e-6)
    Kd = K.to(X.dtype)
    u = Kd[:, 0, 0, None, None] * Xc[..., 0] / z + Kd[:, 0, 2, None, None]
    v = Kd[:, 1, 1, None, None] * Xc[..., 1] / z + Kd[:, 1, 2, None, None]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=X.dtype), torch.arange(W, dtype=X.dtype), indexing="ij")
    flow = torch.stack([u - xs, v - ys], -1)
    return torch.where(hit[..., None], flow, torch.zeros_like(flow))


def extend_flow(flow: np.ndarray, covered: np.ndarray, sigma_px: float = 8.0) -> np.ndarray:
    """Fill an (H, W, 2) flow outside ``covered`` (H, W) by normalised Gaussian averaging of the
    covered values (sigma ``sigma_px``), so a subject reaching beyond the mesh prior still gets
    a smooth initialisation; 0 where no covered pixel is near."""
    import cv2

    m = covered.astype(np.float32)
    if not m.any():
        return np.zeros_like(flow)
    num = cv2.GaussianBlur(flow * m[..., None], (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)
    den = cv2.GaussianBlur(m, (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)
    fill = np.where(den[..., None] > 1e-3, num / np.maximum(den, 1e-3)[..., None], 0.0)
    return np.where(covered[..., None], flow, fill).astype(np.float32)
