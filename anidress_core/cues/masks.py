"""Body + garment masks from images: background subtraction, then garment vs body.

The paper (AniDress §3.2) takes its garment masks from SCHP (Li et al., "Self-
Correction for Human Parsing", TPAMI 2020); its weights cannot be downloaded here,
so the masks are estimated with classical tools and measured against ground truth
(benchmarks/cues.md):

1. foreground: per-pixel colour distance to the camera's background plate (what a
   capture records before the performer walks in), hysteresis thresholding (weak
   pixels are kept where they connect to sure ones), morphological opening/closing,
   small specks dropped and small enclosed holes filled;
2. a shape prior: the body mesh posed by the sequence's SMPL parameters and the
   garment template skinned with the body (linear blend skinning, its body weights),
   rasterised into every camera: labels 1 body / 2 garment (:func:`render_prior`);
3. garment vs body inside the foreground, one of
   * ``prior`` (default): the label of the nearest prior pixel of either class;
   * ``colour``: a per-camera colour histogram Bayes classifier (garment vs body),
     learned on the pixels where the prior is confident, plus a spatial log-odds
     term from the distances to the prior's garment and body pixels, smoothed and
     thresholded (a cheap stand-in for a graph cut); better than ``prior`` when the
     garment's colours differ from the body's, wrong where body clothing is of the
     garment's fabric (benchmarks/cues.md);
   * ``grabcut``: OpenCV GrabCut (Rother, Kolmogorov, Blake, "GrabCut", SIGGRAPH
     2004) initialised with the prior as probable garment / probable body inside the
     foreground and sure background outside it;
4. clean-up: tiny islands of either label take the label around them.

Everything here is pure: arrays in, arrays out (the stage runner reads and writes).
Images are (N, H, W, 3) float in [0, 1] (or uint8), labels (N, H, W) uint8.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .. import raster

__all__ = [
    "MASK_METHODS",
    "MaskParams",
    "colour_distance",
    "foreground",
    "refine_boundary",
    "subject_masks",
    "render_prior",
    "prior_distances",
    "fit_colour_model",
    "colour_log_ratio",
    "label_prior",
    "label_colour",
    "label_grabcut",
    "clean_labels",
    "estimate_masks",
    "temporal_median_plate",
]

MASK_METHODS = ("prior", "colour", "grabcut")
BACKGROUND, BODY, GARMENT = 0, 1, 2


@dataclass(frozen=True)
class MaskParams:
    """Settings of mask estimation (config section ``cues/masks``)."""

    method: str = "prior"
    """Garment vs body: ``prior`` | ``colour`` | ``grabcut`` (module docstring). ``prior`` is the
    default: colour models cannot tell a garment from body clothing of the same fabric (the
    dress scene's plaid dress over a plaid shirt), see benchmarks/cues.md."""
    fg_threshold: float = 0.08
    """Colour distance to the plate (RGB in [0, 1], Euclidean) above which a pixel is surely subject."""
    fg_threshold_low: float = 0.03
    """Hysteresis: pixels above this distance are subject where they connect to sure ones."""
    blur_px: float = 0.5
    """Gaussian sigma (pixels) applied to image and plate before differencing (sensor noise)."""
    open_px: int = 1
    """Radius of the morphological opening (removes specks and thin noise)."""
    close_px: int = 0
    """Radius of the morphological closing (closes hairline gaps; 0: off, as it also closes
    real gaps such as armpits)."""
    min_component_frac: float = 0.02
    """Foreground components smaller than this fraction of the largest are dropped."""
    hole_area_px: int = 0
    """Enclosed background holes smaller than this (pixels) are filled (0: off)."""
    refine_px: int = 1
    """Silhouette pixels within this distance are re-decided by their coverage (0: off;
    :func:`refine_boundary`)."""
    hist_bins: int = 32
    """Colour histogram bins per RGB channel (``colour`` method)."""
    hist_pseudo_count: float = 1.0
    """Count added to every histogram bin (unseen colours: log-ratio 0, the prior decides)."""
    colour_max: float = 5.0
    """Bound of the colour log-likelihood ratio."""
    prior_scale_px: float = 6.0
    """Spatial log-odds = (distance to prior body - distance to prior garment) / this."""
    prior_max: float = 3.0
    """Bound of the spatial log-odds (so colour can overrule a misplaced prior)."""
    confident_px: int = 3
    """Colour model training pixels lie this far inside a prior region (and in the foreground)."""
    smooth_px: float = 0.5
    """Gaussian sigma (pixels) of the smoothing of the garment log-odds (``colour``)."""
    island_px: int = 12
    """Connected islands of one label smaller than this take the surrounding label."""
    grabcut_iters: int = 3
    """GrabCut iterations (``grabcut``)."""

    def __post_init__(self):
        if self.method not in MASK_METHODS:
            raise ValueError(f"MaskParams: method must be one of {MASK_METHODS}, got {self.method!r}")
        if not 0 < self.fg_threshold_low <= self.fg_threshold:
            raise ValueError("MaskParams: need 0 < fg_threshold_low <= fg_threshold, got "
                             f"{self.fg_threshold_low} and {self.fg_threshold}")
        if not 2 <= self.hist_bins <= 64:
            raise ValueError(f"MaskParams: hist_bins must lie in [2, 64], got {self.hist_bins}")


# --------------------------------------------------------------------------- helpers


def _as_float_images(images) -> Tensor:
    t = torch.as_tensor(np.asarray(images))
    if t.dtype == torch.uint8:
        return t.float() / 255.0
    return t.float()


def _gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of (N, Ch, H, W) float32 with replicated borders (OpenCV, image by image:
    its separable SIMD filter is far faster on a CPU than a grouped torch convolution)."""
    import cv2

    if sigma <= 0:
        return x
    a = x.detach().cpu().float().numpy()
    out = np.empty_like(a)
    for i in range(a.shape[0]):
        for c in range(a.shape[1]):
            out[i, c] = cv2.GaussianBlur(a[i, c], (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out)


def _disk(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _uint8_images(images) -> np.ndarray:
    a = np.asarray(images)
    if a.dtype == np.uint8:
        return a
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# --------------------------------------------------------------------------- 1. foreground


def temporal_median_plate(images) -> np.ndarray:
    """Background plate of one camera as the per-pixel median over frames.

    images: (T, H, W, 3). For captures without a recorded plate; it works when every
    background pixel is unoccluded in more than half of the frames.
    """
    a = np.asarray(images)
    if a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"temporal_median_plate: expected (T, H, W, 3), got {a.shape}")
    return np.median(a, axis=0).astype(a.dtype)


def colour_distance(images, plates, blur_px: float = 0.7) -> Tensor:
    """Euclidean RGB distance (N, H, W) between images and plates, both (N, H, W, 3),
    after a Gaussian blur of sigma ``blur_px`` (the sensor noise is averaged out)."""
    im, pl = _as_float_images(images), _as_float_images(plates)
    if im.shape != pl.shape or im.ndim != 4 or im.shape[-1] != 3:
        raise ValueError(f"colour_distance: images {tuple(im.shape)} and plates {tuple(pl.shape)} "
                         "must both be (N, H, W, 3)")
    d = _gaussian_blur((im - pl).permute(0, 3, 1, 2), blur_px)
    return d.norm(dim=1)


def _fill_small_holes(fg: np.ndarray, max_area: int) -> np.ndarray:
    import cv2

    if max_area <= 0:
        return fg
    n, lab, stats, _ = cv2.connectedComponentsWithStats((~fg).astype(np.uint8), connectivity=4)
    H, W = fg.shape
    x, y, w, h, area = (stats[:, i] for i in range(5))
    touches = (x == 0) | (y == 0) | (x + w == W) | (y + h == H)
    fill = (~touches) & (area < max_area)
    fill[0] = False  # label 0: the zero pixels of the input, i.e. the foreground itself
    return fg | fill[lab]


def foreground(distance, params: MaskParams) -> np.ndarray:
    """Subject masks (N, H, W) bool from colour distances (N, H, W) (step 1).

    Hysteresis: strong = distance > fg_threshold, weak = distance > fg_threshold_low;
    weak components touching a strong pixel are kept. Then opening/closing, removal
    of components below ``min_component_frac`` of the largest, filling of enclosed
    holes below ``hole_area_px``.
    """
    import cv2

    d = np.asarray(distance.numpy() if isinstance(distance, Tensor) else distance, np.float32)
    if d.ndim != 3:
        raise ValueError(f"foreground: distances must be (N, H, W), got {d.shape}")
    out = np.zeros(d.shape, bool)
    k_open = _disk(params.open_px) if params.open_px > 0 else None
    k_close = _disk(params.close_px) if params.close_px > 0 else None
    for i in range(d.shape[0]):  # per image: OpenCV's component labelling and morphology
        strong = d[i] > params.fg_threshold
        weak = (d[i] > params.fg_threshold_low).astype(np.uint8)
        n, lab = cv2.connectedComponents(weak, connectivity=8)
        keep = np.zeros(n, bool)
        keep[np.unique(lab[strong])] = True
        keep[0] = False
        m = keep[lab].astype(np.uint8)
        if k_open is not None:
            m = cv2.morphologyEx(m, cv2.MORPH_OPEN, k_open)
        if k_close is not None:
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k_close)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        if n > 1:
            area = stats[1:, cv2.CC_STAT_AREA]
            keep = np.concatenate([[False], area >= params.min_component_frac * area.max()])
            m = keep[lab]
        else:
            m = m.astype(bool)
        out[i] = _fill_small_holes(m, params.hole_area_px)
    return out


def refine_boundary(images, plates, fg, band_px: int = 2, sigma_px: float = 2.0) -> np.ndarray:
    """Put the silhouette where the pixel is half covered (step 1, last part).

    A camera integrates light over a pixel, so a silhouette pixel mixes subject and
    background: I = a F + (1 - a) B. With the plate B known and the subject colour F
    estimated from nearby interior pixels (Gaussian-weighted mean over the foreground
    eroded by ``band_px``), the coverage is a = <I - B, F - B> / |F - B|^2 (the
    projection, as in Porter-Duff matting with a known background). Pixels within
    ``band_px`` of the silhouette are subject where a > 0.5; the interior is kept.
    images, plates: (N, H, W, 3); fg: (N, H, W) bool. Returns (N, H, W) bool.
    """
    import cv2

    fg = np.asarray(fg, bool)
    k = _disk(band_px)
    core = np.stack([cv2.erode(m.astype(np.uint8), k) for m in fg]) > 0
    band = (np.stack([cv2.dilate(m.astype(np.uint8), k) for m in fg]) > 0) & ~core
    im, pl = _as_float_images(images), _as_float_images(plates)
    c = torch.from_numpy(core)[:, None].float()
    # F = sum_q g(p - q) core(q) I(q) / sum_q g(p - q) core(q)  (normalised convolution)
    Fc = _gaussian_blur(im.permute(0, 3, 1, 2) * c, sigma_px) / _gaussian_blur(c, sigma_px).clamp_min(1e-6)
    Fc = Fc.permute(0, 2, 3, 1)
    fb = Fc - pl
    alpha = ((im - pl) * fb).sum(-1) / (fb * fb).sum(-1).clamp_min(1e-6)
    # without interior nearby (thin parts) keep the thresholded decision
    has_core = _gaussian_blur(c, sigma_px)[:, 0].numpy() > 1e-3
    decided = np.where(has_core, alpha.numpy() > 0.5, fg)
    return np.where(band, decided, core)


# --------------------------------------------------------------------------- 2. prior


def render_prior(body_verts: Tensor, body_faces: Tensor, garment_verts: Tensor | None, garment_faces: Tensor | None,
                 K: Tensor, world_to_cam: Tensor, height: int, width: int) -> Tensor:
    """Labels (C, H, W) uint8 of the posed body (1) and skinned garment (2), z-buffered.

    body_verts: (V, 3) world; body_faces: (F, 3); garment_verts: (Vg, 3) or None;
    K: (C, 3, 3); world_to_cam: (C, 4, 4). Pinhole projection (lens distortion is
    ignored: the prior is only a guide).
    """
    verts, faces, label = [body_verts.float()], [body_faces.long()], [torch.full((body_faces.shape[0],), BODY)]
    if garment_verts is not None:
        verts.append(garment_verts.float())
        faces.append(garment_faces.long() + body_verts.shape[0])
        label.append(torch.full((garment_faces.shape[0],), GARMENT))
    v, f, lab = torch.cat(verts), torch.cat(faces), torch.cat(label)
    frags = raster.rasterize(v, f, K.float(), world_to_cam.float(), height, width)
    hit = frags.face_id >= 0
    return torch.where(hit, lab[frags.face_id.clamp_min(0)], torch.zeros_like(frags.face_id)).to(torch.uint8)


def prior_distances(prior) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N, H, W) in pixels to the nearest prior garment and body pixel.

    A view without any pixel of a class gets distance H + W for that class.
    """
    import cv2

    p = np.asarray(prior.numpy() if isinstance(prior, Tensor) else prior)
    N, H, W = p.shape
    dg = np.full(p.shape, float(H + W), np.float32)
    db = np.full(p.shape, float(H + W), np.float32)
    for i in range(N):
        for lab, out in ((GARMENT, dg), (BODY, db)):
            m = p[i] == lab
            if m.any():
                out[i] = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 3)
    return dg, db


