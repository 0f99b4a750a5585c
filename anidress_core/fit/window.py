"""A window of frames fitted jointly, flow constraints between all its frames (issue 23; ours).

The forward chain (:func:`anidress_core.fit.fit_sequence`) fits frame t with L_flow's targets carried
from frame t-1's result, held fixed: an error of frame t-1 pulls frame t along, and nothing later can
pull frame t-1 back. Here W consecutive chained frames s .. s+W-1 are refined together by one
Levenberg-Marquardt over all their bone increments (W x 6 B unknowns). Inside the window L_flow
couples two unknown poses:

    r_n = uv_t(x_t[v_n]) - uv_{t-1}(x_{t-1}[v_n]) - f_n,     L_flow,t = sum_n |r_n|^2 / n_px(t)

over the chain's flow targets (view, vertex) of frame t (:func:`anidress_core.fit.flow_targets`: visible at
t-1, inside the mask, valid flow), with the flow vector f_n (pixels) sampled once at the chain's projection
of t-1 and held fixed (so the residual is linear in the two projections and its Gauss-Newton block exact).
Frame s keeps its targets carried from frame s-1 (the previous window's result, fixed); every other
term is each frame's own problem as the chain built it (the same masks, normals, render windows, L_anchor
references, L_collision planes, L_prior reference). The start is the chain's result, so the window's
loss can only go down. Shapes: W frames in the window, V vertices, B bones, C cameras, N targets,
P = 6 B.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import time
from typing import NamedTuple

import torch
from torch import Tensor

from .. import raster
from ..geometry import lbs
from .jacobians import JACOBIAN_DTYPE, apply_increment, projection_jacobian, skin_jacobian
from .lm import levenberg_marquardt
from .objective import evaluate, gauss_newton_system, total_loss
from .problem import FlowTargets, Problem, Views, uncrop_fragments

__all__ = ["PairFlow", "pair_flow", "WindowEvaluation", "evaluate_window", "window_system", "refine_window"]


class PairFlow(NamedTuple):
    """L_flow between two unknown frames t-1 and t (whole-image pixel coordinates)."""

    cam: Tensor  # (N,) int64 view
    vert: Tensor  # (N,) int64 vertex
    flow: Tensor  # (N, 2) float64 flow t-1 -> t at the vertex's projection in t-1 (pixels), held fixed


def pair_flow(targets: FlowTargets | None, prev_verts: Tensor, views: Views) -> PairFlow | None:
    """The coupled form of frame t's carried targets: f = target - uv_{t-1}(prev_verts) (prev_verts (V, 3),
    the mesh the targets were made from). None when there are no targets."""
    if targets is None or targets.cam.numel() == 0:
        return None
    uv, _ = raster.project_vertices(prev_verts.double(), views.K, views.world_to_cam)  # (C, V, 2)
    return PairFlow(targets.cam, targets.vert, targets.target - uv[targets.cam, targets.vert])


class WindowEvaluation(NamedTuple):
    """The window's loss at W poses (:func:`evaluate_window`)."""

    loss: float  # sum over frames of their problems' totals + w_flow * the coupled L_flow
    frames: list  # W :class:`anidress_core.fit.objective.Evaluation` (each frame's own problem)
    uv: list  # W (C, V, 2) whole-image projections
    pair: list  # W floats: the coupled L_flow of frame i (unweighted; 0.0 for i = 0 or no targets)


