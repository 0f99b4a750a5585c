"""Fitting frames and sequences: flow alignment, Levenberg-Marquardt per frame, temporal filter.

Per frame the unknowns are the bone increments (:mod:`.jacobians`), minimised by Levenberg-Marquardt
(:func:`anidress_core.fit.lm.levenberg_marquardt`) over the loss terms (:mod:`.objective`). Frames t > 0 start
from frame t-1's pose moved by a few Gauss-Newton steps on L_flow alone (``flow_align_iters``, vertex projections
only, no rasterisation), which keeps fast motion inside the one-pixel reach of the silhouette gradients. After
the sequence, optionally, a temporal filter of the bone transforms (``smooth_passes``, ours). Ablation (a) of
the paper, direct vertex fitting without the rig (``method: vertex``), optimises the V x 3 vertex positions with
Adam on the same loss through autograd (Gauss-Newton on 3V unknowns is not practical). Shapes: T frames,
V vertices, B bones, C cameras. Float64 for poses and geometry, float32 for the Jacobian products.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from .. import raster
from ..geometry import lbs, nearest_rotation
from .config import FitConfig
from .jacobians import JACOBIAN_DTYPE, apply_increment, projection_jacobian, skin_jacobian
from .lm import levenberg_marquardt
from .nearest import score_poses
from .objective import evaluate, gauss_newton_system, loss_terms, windowed_problem
from .plan import FitPlan
from .problem import Crop, FlowTargets, FrameCues, Problem, RigParts, Views, check_cues, cue_notes, uncrop_fragments
from .terms.anchor import AnchorRef, update_anchor
from .terms.collision import body_contacts
from .terms.flow import flow_targets
from .terms.prior import Reference
from .window import pair_flow, refine_window

__all__ = ["FrameFit", "flow_align", "fit_problem", "fit_frame", "smooth_transforms", "fit_sequence"]


@dataclass
class FrameFit:
    """Result of :func:`fit_frame`."""

    transforms: Tensor
    """(B, 4, 4) bone transforms rest -> world (:func:`fit_frame`'s vertex method: the start's, unchanged)."""
    verts: Tensor
    """(V, 3) fitted mesh."""
    terms: dict
    """Unweighted loss terms at the result, every name of :data:`anidress_core.fit.terms.TERM_NAMES` (float; 0 for
    an unused term); :func:`fit_sequence` adds wall_s and flow_targets."""
    loss: float
    """Weighted total at the result."""
    iterations: int
    """Loss evaluations spent (LM: accepted + rejected steps; vertex: Adam steps)."""
    converged: bool
    """Stopped by a tolerance rather than by the iteration limit."""
    curve: list = field(default_factory=list)
    """Weighted total loss after each accepted step (index 0: the start)."""
    fragments: raster.Fragments | None = None
    """Occluded fragments of the result (for the next frame's flow targets)."""
    notes: dict = field(default_factory=dict)
    """What the fit did about defective cues in this frame (:func:`anidress_core.fit.problem.cue_notes`; empty:
    nothing), and from :func:`fit_sequence` ``no_flow`` (L_flow off), ``nearest`` (the baseline's pick) and, on
    the last frame of a window refined jointly, ``window`` (:func:`anidress_core.fit.window.refine_window`)."""
    problem: Problem | None = None
    """The problem the frame was fitted on (``fit_frame(keep_problem=True)``, method rig), else None."""
    crop: Crop | None = None
    """Its render windows (None: whole images), kept with ``problem``."""


def flow_align(rig: RigParts, views: Views, flow: FlowTargets, transforms: Tensor, iters: int) -> Tensor:
    """Minimise L_flow alone over the bone increments from ``transforms`` (B, 4, 4) by damped Gauss-Newton.

    The flow residuals are vertex projections, nearly linear in the increments, so a few steps move the previous
    frame's pose to where the flow says the visible vertices went. Every step must lower L_flow, else the pose
    before it is kept.
    """
    G = transforms.double().clone()
    # only the U vertices with a target count: the rig restricted to them (skin_jacobian and lbs read rest,
    # weights and centres only)
    used, slot = torch.unique(flow.vert, return_inverse=True)
    U = used.numel()
    sub = rig._replace(rest=rig.rest[used], weights=rig.weights[used])

    def cost(M):
        uv, _ = raster.project_vertices(lbs(sub.rest, sub.weights, M), views.K, views.world_to_cam)
        d = uv[flow.cam, slot] - flow.target
        return float((d * d).sum())

    c = cost(G)
    for _ in range(iters):
        x = lbs(sub.rest, sub.weights, G)  # (U, 3)
        J3 = skin_jacobian(sub, G).to(JACOBIAN_DTYPE)  # (U, 3, P)
        uv, Puv = projection_jacobian(x, views)
        Pf = Puv[flow.cam, slot]  # (N, 2, 3)
        r = uv[flow.cam, slot] - flow.target
        blocks = torch.zeros(U, 3, 3, dtype=x.dtype, device=x.device).index_add_(0, slot, Pf.transpose(1, 2) @ Pf)
        gx = torch.zeros(U, 3, dtype=x.dtype, device=x.device).index_add_(0, slot, torch.einsum("nij,ni->nj", Pf, r))
        BJ = torch.einsum("vjk,vkq->vjq", blocks.to(J3.dtype), J3).reshape(3 * U, -1)  # (3U, P)
        H = (J3.reshape(3 * U, -1).t() @ BJ).double()
        g = (J3.reshape(3 * U, -1).t() @ gx.reshape(-1).to(J3.dtype)).double()
        d = H.diagonal()
        delta, info = torch.linalg.solve_ex(H + torch.diag(1e-3 * d + 1e-9 * float(d.max().clamp_min(1e-30))), -g)
        if int(info) != 0 or not bool(torch.isfinite(delta).all()):
            break
        G_new = apply_increment(G, rig.centres, delta.view(-1, 6))
        c_new = cost(G_new)
        if not c_new < c:
            break
        gain = (c - c_new) / max(c, 1e-30)
        G, c = G_new, c_new
        if gain < 1e-3:
            break
    return G


def fit_problem(pb: Problem, transforms: Tensor, max_iters: int) -> FrameFit:
    """Levenberg-Marquardt on the bone increments of one frame's problem from ``transforms`` (B, 4, 4)."""
    cfg, rig = pb.cfg, pb.rig
    res = levenberg_marquardt(
        lambda G: evaluate(pb, lbs(rig.rest, rig.weights, G)),
        lambda ev, G: gauss_newton_system(pb, ev, G, JACOBIAN_DTYPE),
        lambda G, delta: apply_increment(G, rig.centres, delta.view(-1, 6)),
        transforms.double().clone(), max_iters, cfg.damping, cfg.rel_tol, cfg.step_tol)
    ev = res.evaluation
    return FrameFit(res.x.clone(), ev.verts, dict(ev.terms), ev.loss, res.iterations, res.converged, res.curve,
                    ev.fragments)


def vertex_adam(pb: Problem, start_verts: Tensor, transforms: Tensor, max_iters: int) -> FrameFit:
    """Ablation (a): Adam on the vertex positions, same loss (autograd through the renderer)."""
    cfg = pb.cfg
    x = start_verts.double().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=cfg.vertex.lr)
    best, best_x, since = float("inf"), x.detach().clone(), 0
    curve = []
    it, converged = 0, False
    for it in range(1, max_iters + 1):
        opt.zero_grad()
        total, _ = loss_terms(pb, x)
        val = float(total)
        if not math.isfinite(val):
            break
        if val < best * (1 - cfg.rel_tol):
            since = 0
        else:
            since += 1
        if val < best:
            best, best_x = val, x.detach().clone()
        curve.append(val)
        if since >= cfg.vertex.patience:
            converged = True
            break
        total.backward()
        if not bool(torch.isfinite(x.grad).all()):
            break
        opt.step()
    ev = evaluate(pb, best_x)
    return FrameFit(transforms.double().clone(), best_x, dict(ev.terms), ev.loss, it, converged, curve, ev.fragments)