# --------------------------------------------------------------------------- 3. garment vs body


def label_prior(fg, prior) -> np.ndarray:
    """Each foreground pixel takes the label of the nearest prior pixel (ties: body)."""
    fg = np.asarray(fg, bool)
    dg, db = prior_distances(prior)
    return np.where(fg, np.where(dg < db, GARMENT, BODY), BACKGROUND).astype(np.uint8)


def _bin_index(images: Tensor, bins: int) -> Tensor:
    q = (images.clamp(0, 1) * bins).long().clamp_max(bins - 1)  # (N, H, W, 3)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]  # (N, H, W)


def fit_colour_model(images, camera: np.ndarray, fg, prior, num_cameras: int, params: MaskParams) -> Tensor:
    """Per-camera colour log-likelihood ratio log p(c | garment) - log p(c | body).

    images: (N, H, W, 3); camera: (N,) camera index of each image; fg, prior: (N, H, W).
    Training pixels: foreground pixels at least ``confident_px`` inside a prior region
    of one class. Histograms of ``hist_bins``^3 RGB bins, smoothed by a [1, 2, 1]
    kernel along each axis, plus ``hist_pseudo_count`` per bin; the ratio is bounded
    by ``colour_max``.
    Returns (num_cameras, bins^3) float32.
    """
    import cv2

    im = _as_float_images(images)
    fg = np.asarray(fg, bool)
    p = np.asarray(prior.numpy() if isinstance(prior, Tensor) else prior)
    cam = torch.as_tensor(np.asarray(camera), dtype=torch.long)
    b = params.hist_bins
    idx = _bin_index(im, b)  # (N, H, W)
    # 1. confident pixels: eroded prior regions, inside the foreground
    conf = np.zeros((2,) + p.shape, bool)
    k = _disk(params.confident_px) if params.confident_px > 0 else None
    for i in range(p.shape[0]):
        for j, lab in enumerate((BODY, GARMENT)):
            m = (p[i] == lab).astype(np.uint8)
            conf[j, i] = (cv2.erode(m, k) > 0 if k is not None else m > 0) & fg[i]
    # 2. counts[c, class, bin] via one bincount
    conf_t = torch.from_numpy(conf)
    cls = torch.arange(2)[:, None, None, None].expand_as(conf_t)
    key = (cam[None, :, None, None].expand_as(conf_t) * 2 + cls) * b ** 3 + idx[None].expand_as(conf_t)
    counts = torch.bincount(key[conf_t], minlength=num_cameras * 2 * b ** 3).float().reshape(num_cameras * 2, 1, b, b, b)
    # 3. smooth: separable [1, 2, 1] / 4 along the three colour axes
    k1 = torch.tensor([0.25, 0.5, 0.25])
    for dim in range(3):
        shape = [1, 1, 1, 1, 1]
        shape[2 + dim] = 3
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - dim)] = pad[2 * (2 - dim) + 1] = 1
        counts = F.conv3d(F.pad(counts, pad, mode="replicate"), k1.view(shape))
    counts = counts.reshape(num_cameras, 2, b ** 3) + params.hist_pseudo_count
    logp = counts.log() - counts.sum(-1, keepdim=True).log()
    return (logp[:, 1] - logp[:, 0]).clamp(-params.colour_max, params.colour_max).float()