def evaluate_window(problems: list[Problem], views: Views, pairs: list[PairFlow | None], X: Tensor
                    ) -> WindowEvaluation:
    """Evaluate W frames' problems at X (W, B, 4, 4) and the coupled L_flow between consecutive frames.

    problems[i]: frame i's problem (render windows allowed; L_flow's state None for i > 0, the coupled term
    replaces it); views: the whole-image views; pairs[i] (i > 0): the targets between frames i-1 and i."""
    rig = problems[0].rig
    frames, uvs, pair = [], [], [0.0]
    for i, pb in enumerate(problems):
        ev = evaluate(pb, lbs(rig.rest, rig.weights, X[i]))
        frames.append(ev)
        uvs.append(raster.project_vertices(ev.verts, views.K, views.world_to_cam)[0])
    loss = sum(ev.loss for ev in frames)
    for i in range(1, len(problems)):
        p = pairs[i]
        if p is None:
            pair.append(0.0)
            continue
        d = uvs[i][p.cam, p.vert] - uvs[i - 1][p.cam, p.vert] - p.flow
        pair.append(float((d * d).sum()) / problems[i].n_px)
        loss += problems[i].cfg.weights.flow * pair[-1]
    return WindowEvaluation(float(loss), frames, uvs, pair)


def window_system(problems: list[Problem], views: Views, pairs: list[PairFlow | None], wev: WindowEvaluation,
                  X: Tensor, jdtype=torch.float64) -> tuple[Tensor, Tensor]:
    """H (W P, W P) and g (W P,) of the window at ``wev`` (L(d) ~ L + 2 g.d + d.H d), P = 6 B.

    Block diagonal: each frame's :func:`anidress_core.fit.objective.gauss_newton_system`; the coupled
    L_flow adds to the blocks (i-1, i-1), (i, i) and the off-diagonal (i-1, i), (i, i-1)."""
    rig = problems[0].rig
    Wn = len(problems)
    P = 6 * rig.weights.shape[1]
    dev = X.device
    H = torch.zeros(Wn * P, Wn * P, dtype=torch.float64, device=dev)
    g = torch.zeros(Wn * P, dtype=torch.float64, device=dev)
    J3 = []
    for i, (pb, ev) in enumerate(zip(problems, wev.frames)):
        J3.append(skin_jacobian(rig, X[i]).to(jdtype))  # (V, 3, P)
        Hi, gi = gauss_newton_system(pb, ev, X[i], jdtype, skin=J3[-1])
        sl = slice(i * P, (i + 1) * P)
        H[sl, sl] += Hi
        g[sl] += gi
    @functools.cache
    def proj_jacobian(i: int) -> Tensor:  # (C, V, 2, 3) d uv / d x of frame i in the whole-image views
        return projection_jacobian(wev.frames[i].verts, views)[1]

    for i in range(1, Wn):
        p = pairs[i]
        w = problems[i].cfg.weights.flow / problems[i].n_px
        if p is None or not w > 0:
            continue
        # per target n: r_n = uv_i - uv_{i-1} - f_n depends on one vertex at two frames; summed per vertex
        # (3 x 3 blocks over the U vertices with a target), then chained with the skinning Jacobians once
        used, slot = torch.unique(p.vert, return_inverse=True)
        U = used.numel()
        Pa, Pb = proj_jacobian(i - 1)[p.cam, p.vert], proj_jacobian(i)[p.cam, p.vert]  # (N, 2, 3)
        r = wev.uv[i][p.cam, p.vert] - wev.uv[i - 1][p.cam, p.vert] - p.flow  # (N, 2)

        def per_vertex(x: Tensor) -> Tensor:
            return torch.zeros(U, *x.shape[1:], dtype=x.dtype, device=dev).index_add_(0, slot, x)

        Maa = per_vertex(Pa.transpose(1, 2) @ Pa)  # (U, 3, 3)
        Mbb = per_vertex(Pb.transpose(1, 2) @ Pb)
        Mab = -per_vertex(Pa.transpose(1, 2) @ Pb)
        ga = -per_vertex(torch.einsum("nij,ni->nj", Pa, r))  # (U, 3)
        gb = per_vertex(torch.einsum("nij,ni->nj", Pb, r))
        Ja, Jb = J3[i - 1][used], J3[i][used]  # (U, 3, P)
        Ja2, Jb2 = Ja.reshape(3 * U, P), Jb.reshape(3 * U, P)
        a, b = slice(i * P, (i + 1) * P), slice((i - 1) * P, i * P)
        H[a, a] += w * (Jb2.t() @ (Mbb.to(jdtype) @ Jb).reshape(3 * U, P)).double()
        H[b, b] += w * (Ja2.t() @ (Maa.to(jdtype) @ Ja).reshape(3 * U, P)).double()
        Hab = w * (Ja2.t() @ (Mab.to(jdtype) @ Jb).reshape(3 * U, P)).double()  # rows: frame i-1
        H[b, a] += Hab
        H[a, b] += Hab.t()
        g[a] += w * (Jb2.t() @ gb.reshape(-1).to(jdtype)).double()
        g[b] += w * (Ja2.t() @ ga.reshape(-1).to(jdtype)).double()
    return H, g


