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
Th; they are optimised with Levenberg-Marquardt on the Gauss-Newton system (``method="lm"``, the
default) or with Adam (autograd through :meth:`BodyModel.pose`; settings :data:`ADAM_SETTINGS`).
Measured on the demo skirt exported as a capture (12 cameras 256 x 256, 6500-vertex mannequin,
parser-like masks, 2.2 cm start, 16 frames, one CPU thread of a shared 2-core machine): Adam 20 steps
0.93 cm at 0.65 s/frame, 50 steps 0.84 cm at 1.3 s/frame; LM 3 evaluations 0.94 cm at 1.1 s/frame,
6 evaluations 0.79 cm at 1.7 s/frame (with Adam's prior weight 0.05 LM reaches a lower loss but
1.3 cm: it fits the parser masks' errors, hence w_prior = 2 for LM). The whole walk (60 frames, chunks
of 16, ``anidress refine-body``): 2.00 -> 0.72 cm with LM at 2.05 s/frame, 0.79 cm with Adam at
2.4 s/frame, joint angles 2.58 -> 2.43 deg with LM, 2.86 deg with Adam; the exact poses against the
same parser masks move by 0.42 cm (LM, 32 frames). On exact masks (the tests' scene: 4
cameras, 6 frames, 1500 vertices) LM with w_prior 0.05 reached 0.55 cm in 5 evaluations (0.85 s) against
Adam's 0.59 cm in 50 steps (1.45 s); with the default w_prior 2 it stops at 0.89 cm (the prior holds it
back with 4 views) and moves exact poses by 0.14 cm (Adam: 0.33 cm). Timings are of a machine shared with
other jobs (+-30 %).

Views whose mask holds no subject pixel (the subject is not seen or the mask is missing) give no
residual. Cameras are pinholes without distortion (undistort the masks first, like the garment fit).

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

__all__ = ["ADAM_SETTINGS", "RefineConfig", "RefineResult", "MaskTargets", "mask_targets", "refine_body_poses",
           "silhouette_iou", "project_points", "project_points_jacobian", "gauss_newton_system"]

BODY, GARMENT = 1, 2


ADAM_SETTINGS = {"method": "adam", "w_prior": 0.05}
"""RefineConfig fields for Adam (``RefineConfig(**ADAM_SETTINGS)``; the defaults are Levenberg-Marquardt's)."""


@dataclass(frozen=True)
class RefineConfig:
    """Settings of :func:`refine_body_poses` (weights are relative to L_inside's)."""

    method: str = "lm"
    """``"adam"`` (first-order, autograd) or ``"lm"`` (Levenberg-Marquardt on the Gauss-Newton system,
    IRLS weights for the robust penalty, :func:`anidress_core.fit.lm.levenberg_marquardt`)."""
    iters: int = 50
    """Adam steps."""
    lm_iters: int = 6
    """Levenberg-Marquardt evaluations (accepted + rejected steps)."""
    lm_damping: float = 1e-3
    """Initial LM damping relative to the largest diagonal entry of the system."""
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
    w_prior: float = 2.0
    """Weight of L_prior (mean over components of (change / sigma)^2 per frame); 0.05 for Adam, whose few
    small steps regularise by themselves (:data:`ADAM_SETTINGS`)."""
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