def colour_log_ratio(images, camera: np.ndarray, model: Tensor, bins: int) -> Tensor:
    """Garment-vs-body colour log-likelihood ratio (N, H, W) of every pixel."""
    idx = _bin_index(_as_float_images(images), bins)
    cam = torch.as_tensor(np.asarray(camera), dtype=torch.long)
    return model[cam[:, None, None], idx]


def label_colour(images, camera: np.ndarray, fg, prior, model: Tensor, params: MaskParams) -> np.ndarray:
    """Colour + spatial-prior classification of the foreground (method ``colour``).

    log-odds(garment) = colour log-ratio + clamp((d_body - d_garment) / prior_scale_px,
    +-prior_max), averaged over the foreground with a Gaussian of ``smooth_px``
    (normalised convolution), garment where positive.
    """
    fg = np.asarray(fg, bool)
    lr = colour_log_ratio(images, camera, model, params.hist_bins)
    dg, db = prior_distances(prior)
    spatial = torch.from_numpy((db - dg) / params.prior_scale_px).clamp(-params.prior_max, params.prior_max)
    logit = lr + spatial
    m = torch.from_numpy(fg)[:, None].float()
    if params.smooth_px > 0:
        logit = (_gaussian_blur(logit[:, None] * m, params.smooth_px)
                 / _gaussian_blur(m, params.smooth_px).clamp_min(1e-6))[:, 0]
    lab = np.where(fg, np.where(logit.numpy() > 0, GARMENT, BODY), BACKGROUND).astype(np.uint8)
    return lab


