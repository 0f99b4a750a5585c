"""Per-frame refinement of the body pose (Rh, Th, joint rotations) against the subject masks.

Captured body poses come from a markerless fit (EasyMocap) with centimetre errors and
frame-to-frame jitter; the paper's setup refines them against the masks before the
garment fit. :func:`refine_body_poses` does this for a sequence, all frames at once:

* L_inside: every body vertex projects inside the SUBJECT silhouette (body or garment
  label): the squared distance (pixels) of the projection outside the subject's outline,
  bilinearly sampled from a signed distance transform of the mask (zero inside). The garment
  covers the hips and legs, so a body vertex under the skirt is inside too.
* L_cover: every BODY-labelled pixel on the outline of the subject (a body pixel next
  to background, not next to garment: the garment/body border is no body outline) lies
  on the posed body: the squared distance to the nearest projected body vertex (a
  one-sided chamfer; the nearest vertex is found without gradients and reassigned every
  ``reassign_every`` steps, ICP-style).
  Both silhouette terms use the robust pseudo-Huber penalty of scale ``robust_px`` (parser
  masks have ragged edges) and are averaged over their residuals. They are chamfer
  (distance-transform) terms rather than the antialiased edge coverage of
  :mod:`anidress_core.fit.terms.silhouette`, because that one's gradient reaches one pixel
  from an edge and 2 cm of pose error is 2-5 pixels on the demo cameras.
* L_prior: the change from the input pose, per component in units of the typical error
  of the input (``sigma_rot`` for Rh and each joint rotation, ``sigma_trans`` for Th).
* L_smooth: the squared second difference (acceleration) of the joint positions across
  frames, in units of ``sigma_accel`` (the input's jitter is white noise of a few mm).

The unknowns are additive increments of the axis-angle vectors (small next to pi) and of
Th; they are optimised with Adam (autograd through :meth:`BodyModel.pose`). Views whose
mask holds no subject pixel (the subject is not seen or the mask is missing) give no
residual. Cameras are pinholes without distortion (undistort the masks first, like the
garment fit).

Dimension letters: T frames, C cameras, H, W image size, V body vertices.
Mask labels (the cue stage's): 0 background, 1 body, 2 garment.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .model import BodyModel

__all__ = ["RefineConfig", "RefineResult", "MaskTargets", "mask_targets", "refine_body_poses",
           "silhouette_iou", "project_points"]

BODY, GARMENT = 1, 2


@dataclass(frozen=True)
class RefineConfig:
    """Settings of :func:`refine_body_poses` (weights are relative to L_inside's)."""

    iters: int = 50
    """Adam steps."""
    lr_rot: float = 0.01
    """Adam step size of Rh and the joint rotations (rad); decays to ``lr_end`` of it (cosine)."""
    lr_trans: float = 0.004
    """Adam step size of Th (m)."""
    lr_end: float = 0.1
    """Final step size relative to the first (Adam keeps moving in flat directions: small steps at the end)."""
    w_inside: float = 1.0
    """Weight of L_inside."""
    w_cover: float = 1.0
    """Weight of L_cover."""
    robust_px: float = 3.0
    """Scale of the pseudo-Huber penalty of the silhouette residuals (pixels)."""
    w_prior: float = 0.05
    """Weight of L_prior (mean over components of (change / sigma)^2 per frame)."""
    sigma_rot: float = 0.05
    """Typical error of the input rotations (rad)."""
    sigma_trans: float = 0.02
    """Typical error of the input Th (m)."""
    w_smooth: float = 0.01
    """Weight of L_smooth (mean over frames and joints of (acceleration / sigma_accel)^2)."""
    sigma_accel: float = 0.01
    """Acceptable frame-to-frame second difference of a joint position (m)."""
    reassign_every: int = 10
    """Steps between nearest-vertex assignments of L_cover."""
    max_outline_px: int = 300
    """At most this many outline pixels per view (evenly subsampled) in L_cover."""


class MaskTargets(NamedTuple):
    """What the silhouette terms compare against (see :func:`mask_targets`).

    sdf: (T, C, H, W) signed distance (pixels) to the subject's outline: > 0 outside, < 0 inside
        (clamped at -3.5), 0 in views without a subject pixel.
    view_ok: (T, C) bool, the view's mask holds a subject pixel.
    outline_xy: (N, 2) float (u = column, v = row) of the body outline: the centres of body pixels
        next to background, moved half a pixel towards it.
    outline_normal: (N, 2) unit outward normal of the outline there (from the background
        4-neighbours: axis-aligned or diagonal).
    outline_tc: (N, 2) int64 (frame, camera) of each outline pixel.
    """

    sdf: Tensor
    view_ok: Tensor
    outline_xy: Tensor
    outline_normal: Tensor
    outline_tc: Tensor


class RefineResult(NamedTuple):
    """Output of :func:`refine_body_poses`.

    poses: (T, 72) refined axis-angle joint rotations (the root's, ``poses[:, :3]``, as given).
    Rh, Th: (T, 3) refined global rotation and translation.
    loss_curve: total loss before each Adam step and at the end (iters + 1 floats).
    terms_before, terms_after: the loss terms (dict name -> float) at the input and the result.
    seconds: wall time of the optimisation.
    """

    poses: Tensor
    Rh: Tensor
    Th: Tensor
    loss_curve: list
    terms_before: dict
    terms_after: dict
    seconds: float


def mask_targets(labels: Tensor, max_outline_px: int = 300) -> MaskTargets:
    """Distance fields and body outline pixels of label masks.

    labels: (T, C, H, W) integer 0 background / 1 body / 2 garment (other values: background).
    max_outline_px: per view, at most this many outline pixels (evenly subsampled).
    """
    if labels.ndim != 4:
        raise ValueError(f"mask_targets: labels must be (T, C, H, W), got {tuple(labels.shape)}")
    T, C, H, W = labels.shape
    lab = labels.to(torch.int64)
    subject = (lab == BODY) | (lab == GARMENT)
    view_ok = subject.flatten(2).any(-1)
    # 1. signed distance to the subject's outline (OpenCV's exact L2 transforms, per image): positive
    #    outside, negative inside, zero half way between a subject pixel's centre and its neighbour's
    def edt(inside: Tensor) -> Tensor:
        src = inside.to(torch.uint8).reshape(T * C, H, W).numpy()
        d = [cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for m in src]
        return torch.from_numpy(np.stack(d) if d else np.zeros((0, H, W), np.float32)).reshape(T, C, H, W).float()

    sdf = (edt(~subject) - edt(subject)).clamp(-4.0, None)
    sdf = torch.where(subject, sdf + 0.5, sdf - 0.5)
    sdf = torch.where(view_ok[..., None, None], sdf, torch.zeros_like(sdf))
    # 2. body outline: a body pixel with a background 4-neighbour (image borders do not count), moved half
    #    a pixel towards its background neighbours (the outline lies between the two pixel centres)
    bg = F.pad((~subject).float().reshape(T * C, 1, H, W), (1, 1, 1, 1), value=0.0)
    up, down = bg[..., :-2, 1:-1].reshape(T, C, H, W), bg[..., 2:, 1:-1].reshape(T, C, H, W)
    left, right = bg[..., 1:-1, :-2].reshape(T, C, H, W), bg[..., 1:-1, 2:].reshape(T, C, H, W)
    outline = (lab == BODY) & ((up + down + left + right) > 0)
    t, c, i, j = outline.nonzero(as_tuple=True)
    dxy = torch.stack([right[t, c, i, j] - left[t, c, i, j], down[t, c, i, j] - up[t, c, i, j]], -1)
    dxy = dxy / dxy.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # outward normal (corners: diagonal)
    # 3. even subsampling per view: keep the k-th pixel of a view when k * stride hits an integer
    if t.numel():
        view = t * C + c
        counts = torch.bincount(view, minlength=T * C)
        start = torch.cumsum(counts, 0) - counts
        k = torch.arange(view.numel()) - start[view]
        stride = (counts.float() / max_outline_px).clamp_min(1.0)[view]
        keep = torch.floor(k.float() / stride) != torch.floor((k.float() - 1) / stride)
        t, c, i, j, dxy = t[keep], c[keep], i[keep], j[keep], dxy[keep]
    xy = torch.stack([j, i], -1).float() + 0.5 * dxy
    return MaskTargets(sdf, view_ok, xy, dxy, torch.stack([t, c], -1))


def project_points(x: Tensor, K: Tensor, world_to_cam: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole projection of per-frame points into every camera.

    x: (T, V, 3) world; K: (C, 3, 3); world_to_cam: (C, 4, 4).
    Returns uv (T, C, V, 2) pixels and z (T, C, V) camera depth.
    """
    # X[t, c, v, i] = sum_j R[c, i, j] x[t, v, j] + t[c, i]
    E = world_to_cam.to(x.dtype)
    Xc = torch.einsum("cij,tvj->tcvi", E[:, :3, :3], x) + E[None, :, None, :3, 3]
    z = Xc[..., 2]
    zs = torch.where(z.abs() > 1e-6, z, torch.full_like(z, 1e-6))
    # p[t, c, v, i] = sum_j K[c, i, j] X[t, c, v, j] / z
    p = torch.einsum("cij,tcvj->tcvi", K.to(x.dtype), Xc / zs[..., None])
    return p[..., :2], z


def _pseudo_huber(d2: Tensor, s: float) -> Tensor:
    """s^2 (sqrt(1 + d^2 / s^2) - 1): d^2 / 2 near zero, s |d| far away."""
    return s * s * (torch.sqrt(1.0 + d2 / (s * s)) - 1.0)


def _sample(field: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of field (T, C, H, W) at uv (T, C, V, 2) pixels -> (T, C, V), inside-image mask."""
    T, C, H, W = field.shape
    gx = (uv[..., 0] + 0.5) / W * 2 - 1  # align_corners=False: pixel j's centre at (j + 0.5) / W
    gy = (uv[..., 1] + 0.5) / H * 2 - 1
    grid = torch.stack([gx, gy], -1).reshape(T * C, 1, -1, 2).to(field.dtype)
    s = F.grid_sample(field.reshape(T * C, 1, H, W), grid, mode="bilinear", padding_mode="border", align_corners=False)
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= W - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= H - 0.5)
    return s.reshape(T, C, -1), inside


@torch.no_grad()
def _nearest_vertex(uv: Tensor, z: Tensor, tgt: MaskTargets, chunk: int = 1 << 24) -> Tensor:
    """(N,) index of the projected vertex (in front of the camera) nearest to each outline pixel.

    The outline pixels are padded to (T C, N_max, 2) per view and compared with that view's
    projected vertices by ``torch.cdist`` (a matrix product), a chunk of views at a time (memory).
    """
    T, C, V, _ = uv.shape
    tc = tgt.outline_tc
    N = tc.shape[0]
    view = tc[:, 0] * C + tc[:, 1]
    counts = torch.bincount(view, minlength=T * C)
    k = torch.arange(N) - (torch.cumsum(counts, 0) - counts)[view]
    n_max = int(counts.max()) if N else 0
    pts = torch.zeros(T * C, n_max, 2, dtype=uv.dtype)
    pts[view, k] = tgt.outline_xy.to(uv.dtype)
    uvv, behind = uv.reshape(T * C, V, 2), (z <= 1e-3).reshape(T * C, 1, V)
    idx = torch.zeros(T * C, n_max, dtype=torch.int64)
    step = max(1, chunk // max(n_max * V, 1))
    for a in range(0, T * C, step):  # chunks of views (memory), not a loop over pixels
        d = torch.cdist(pts[a:a + step], uvv[a:a + step])  # (n, N_max, V)
        idx[a:a + step] = d.masked_fill_(behind[a:a + step], float("inf")).argmin(-1)
    return idx[view, k]


def refine_body_poses(body_model: BodyModel, K: Tensor, world_to_cam: Tensor, masks: Tensor, poses: Tensor,
                      Rh: Tensor, Th: Tensor, shapes: Tensor | None = None,
                      cfg: RefineConfig = RefineConfig()) -> RefineResult:
    """Refine body poses per frame against label masks (all frames optimised together).

    body_model: the body (SMPL or mannequin). K: (C, 3, 3), world_to_cam: (C, 4, 4) pinhole
    cameras of the masks. masks: (T, C, H, W) integer labels 0 background / 1 body / 2 garment.
    poses: (T, 72) axis-angle (EasyMocap: root ``poses[:, :3]`` normally zero; it is kept fixed,
    the global rotation is refined through Rh); Rh, Th: (T, 3); shapes: (S,), (T, S) or None.
    Returns :class:`RefineResult` with poses (T, 72), Rh, Th (T, 3) float32 (the input's dtype
    for float64 input). See the module docstring for the loss.
    """
    if poses.ndim != 2 or poses.shape[1] != 72:
        raise ValueError(f"refine_body_poses: poses must be (T, 72), got {tuple(poses.shape)}")
    T = poses.shape[0]
    if Rh.shape != (T, 3) or Th.shape != (T, 3):
        raise ValueError(f"refine_body_poses: Rh and Th must be ({T}, 3), got {tuple(Rh.shape)}, {tuple(Th.shape)}")
    if K.ndim != 3 or K.shape[1:] != (3, 3) or world_to_cam.shape != (K.shape[0], 4, 4):
        raise ValueError(f"refine_body_poses: K must be (C, 3, 3) and world_to_cam (C, 4, 4), got "
                         f"{tuple(K.shape)}, {tuple(world_to_cam.shape)}")
    C = K.shape[0]
    if masks.ndim != 4 or masks.shape[:2] != (T, C):
        raise ValueError(f"refine_body_poses: masks must be ({T}, {C}, H, W), got {tuple(masks.shape)}")
    dtype = poses.dtype if poses.dtype == torch.float64 else torch.float32
    body = body_model
    if body.v_template.dtype != dtype:
        body = _cast(body, dtype)
    P0, R0, T0 = (a.detach().to(dtype) for a in (poses, Rh, Th))
    sh = None if shapes is None else shapes.detach().to(dtype)
    Kd, Ed = K.to(dtype), world_to_cam.to(dtype)
    tgt = mask_targets(masks, cfg.max_outline_px)
    sdf = tgt.sdf.to(dtype)
    view_w = tgt.view_ok.to(dtype)[..., None]  # (T, C, 1)
    tc = tgt.outline_tc
    oxy = tgt.outline_xy.to(dtype)
    onrm = tgt.outline_normal.to(dtype)

    d_pose = torch.zeros(T, 69, dtype=dtype, requires_grad=True)
    d_rh = torch.zeros(T, 3, dtype=dtype, requires_grad=True)
    d_th = torch.zeros(T, 3, dtype=dtype, requires_grad=True)
    vertex_of = None

    def loss(step: int) -> tuple[Tensor, dict]:
        nonlocal vertex_of
        p = torch.cat([P0[:, :3], P0[:, 3:] + d_pose], 1)
        posed = body.pose(p, R0 + d_rh, T0 + d_th, sh)
        uv, z = project_points(posed.vertices, Kd, Ed)  # (T, C, V, 2), (T, C, V)
        # 1. L_inside: distance outside the subject mask of every projected vertex
        d_out, in_img = _sample(sdf, uv)
        w = view_w * (in_img & (z > 1e-3)).to(dtype)
        l_in = (w * _pseudo_huber(d_out.clamp_min(0.0).square(), cfg.robust_px)).sum() / w.sum().clamp_min(1.0)
        # 2. L_cover: body outline pixels to their nearest projected vertex
        if tc.shape[0]:
            if vertex_of is None or step % max(cfg.reassign_every, 1) == 0:
                vertex_of = _nearest_vertex(uv.detach(), z.detach(), tgt)
            q = uv[tc[:, 0], tc[:, 1], vertex_of]  # (N, 2)
            # distance along the outline's normal (the nearest vertex may sit beside the pixel along
            # the outline: vertices are a few pixels apart)
            d = ((q - oxy) * onrm).sum(-1)
            l_cov = _pseudo_huber(d.square(), cfg.robust_px).mean()
        else:
            l_cov = uv.new_zeros(())
        # 3. L_prior: change from the input in units of its typical error
        l_prior = ((d_pose.square().sum(-1) + d_rh.square().sum(-1)) / cfg.sigma_rot ** 2
                   + d_th.square().sum(-1) / cfg.sigma_trans ** 2).mean() / 75.0
        # 4. L_smooth: joint accelerations, a[t] = J[t+1] - 2 J[t] + J[t-1]
        if T >= 3:
            J = posed.joints
            acc = J[2:] - 2 * J[1:-1] + J[:-2]
            l_smooth = acc.square().sum(-1).mean() / cfg.sigma_accel ** 2
        else:
            l_smooth = uv.new_zeros(())
        terms = {"inside": l_in, "cover": l_cov, "prior": l_prior, "smooth": l_smooth}
        total = cfg.w_inside * l_in + cfg.w_cover * l_cov + cfg.w_prior * l_prior + cfg.w_smooth * l_smooth
        return total, terms

    t0 = time.perf_counter()
    opt = torch.optim.Adam([{"params": [d_pose, d_rh], "lr": cfg.lr_rot}, {"params": [d_th], "lr": cfg.lr_trans}])
    base = [g["lr"] for g in opt.param_groups]
    curve: list[float] = []
    terms_before: dict = {}
    for step in range(cfg.iters):
        f = cfg.lr_end + (1 - cfg.lr_end) * 0.5 * (1 + math.cos(math.pi * step / max(cfg.iters, 1)))
        for g, b in zip(opt.param_groups, base):
            g["lr"] = b * f
        opt.zero_grad()
        total, terms = loss(step)
        if step == 0:
            terms_before = {k: float(v.detach()) for k, v in terms.items()}
        curve.append(float(total.detach()))
        total.backward()
        for prm in (d_pose, d_rh, d_th):  # a non-finite gradient (degenerate projection) moves nothing
            prm.grad = torch.nan_to_num(prm.grad, nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
    with torch.no_grad():
        total, terms = loss(0 if cfg.iters == 0 else cfg.iters)
        if not terms_before:
            terms_before = {k: float(v.detach()) for k, v in terms.items()}
        curve.append(float(total))
        out = RefineResult(torch.cat([P0[:, :3], P0[:, 3:] + d_pose], 1).detach(), (R0 + d_rh).detach(),
                           (T0 + d_th).detach(), curve, terms_before, {k: float(v) for k, v in terms.items()},
                           time.perf_counter() - t0)
    return out


def _cast(body: BodyModel, dtype: torch.dtype) -> BodyModel:
    """The body model with its float tensors in ``dtype``."""
    import dataclasses

    kw = {}
    for f in dataclasses.fields(body):
        v = getattr(body, f.name)
        if isinstance(v, Tensor) and v.is_floating_point():
            kw[f.name] = v.to(dtype)
    return dataclasses.replace(body, **kw)


def silhouette_iou(body_model: BodyModel, K: Tensor, world_to_cam: Tensor, masks: Tensor, poses: Tensor, Rh: Tensor,
                   Th: Tensor, shapes: Tensor | None = None) -> float:
    """IoU of the rendered body against the mask's body pixels, over the pixels not labelled garment.

    Same arguments as :func:`refine_body_poses`; views without a subject pixel are skipped.
    Returns the pooled IoU (intersection and union summed over frames and views).
    """
    from .. import raster

    T, C, H, W = masks.shape
    posed = body_model.pose(poses.float(), Rh.float(), Th.float(), None if shapes is None else shapes.float())
    lab = masks.to(torch.int64)
    ok = ((lab == BODY) | (lab == GARMENT)).flatten(2).any(-1)
    inter = union = 0
    with torch.no_grad():
        for t in range(T):  # one rasterisation per frame (all views at once)
            fr = raster.rasterize(posed.vertices[t], body_model.faces, K.float(), world_to_cam.float(), H, W,
                                  with_bary=False)
            r = fr.face_id >= 0
            m = lab[t] == BODY
            known = (lab[t] != GARMENT) & ok[t][:, None, None]
            inter += int((r & m & known).sum())
            union += int(((r | m) & known).sum())
    return inter / max(union, 1)