def _objective(body_model: BodyModel, K: Tensor, world_to_cam: Tensor, masks: Tensor, poses: Tensor, Rh: Tensor,
               Th: Tensor, shapes: Tensor | None, cfg: RefineConfig):
    """The loss of :func:`refine_body_poses` as a function of the increments (validated inputs).

    Returns (body, P0, R0, T0, shapes, K, world_to_cam, sdf, targets, loss) in the working dtype; loss(d_pose
    (T, 69), d_rh (T, 3), d_th (T, 3), reassign) -> an evaluation (.loss float, .total Tensor, .terms, .aux).
    """
    T = poses.shape[0]
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

    vertex_of = None

    class _Eval(NamedTuple):
        loss: float
        total: Tensor
        terms: dict
        aux: dict

    def loss(d_pose: Tensor, d_rh: Tensor, d_th: Tensor, reassign: bool) -> _Eval:
        nonlocal vertex_of
        p = torch.cat([P0[:, :3], P0[:, 3:] + d_pose], 1)
        posed = body.pose(p, R0 + d_rh, T0 + d_th, sh)
        uv, z = project_points(posed.vertices, Kd, Ed)  # (T, C, V, 2), (T, C, V)
        # 1. L_inside: distance outside the subject mask of every projected vertex
        d_out, in_img = _sample(sdf, uv)
        w = view_w * (in_img & (z > 1e-3)).to(dtype)
        n_in = w.sum().clamp_min(1.0)
        l_in = (w * _pseudo_huber(d_out.clamp_min(0.0).square(), cfg.robust_px)).sum() / n_in
        # 2. L_cover: body outline pixels to their nearest projected vertex
        d = None
        if tc.shape[0]:
            if vertex_of is None or reassign:
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
        acc = None
        if T >= 3:
            J = posed.joints
            acc = J[2:] - 2 * J[1:-1] + J[:-2]
            l_smooth = acc.square().sum(-1).mean() / cfg.sigma_accel ** 2
        else:
            l_smooth = uv.new_zeros(())
        terms = {"inside": l_in, "cover": l_cov, "prior": l_prior, "smooth": l_smooth}
        total = cfg.w_inside * l_in + cfg.w_cover * l_cov + cfg.w_prior * l_prior + cfg.w_smooth * l_smooth
        aux = {"uv": uv, "z": z, "d_out": d_out, "w": w, "n_in": n_in, "d": d, "vertex_of": vertex_of, "acc": acc}
        return _Eval(float(total.detach()), total, terms, aux)

    return body, P0, R0, T0, sh, Kd, Ed, sdf, tgt, loss


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
    body, P0, R0, T0, sh, Kd, Ed, sdf, tgt, loss = _objective(body_model, K, world_to_cam, masks, poses, Rh, Th,
                                                              shapes, cfg)
    dtype = P0.dtype
    if cfg.method == "lm":
        return _refine_lm(body, P0, R0, T0, sh, Kd, Ed, sdf, tgt, loss, cfg)
    if cfg.method != "adam":
        raise ValueError(f"refine_body_poses: method must be 'adam' or 'lm', got {cfg.method!r}")
    d_pose = torch.zeros(T, 69, dtype=dtype, requires_grad=True)
    d_rh = torch.zeros(T, 3, dtype=dtype, requires_grad=True)
    d_th = torch.zeros(T, 3, dtype=dtype, requires_grad=True)

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
        ev = loss(d_pose, d_rh, d_th, step % max(cfg.reassign_every, 1) == 0)
        total, terms = ev.total, ev.terms
        if step == 0:
            terms_before = {k: float(v.detach()) for k, v in terms.items()}
        curve.append(float(total.detach()))
        total.backward()
        for prm in (d_pose, d_rh, d_th):  # a non-finite gradient (degenerate projection) moves nothing
            prm.grad = torch.nan_to_num(prm.grad, nan=0.0, posinf=0.0, neginf=0.0)
        opt.step()
    with torch.no_grad():
        ev = loss(d_pose, d_rh, d_th, True)
        total, terms = ev.total, ev.terms
        if not terms_before:
            terms_before = {k: float(v.detach()) for k, v in terms.items()}
        curve.append(float(total))
        out = RefineResult(torch.cat([P0[:, :3], P0[:, 3:] + d_pose], 1).detach(), (R0 + d_rh).detach(),
                           (T0 + d_th).detach(), curve, terms_before, {k: float(v) for k, v in terms.items()},
                           time.perf_counter() - t0)
    return out


def project_points_jacobian(uv: Tensor, z: Tensor, K: Tensor, world_to_cam: Tensor) -> Tensor:
    """d uv / d x_world (T, C, V, 2, 3) of :func:`project_points` (pinhole, K with skew)."""
    zs = torch.where(z.abs() > 1e-6, z, torch.full_like(z, 1e-6))
    Kc = K.to(uv.dtype)[:, :, :, None]  # (C, 3, 3, 1): broadcasts against (T, C, V)
    fx, s_, cx, fy, cy = Kc[:, 0, 0], Kc[:, 0, 1], Kc[:, 0, 2], Kc[:, 1, 1], Kc[:, 1, 2]
    zero = torch.zeros_like(zs)
    # d(u, v)/d X_cam = [[fx, s, -(u - cx)], [0, fy, -(v - cy)]] / z
    row_u = torch.stack([fx.expand_as(zs), s_.expand_as(zs), -(uv[..., 0] - cx)], -1)
    row_v = torch.stack([zero, fy.expand_as(zs), -(uv[..., 1] - cy)], -1)
    Jc = torch.stack([row_u, row_v], -2) / zs[..., None, None]  # (T, C, V, 2, 3)
    # d uv / d x[t, c, v, i, k] = sum_j Jc[t, c, v, i, j] R[c, j, k]
    return torch.einsum("tcvij,cjk->tcvik", Jc, world_to_cam[:, :3, :3].to(uv.dtype))