def fit_frame(rig: RigParts, views: Views, cues: FrameCues, init: Tensor, cfg: FitConfig | None = None,
              flow: FlowTargets | None = None, first: bool = False, init_verts: Tensor | None = None,
              anchor: AnchorRef | None = None, prior_verts: Tensor | None = None, keep_problem: bool = False,
              prior_scale: Tensor | None = None) -> FrameFit:
    """Fit one frame from ``init`` (B, 4, 4), frame t-1's result or frame 0's start.

    flow: targets from :func:`flow_targets` (None at the first frame or without flow); first: ``max_iters_first``.
    Method 'vertex': the start mesh is ``init_verts`` (V, 3) (default: LBS of ``init``), ``init`` is returned
    unchanged. anchor: L_anchor's references (:func:`update_anchor`). prior_verts: (V, 3) L_prior's reference at
    this frame (default: at the first frame the start, none after it), prior_scale: (V,) its factor per vertex
    (:func:`anidress_core.fit.terms.prior.spread_scale`; default 1). keep_problem: the result keeps its problem
    and render windows (method rig). Never returns non-finite poses: steps with a non-finite loss are rejected,
    and defective cues are handled as :func:`anidress_core.fit.problem.cue_notes` says (no view left: the start
    pose, ``init`` moved by the flow alignment, is kept, ``converged`` False), recorded in the result's ``notes``.
    cfg: default the pipeline's (:meth:`FitConfig.from_config` of an empty section).
    """
    cfg = FitConfig.from_config({}) if cfg is None else cfg
    init = torch.as_tensor(init, device=rig.rest.device).double()
    if init.shape != (rig.weights.shape[1], 4, 4):
        raise ValueError(f"fit_frame: init must be ({rig.weights.shape[1]}, 4, 4), got {tuple(init.shape)}")
    if not bool(torch.isfinite(init).all()):
        raise ValueError("fit_frame: the starting transforms contain NaN or inf")
    check_cues(views, cues)
    cues, flow, notes = cue_notes(cues, None if first else flow)
    G = init
    if cfg.method == "vertex":
        x_start = lbs(rig.rest, rig.weights, init) if init_verts is None else init_verts.double()
    else:
        if (cfg.method == "rig" and flow is not None and cfg.weights.flow > 0 and cfg.flow_align_iters > 0
                and flow.cam.numel()):
            G = flow_align(rig, views, flow, G, cfg.flow_align_iters)
        x_start = lbs(rig.rest, rig.weights, G)
    if prior_verts is not None:
        prior = torch.as_tensor(prior_verts, device=rig.rest.device).double()
    else:
        prior = lbs(rig.rest, rig.weights, init) if first and cfg.method == "rig" else (x_start if first else None)
    if prior is not None:  # L_prior's reference, its factor per vertex, its tangent planes
        prior = Reference(prior, prior_scale if cfg.method == "rig" else None,
                          x_start if cfg.prior_tangent_planes == "start" else None)
    contacts = None
    if cfg.weights.collision > 0 and cfg.method in ("rig", "nearest"):
        if cues.occluder_mesh is None:
            raise ValueError("fit: weights.collision > 0 needs the body mesh (FrameCues.occluder_mesh)")
        contacts = body_contacts(x_start, *cues.occluder_mesh, cfg.collision_radius)
    pb, window = windowed_problem(rig, views, cues, cfg, x_start, flow, prior=prior, collision=contacts,
                                  anchor=None if cfg.method == "vertex" else anchor)
    if notes.get("no_mask") or cfg.method == "nearest":  # the start evaluated, not optimised
        ev = evaluate(pb, x_start)
        res = FrameFit(G.clone(), ev.verts, dict(ev.terms), ev.loss, 0, not notes.get("no_mask"), [ev.loss],
                       ev.fragments)
    elif cfg.method == "vertex":
        res = vertex_adam(pb, x_start, init, cfg.vertex.max_iters * (3 if first else 1))
    else:
        res = fit_problem(pb, G, cfg.max_iters_first if first else cfg.max_iters)
    res.notes = notes
    if keep_problem and cfg.method == "rig":
        res.problem, res.crop = pb, window
    if window is not None:  # visibility in whole images (outside the windows: no garment)
        res.fragments = uncrop_fragments(res.fragments, window, views.height, views.width)
    return res