def refine_window(fits: list, pairs: list[PairFlow | None], views: Views, max_iters: int,
                  log: logging.Logger = logging.getLogger("anidress.fit")) -> list:
    """Refine W chained frames jointly (module docstring) from their chained poses.

    fits: the chain's :class:`anidress_core.fit.FrameFit` of the W frames with their problems and render windows
    (``problem``, ``crop``; L_flow's state is dropped for i > 0); pairs[i]: :func:`pair_flow` of frame i's chained
    targets (pairs[0] unused). Returns the W results refined (the coupled L_flow as each frame's
    ``terms['flow']``, ``loss`` its own total with it, the refinement's time shared out over ``terms['wall_s']``;
    ``iterations`` stay the chain's), the record ``{'frames', 'loss', 'chain_loss', 'iterations'}`` in the last
    frame's ``notes['window']``, their problems dropped. Unchanged when fewer than two frames, or when a frame was
    not optimised (no mask)."""
    if len(fits) < 2 or any(f.problem is None or f.notes.get("no_mask") for f in fits):
        return [dataclasses.replace(f, problem=None, crop=None) for f in fits]
    t0 = time.perf_counter()
    cfg, rig = fits[0].problem.cfg, fits[0].problem.rig
    pbs = [f.problem if i == 0 else f.problem._replace(states={**f.problem.states, "flow": None})
           for i, f in enumerate(fits)]
    X0 = torch.stack([f.transforms.double() for f in fits])

    def update(X: Tensor, delta: Tensor) -> Tensor:
        d = delta.view(len(pbs), -1, 6)
        return torch.stack([apply_increment(X[i], rig.centres, d[i]) for i in range(len(pbs))])

    res = levenberg_marquardt(lambda X: evaluate_window(pbs, views, pairs, X),
                              lambda wev, X: window_system(pbs, views, pairs, wev, X, JACOBIAN_DTYPE),
                              update, X0, max_iters, cfg.damping, cfg.rel_tol, cfg.step_tol)
    wev: WindowEvaluation = res.evaluation
    rec = {"frames": len(fits), "loss": wev.loss, "chain_loss": res.curve[0], "iterations": res.iterations}
    log.info("fit: window of %d frames refined jointly: loss %.6g -> %.6g (%d evaluations)", len(fits),
             rec["chain_loss"], rec["loss"], rec["iterations"])
    share = (time.perf_counter() - t0) / len(fits)
    out = []
    for i, (f, ev) in enumerate(zip(fits, wev.frames)):
        terms = dict(ev.terms)
        if i > 0:
            terms["flow"] = wev.pair[i]
        frags = ev.fragments if f.crop is None else uncrop_fragments(ev.fragments, f.crop, views.height, views.width)
        out.append(dataclasses.replace(f, transforms=res.x[i].clone(), verts=ev.verts, fragments=frags,
                                       terms={**f.terms, **terms, "wall_s": f.terms.get("wall_s", 0.0) + share},
                                       loss=total_loss(cfg.weights, terms), problem=None, crop=None))
    out[-1].notes = {**out[-1].notes, "window": rec}
    return out