def label_grabcut(images, fg, prior, params: MaskParams) -> np.ndarray:
    """GrabCut (OpenCV) per image, seeded by the prior inside the foreground (method ``grabcut``).

    Inside the foreground's bounding box (plus 4 px): nearest-prior garment pixels are
    probable foreground, the rest of the subject probable background, non-subject
    pixels sure background.
    """
    import cv2

    fg = np.asarray(fg, bool)
    im8 = _uint8_images(images)
    init = label_prior(fg, prior)
    out = np.zeros(fg.shape, np.uint8)
    for i in range(fg.shape[0]):  # per image: GrabCut has no batched form
        rows, cols = np.flatnonzero(fg[i].any(1)), np.flatnonzero(fg[i].any(0))
        if rows.size == 0:
            continue
        H, W = fg[i].shape
        y0, y1 = max(0, rows[0] - 4), min(H, rows[-1] + 5)
        x0, x1 = max(0, cols[0] - 4), min(W, cols[-1] + 5)
        lab = init[i, y0:y1, x0:x1]
        mask = np.full(lab.shape, cv2.GC_BGD, np.uint8)
        mask[lab == GARMENT] = cv2.GC_PR_FGD
        mask[lab == BODY] = cv2.GC_PR_BGD
        if not (lab == GARMENT).any() or not (lab != GARMENT).any():
            out[i, y0:y1, x0:x1] = lab
            continue
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        img = np.ascontiguousarray(im8[i, y0:y1, x0:x1, ::-1])  # BGR, as OpenCV expects
        cv2.grabCut(img, mask, None, bgd, fgd, params.grabcut_iters, cv2.GC_INIT_WITH_MASK)
        is_g = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
        out[i, y0:y1, x0:x1] = np.where(lab > 0, np.where(is_g, GARMENT, BODY), BACKGROUND)
    return out


