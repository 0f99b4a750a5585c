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

__all__ = ["FLOW_METHODS", "Region", "FlowEstimate", "flow_region", "to_gray8", "estimate_flow",
           "make_estimator"]

FLOW_METHODS = ("dis_ultrafast", "dis_fast", "dis_medium", "deepflow", "tvl1", "farneback")
"""Names accepted by :func:`estimate_flow` (config ``cues/flows/method``)."""

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
                  estimator=None) -> FlowEstimate:
    """Forward flow from ``img0`` (frame t-1) to ``img1`` (frame t) inside ``region``.

    img0, img1: (H, W, 3) RGB (float in [0, 1] or uint8) or (H, W) uint8 grey.
    region: the box to process (default: the whole image); flow is 0 and ``valid``
    False outside it. estimator: a reusable object from :func:`make_estimator`.
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
    flow = np.zeros((H, W, 2), np.float32)
    valid = np.zeros((H, W), bool)
    if region is None:
        region = Region(0, H, 0, W)
    y0, y1, x0, x1 = region
    if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
        raise ValueError(f"estimate_flow: region {tuple(region)} outside the {H}x{W} image")
    a = np.ascontiguousarray(g0[y0:y1, x0:x1])
    b = np.ascontiguousarray(g1[y0:y1, x0:x1])
    est = estimator if estimator is not None else make_estimator(method)
    t0 = time.perf_counter()
    if method == "farneback":
        # OpenCV's documented example parameters (pyramid 0.5, 3 levels, window 15)
        f = cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 15, 3, 5, 1.2, 0)
    else:
        f = est.calc(a, b, None)
    dt = time.perf_counter() - t0
    flow[y0:y1, x0:x1] = f
    valid[y0:y1, x0:x1] = True
    return FlowEstimate(flow, valid, region, dt)