def _split(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Increments (T, 75) -> joint poses (T, 69), Rh (T, 3), Th (T, 3)."""
    return x[:, :69], x[:, 69:72], x[:, 72:]


def _lm_system(body: BodyModel, P0: Tensor, R0: Tensor, T0: Tensor, sh: Tensor | None, K: Tensor, E: Tensor,
               sdf: Tensor, tgt: MaskTargets, cfg: RefineConfig):
    """The Gauss-Newton system (H (75 T, 75 T), g (75 T,)) float64 of the loss at increments x (T, 75) =
    (joint poses 69, Rh 3, Th 3) per frame, as a function system(evaluation at x, x).

    Convention of :func:`anidress_core.fit.lm.levenberg_marquardt`: L ~ L + 2 g.dx + dx.H dx. Each robust
    residual d of weight c adds c w/2 (dd)(dd)^T to H and c w d / 2 dd to g with the IRLS weight
    w = 1 / sqrt(1 + d^2 / s^2) (the pseudo-Huber penalty's derivative), so g is half the exact gradient;
    dd = (dd/dX) (dX/dx), with dX/dx (T, V, 3, 75) the body's Jacobian by forward-mode autodiff with ONE
    increment shared by all frames (frame t's vertices depend on frame t's increment only: 75 tangents
    for every frame at once). The smoothness term couples neighbouring frames, so H is the full
    (75 T, 75 T) matrix (block-diagonal plus the acceleration terms).
    """
    T, dtype = P0.shape[0], P0.dtype
    n = 75
    s2 = cfg.robust_px ** 2
    tc = tgt.outline_tc
    onrm = tgt.outline_normal.to(dtype)
    split = _split

    def posed_of(x: Tensor):
        def f(delta: Tensor) -> tuple[Tensor, Tensor]:
            dp, dr, dt = split(x + delta[None])
            pz = body.pose(torch.cat([P0[:, :3], P0[:, 3:] + dp], 1), R0 + dr, T0 + dt, sh)
            return pz.vertices, pz.joints
        return torch.func.jacfwd(f)(torch.zeros(n, dtype=dtype))  # (T, V, 3, 75), (T, 24, 3, 75)

    def system(ev, x: Tensor) -> tuple[Tensor, Tensor]:
        a = ev.aux
        uv, z = a["uv"], a["z"]
        dX, dJ = posed_of(x)
        V = uv.shape[2]
        Puv = project_points_jacobian(uv, z, K, E)  # (T, C, V, 2, 3)
        # 1. inside: d = relu(sdf(uv)), dd/dX = grad sdf(uv) . duv/dX (bilinear gradient by autograd)
        with torch.enable_grad():
            q = uv.detach().requires_grad_()
            g_uv, = torch.autograd.grad(_sample(sdf, q)[0].sum(), q)
        d_in = a["d_out"].clamp_min(0.0)
        c_in = cfg.w_inside * a["w"] * (a["d_out"] > 0).to(dtype) / a["n_in"]
        w_in = c_in / torch.sqrt(1.0 + d_in.square() / s2)
        g_in = torch.einsum("tcvi,tcvij->tcvj", g_uv, Puv)  # (T, C, V, 3)
        # M[t, v] = sum_c w a a^T,  b[t, v] = sum_c w d a
        M = torch.einsum("tcv,tcvi,tcvj->tvij", w_in, g_in, g_in)
        b = torch.einsum("tcv,tcvi->tvi", w_in * d_in, g_in)
        # 2. cover: d = n . (uv[q] - p), dd/dX_q = n^T duv/dX_q
        if a["d"] is not None:
            d = a["d"]
            vq = a["vertex_of"]
            g_cov = torch.einsum("ni,nij->nj", onrm, Puv[tc[:, 0], tc[:, 1], vq])  # (N, 3)
            w_cov = cfg.w_cover / d.shape[0] / torch.sqrt(1.0 + d.square() / s2)
            flat = tc[:, 0] * V + vq
            M = M.reshape(T * V, 3, 3).index_add(0, flat, w_cov[:, None, None] * g_cov[:, :, None] * g_cov[:, None, :])
            b = b.reshape(T * V, 3).index_add(0, flat, (w_cov * d)[:, None] * g_cov)
            M, b = M.reshape(T, V, 3, 3), b.reshape(T, V, 3)
        # H_t = 1/2 sum_v dX^T M dX, g_t = 1/2 sum_v dX^T b
        Hb = 0.5 * torch.einsum("tvip,tvij,tvjq->tpq", dX, M, dX)
        gb = 0.5 * torch.einsum("tvip,tvi->tp", dX, b)
        H = torch.block_diag(*Hb).double()
        g = gb.reshape(-1).double()
        # 3. prior: c x^2 / sigma^2 per component
        c_p = cfg.w_prior / (75.0 * T)
        sig = torch.cat([torch.full((72,), cfg.sigma_rot), torch.full((3,), cfg.sigma_trans)]).double() ** 2
        diag = (c_p / sig).repeat(T)
        H = H + torch.diag(diag)
        g = g + diag * x.reshape(-1).double()
        # 4. smoothness: acc[k] = J[k+2] - 2 J[k+1] + J[k], Jacobian rows (T-2) * 72, columns 75 T
        if a["acc"] is not None:
            c_s = cfg.w_smooth / ((T - 2) * 24 * cfg.sigma_accel ** 2)
            Js = torch.zeros(T - 2, 72, T, n, dtype=torch.float64)
            k = torch.arange(T - 2)
            for o, coef in ((0, 1.0), (1, -2.0), (2, 1.0)):  # the three frames of each acceleration
                Js[k, :, k + o] += coef * dJ[k + o].reshape(T - 2, 72, n).double()
            Js = Js.reshape((T - 2) * 72, T * n)
            H = H + c_s * Js.t() @ Js
            g = g + c_s * Js.t() @ a["acc"].reshape(-1).double()
        return H, g

    return system


def _refine_lm(body: BodyModel, P0: Tensor, R0: Tensor, T0: Tensor, sh: Tensor | None, K: Tensor, E: Tensor,
               sdf: Tensor, tgt: MaskTargets, loss, cfg: RefineConfig) -> RefineResult:
    """Levenberg-Marquardt (:func:`anidress_core.fit.lm.levenberg_marquardt`) on the increments (T, 75),
    the system of :func:`_lm_system`, solved densely."""
    from ..fit.lm import levenberg_marquardt

    T, dtype, n = P0.shape[0], P0.dtype, 75
    system = _lm_system(body, P0, R0, T0, sh, K, E, sdf, tgt, cfg)

    def evaluate(x: Tensor):
        with torch.no_grad():
            return loss(*_split(x), True)

    t0 = time.perf_counter()
    x0 = torch.zeros(T, n, dtype=dtype)
    ev0 = evaluate(x0)
    res = levenberg_marquardt(evaluate, system, lambda x, d: x + d.reshape(T, n).to(dtype), x0,
                              max_iters=cfg.lm_iters, damping=cfg.lm_damping, rel_tol=1e-6, step_tol=1e-7)
    dp, dr, dt = _split(res.x)
    return RefineResult(torch.cat([P0[:, :3], P0[:, 3:] + dp], 1), R0 + dr, T0 + dt, list(res.curve),
                        {k: float(v) for k, v in ev0.terms.items()},
                        {k: float(v) for k, v in res.evaluation.terms.items()}, time.perf_counter() - t0)


def gauss_newton_system(body_model: BodyModel, K: Tensor, world_to_cam: Tensor, masks: Tensor, poses: Tensor,
                        Rh: Tensor, Th: Tensor, x: Tensor, shapes: Tensor | None = None,
                        cfg: RefineConfig = RefineConfig()) -> tuple[Tensor, Tensor, Tensor]:
    """The loss of :func:`refine_body_poses` at increments x (T, 75) (joint poses 69, Rh 3, Th 3 per frame)
    with its autograd graph to x, and the Levenberg-Marquardt system there: (loss (), H (75 T, 75 T),
    g (75 T,)), g being half the gradient (for checks; same arguments as :func:`refine_body_poses`)."""
    ob = _objective(body_model, K, world_to_cam, masks, poses, Rh, Th, shapes, cfg)
    body, P0, R0, T0, sh, Kd, Ed, sdf, tgt, loss = ob
    ev = loss(*_split(x.to(P0.dtype)), True)
    H, g = _lm_system(body, P0, R0, T0, sh, Kd, Ed, sdf, tgt, cfg)(ev, x.detach().to(P0.dtype))
    return ev.total, H, g


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