def smooth_transforms(transforms: Tensor, passes: int = 1) -> Tensor:
    """Temporal filter of bone transforms (T, B, 4, 4) -> (T, B, 4, 4) (not in the paper).

    Each pass replaces every inner frame by (G[t-1] + 2 G[t] + G[t+1]) / 4 (the first and last
    frames are kept) and projects the rotation block back onto SO(3) (the closest rotation,
    by SVD). Skinning is linear in the transforms, so before the projection the skinned
    vertices are the same filter of the fitted vertices; the projection changes them only by
    the spread of the three rotations (second order). A rotation at constant angular velocity
    and a translation at constant velocity pass unchanged. Cuts the frame-to-frame jitter of
    per-frame fits.
    """
    G = torch.as_tensor(transforms).clone()
    if G.ndim != 4 or G.shape[-2:] != (4, 4):
        raise ValueError(f"smooth_transforms: transforms must be (T, B, 4, 4), got {tuple(G.shape)}")
    for _ in range(int(passes)):
        if G.shape[0] < 3:
            break
        inner = 0.25 * G[:-2] + 0.5 * G[1:-1] + 0.25 * G[2:]
        inner[..., :3, :3] = nearest_rotation(inner[..., :3, :3])
        G[1:-1] = inner
    return G


def fit_sequence(plan: FitPlan, cues_of: Callable[[int], FrameCues],
                 flow_of: Callable[[int], tuple[Tensor, Tensor | None] | None], progress: bool = True,
                 log: logging.Logger = logging.getLogger("anidress.fit")) -> list[FrameFit]:
    """Fit frames 0..T-1 of ``plan`` (:class:`anidress_core.fit.FitPlan`) in order, frame t starting from frame
    t-1's result (or from ``plan.starts[t]``, the oracle, with the flow alignment and the rest as usual).

    cues_of(t) -> :class:`FrameCues`; flow_of(t) -> (flow (C, H, W, 2), valid (C, H, W) or None) of t-1 -> t, or
    None (L_flow off there, ``notes['no_flow']``). Returns one :class:`FrameFit` per frame (its wall time in
    ``terms['wall_s']``; its ``notes`` logged as a warning). L_anchor's references are taken from each frame's
    result (:func:`update_anchor`) and used from the next frame on, the vertices of ``plan.anchor_init`` keeping
    theirs. ``cfg.window`` > 1 (method rig): after every ``window`` chained frames (and at the last frame) those
    frames are refined jointly (:mod:`anidress_core.fit.window`), the next frame chained from the refined last one.
    The temporal filter comes last. Method 'nearest': frame t's pose is the candidate of ``plan.candidates_of(t)``
    with the lowest loss (:func:`score_poses`; ``notes['nearest']``). Method 'vertex': the stored transforms are the
    rig's closest to the fitted vertices (:meth:`RigParts.closest_pose`).
    """
    from tqdm import tqdm

    cfg, rig, views, T = plan.cfg, plan.rig, plan.views, plan.frames
    dev = rig.rest.device
    follows = cfg.prior_follows_simulation
    if follows and (plan.sim_transforms is None or plan.sim_transforms.shape[0] < T):
        raise ValueError(f"fit_sequence: prior_reference {cfg.prior_reference!r} needs the simulated transforms of "
                         f"all {T} frames")
    for name in ("starts", "prior_scales"):
        if getattr(plan, name) is not None and getattr(plan, name).shape[0] < T:
            raise ValueError(f"fit_sequence: {name} must hold all {T} frames, got {tuple(getattr(plan, name).shape)}")
    if cfg.method == "nearest" and plan.candidates_of is None:
        raise ValueError("fit_sequence: method 'nearest' needs candidates_of (the simulation database)")
    use_window = cfg.window > 1 and cfg.method == "rig"
    pairs: list = []  # the current window's coupled flow targets (pair_flow), one per frame so far
    out: list[FrameFit] = []
    G = torch.as_tensor(plan.init, device=dev).double()
    x_prev, prev_mask, anchor = None, None, plan.anchor_init
    for t in tqdm(range(T), desc="fit", unit="frame", disable=not progress):
        t0 = time.perf_counter()
        cues = cues_of(t)
        targets = None
        if t > 0 and cfg.weights.flow > 0:
            fl = flow_of(t)
            if fl is None:
                log.warning("fit: frame %d has no flow; L_flow is off for it", t)
            else:
                prev = out[-1]
                targets = flow_targets(prev.verts, views, prev.fragments, fl[0], fl[1], prev_mask,
                                       cfg.visibility_depth_tol, cfg.flow_margin_px)
        if plan.starts is not None:
            G = torch.as_tensor(plan.starts[t], device=dev).double()
        picked = None
        if cfg.method == "nearest":  # the baseline: the database pose with the lowest loss, not optimised
            cands = plan.candidates_of(t)
            scores = score_poses(rig, views, cues, cands.transforms, cfg, targets, anchor)
            i = int(torch.argmin(torch.nan_to_num(scores, nan=float("inf"))))
            G, picked = cands.transforms[i].double(), {"kept": cands.labels[i], "candidates": len(cands.labels)}
        if use_window:
            pairs.append(None if t % cfg.window == 0 else pair_flow(targets, out[-1].verts, views))
        prior = None
        if follows:
            prior = lbs(rig.rest, rig.weights, torch.as_tensor(plan.sim_transforms[t], device=dev).double())
        res = fit_frame(rig, views, cues, G, cfg, targets, first=(t == 0), init_verts=x_prev, anchor=anchor,
                        prior_verts=prior, keep_problem=use_window,
                        prior_scale=plan.prior_scales[t] if follows and plan.prior_scales is not None else None)
        if t > 0 and cfg.weights.flow > 0 and (targets is None or targets.cam.numel() == 0):
            res.notes["no_flow"] = True
        if res.notes:
            log.warning("fit: frame %d: %s", t, res.notes)
        if picked is not None:  # the baseline's pick: a record, not a defect
            res.notes = {**res.notes, "nearest": picked}
        if cfg.weights.anchor > 0 and cues.image is not None:
            anchor = update_anchor(anchor, res.verts, views, res.fragments, cues.image, cues.mask, cfg)
        res.terms["wall_s"] = time.perf_counter() - t0
        res.terms["flow_targets"] = 0 if targets is None else int(targets.cam.numel())
        out.append(res)
        if use_window and ((t + 1) % cfg.window == 0 or t == T - 1):
            first_of_window = t + 1 - len(pairs)
            out[first_of_window:] = refine_window(out[first_of_window:], pairs, views, cfg.window_iters, log)
            pairs = []
        G = out[-1].transforms
        x_prev = res.verts if cfg.method == "vertex" else None
        prev_mask = cues.mask
    if cfg.smooth_passes > 0 and cfg.method == "rig" and len(out) >= 3:
        Gs = smooth_transforms(torch.stack([r.transforms for r in out]), cfg.smooth_passes)
        for r, g in zip(out, Gs):
            r.transforms, r.verts = g, lbs(rig.rest, rig.weights, g)
    if cfg.method == "vertex" and out:  # no bone transforms: the rig pose closest to the fitted vertices
        for r, g in zip(out, rig.closest_pose(torch.stack([r.verts.detach() for r in out]))):
            r.transforms = g
    return out