def clean_labels(labels, min_area: int) -> np.ndarray:
    """Body/garment islands smaller than ``min_area`` pixels take the other subject label."""
    import cv2

    lab = np.array(labels, np.uint8, copy=True)
    if min_area <= 0:
        return lab
    for i in range(lab.shape[0]):
        for cls, other in ((GARMENT, BODY), (BODY, GARMENT)):
            m = (lab[i] == cls).astype(np.uint8)
            n, comp, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
            if n <= 1:
                continue
            small = np.concatenate([[False], stats[1:, cv2.CC_STAT_AREA] < min_area])
            # only islands surrounded by the other subject label flip (not ones at the silhouette)
            island = np.where(small[comp], comp, 0).astype(np.float32)
            if island.any():
                # each pixel just outside a small island gets that island's id (grey dilation)
                near = cv2.dilate(island, np.ones((3, 3), np.uint8)).astype(np.int64)
                border = (near > 0) & (island == 0)
                # per island: flip when more of its border is the other label than background
                other_n = np.bincount(near[border & (lab[i] == other)], minlength=n)
                bg_n = np.bincount(near[border & (lab[i] == BACKGROUND)], minlength=n)
                ok = small & (other_n > bg_n)
                lab[i][ok[comp]] = other
    return lab


def subject_masks(images, plates, params: MaskParams) -> np.ndarray:
    """Step 1 complete: foreground (N, H, W) bool with the refined silhouette."""
    fg = foreground(colour_distance(images, plates, params.blur_px), params)
    if params.refine_px > 0:
        fg = refine_boundary(images, plates, fg, params.refine_px)
    return fg


def estimate_masks(images, plates, prior, params: MaskParams, camera: np.ndarray | None = None,
                   model: Tensor | None = None, has_garment: bool = True, fg: np.ndarray | None = None) -> np.ndarray:
    """Labels (N, H, W) uint8 (0 background, 1 body, 2 garment) of N images.

    images, plates: (N, H, W, 3); prior: (N, H, W) labels from :func:`render_prior`
    (may be None when ``has_garment`` is False or the method needs none); camera
    (N,) and model (from :func:`fit_colour_model`) for the ``colour`` method;
    fg: the :func:`subject_masks` of the images if already computed.
    """
    if fg is None:
        fg = subject_masks(images, plates, params)
    if not has_garment:
        return fg.astype(np.uint8) * BODY
    if prior is None:
        raise ValueError("estimate_masks: garment vs body needs the rendered prior")
    if params.method == "prior":
        lab = label_prior(fg, prior)
    elif params.method == "colour":
        if model is None or camera is None:
            raise ValueError("estimate_masks: method 'colour' needs a colour model and camera indices")
        lab = label_colour(images, camera, fg, prior, model, params)
    else:
        lab = label_grabcut(images, fg, prior, params)
    return clean_labels(lab, params.island_px)
