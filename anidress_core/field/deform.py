"""Backward deformation: observation space -> canonical space (AniDress §3.3, eq. 2-3).

The unified pose S stacks K = 24 body joint transforms and B garment bone transforms,
all mapping the canonical (body rest) frame to the world (column vectors). A point
x_o of frame t is mapped to the canonical frame by

    x_c = sum_k w_o^k T_k^-1 x_o,     w_o^k = W_k(T_k^-1 x_o) / sum_i W_i(T_i^-1 x_o)

with W the canonical motion-weight volume (HumanNeRF's formulation): every joint
proposes its own canonical position T_k^-1 x_o, the volume says how much that joint
owns the point it proposes, and the proposals are blended. The sum of the volume
weights (before normalisation) is the foreground likelihood that gates density
(HumanNeRF multiplies alpha by it).

This blend is not the inverse of the forward skinning x_o = sum_k W_k(x_c) T_k x_c that
poses the garment: where neighbouring joints move differently (the rig's virtual bones),
the joints' proposals differ by centimetres and their blend lands off the material point,
differently in every frame (studies/field: 17 mm median on the demo skirt's posed garment
surface, 4 mm after three iterations below). With ``iterations`` n > 0 the warp solves the
forward skinning for x_c instead, by fixed-point iteration from the blend (the root SNARF,
Chen et al. ICCV 2021, finds by Broyden's method):

    w_k = W_k(x_c) / sum_{m in cand} W_m(x_c),   x_c <- (sum_k w_k T_k)^-1 x_o

with the weights of every candidate read at the same canonical point. The last iteration
carries the gradient (with respect to the volume and the transforms); the earlier ones
only place it (the one-step gradient of implicit layers). The foreground likelihood is
then sum_{m in cand} W_m at the solved point.

Joint culling (DESIGN.md §6): only the ``M`` candidate joints of a sample (from the
occupancy grid, :mod:`anidress_core.field.sampler`) are evaluated; candidate index K
means "no joint" and contributes nothing.

:func:`inverse_lbs` is the exact inverse of forward LBS for known per-point weights,
the reference the round-trip tests use.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
import warp as wp
from torch import Tensor

from . import kernels
from .weights import sample_channels

__all__ = ["WarpResult", "backward_warp", "channel_last", "forward_lbs", "inverse_lbs", "invert_affine3", "CONVERGED_M"]

CONVERGED_M = 1e-4
"""Rendering (no gradient): a fixed-point step that moves a sample less than this (metres, largest coordinate)
ends its iterations but the last; training takes every step."""


class WarpResult(NamedTuple):
    x_c: Tensor
    """(N, 3) canonical points."""
    fg: Tensor
    """(N,) foreground likelihood in [0, 1]: sum of the candidates' volume weights, clamped."""


def forward_lbs(x_c: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """x_o = sum_k w_k T_k x_c for points x_c (N, 3), weights (N, K), transforms (K | N, K, 4, 4)."""
    # A[n] = sum_k w[n, k] T[(n,) k]  (blend the 3x4 matrices, then apply once)
    A = torch.einsum("nk,...kij->nij", weights, transforms[..., :3, :]) if transforms.ndim == 3 \
        else torch.einsum("nk,nkij->nij", weights, transforms[..., :3, :])
    return (A[:, :, :3] @ x_c[..., None])[..., 0] + A[:, :, 3]


def inverse_lbs(x_o: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Exact inverse of :func:`forward_lbs`: x_c = (sum_k w_k T_k)^-1 x_o.

    x_o (N, 3), weights (N, K) the weights of the canonical point, transforms
    (K | N, K, 4, 4). The blended 3x3 part must be invertible (true for convex weights
    of rotations that are not opposite).
    """
    A = torch.einsum("nk,...kij->nij", weights, transforms[..., :3, :]) if transforms.ndim == 3 \
        else torch.einsum("nk,nkij->nij", weights, transforms[..., :3, :])
    return torch.linalg.solve(A[:, :, :3], (x_o - A[:, :, 3])[..., None])[..., 0]


def invert_affine3(A: Tensor, min_det: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Closed-form inverse of the 3x3 parts of blended transforms A (N, 3, 4).

    Returns (Rinv (N, 3, 3), ok (N,) bool). Rinv = adj(R) / det(R); where |det| < min_det
    (opposite rotations blended) ok is False and Rinv is the identity (the caller keeps
    its previous estimate there).
    """
    R = A[:, :, :3]
    c0 = torch.cross(R[:, :, 1], R[:, :, 2], dim=-1)  # rows of adj(R) are the cross products of columns
    c1 = torch.cross(R[:, :, 2], R[:, :, 0], dim=-1)
    c2 = torch.cross(R[:, :, 0], R[:, :, 1], dim=-1)
    det = (R[:, :, 0] * c0).sum(-1)
    ok = det.abs() > min_det
    safe = torch.where(ok, det, torch.ones_like(det))
    inv = torch.stack([c0, c1, c2], 1) / safe[:, None, None]
    eye = torch.eye(3, dtype=A.dtype, device=A.device).expand_as(inv)
    return torch.where(ok[:, None, None], inv, eye), ok


def _skinning_step(x_o: Tensor, x_c: Tensor, pair: Tensor, c: Tensor, fwd: Tensor, volume: Tensor, box: Tensor,
                   eps: float) -> tuple[Tensor, Tensor, Tensor]:
    """One fixed-point step x_c <- (sum_m w_m T_m)^-1 x_o with every candidate's weight read at x_c.

    pair (P,) the sample of each (sample, candidate) pair, c (P,) its joint, fwd (P, 3, 4) its
    T_c. Returns the new x_c (N, 3) (the old one where the blend is singular or empty), the
    pairs' volume weights (P,) and their sum per sample (N,).
    """
    N = x_o.shape[0]
    wq = sample_channels(volume, box, x_c[pair][:, None], c[:, None])[:, 0]  # (P,)
    s = x_o.new_zeros(N).index_add(0, pair, wq)
    wn = wq / s.clamp_min(eps)[pair]
    # A[n] = sum_m w[n, m] T_{c_m}[:3, :]
    A = x_o.new_zeros(N, 12).index_add(0, pair, wn[:, None] * fwd.reshape(-1, 12)).view(N, 3, 4)
    Rinv, ok = invert_affine3(A)
    new = (Rinv @ (x_o - A[:, :, 3])[..., None])[..., 0]
    return torch.where((ok & (s > eps))[:, None], new, x_c), wq, s


def volume_frame(volume: Tensor, box: Tensor, dt) -> tuple[tuple[int, int, int, int], Tensor, Tensor]:
    """Grid size (D, H, W, C), corner (3,) and scale (3,) of voxel coordinates u = (p - lo) * scale."""
    C, D, H, W = volume.shape
    box = box.to(device=volume.device, dtype=dt)
    scale = torch.tensor([W - 1, H - 1, D - 1], dtype=dt, device=volume.device) / (box[1] - box[0])
    return (D, H, W, C), box[0].contiguous(), scale


def channel_last(volume: Tensor, dt=None) -> Tensor:
    """The (C, D, H, W) volume as the Warp kernels read it: flat (D H W C,), channel-last, so that the
    candidates of one point read the same cache lines (differentiable). A caller that warps many batches
    with one volume converts it once and passes it to :func:`backward_warp` as ``volume_last``."""
    return volume.to(dt or volume.dtype).permute(1, 2, 3, 0).reshape(-1)


def _place_warp(x_o: Tensor, frame: Tensor | None, inv_transforms: Tensor, transforms: Tensor, cand: Tensor,
                volume: Tensor, box: Tensor, iterations: int, eps: float,
                volume_last: Tensor | None = None, final: bool = False) -> tuple[Tensor, Tensor]:
    """The blend and ``iterations`` fixed-point steps, no gradient, in one Warp kernel
    (:func:`anidress_core.field.kernels.warp_place`): x_c (N, 3) and the weights' sum s (N,)
    where the last step read them. ``final``: the last of the steps is the warp's final one (rendering),
    taken by every sample, converged or not."""
    N = x_o.shape[0]
    dev, dt = x_o.device, x_o.dtype
    out = torch.empty(N, 3, dtype=dt, device=dev)
    s = torch.empty(N, dtype=dt, device=dev)
    if N == 0:
        return out, s
    wdev, stream = kernels.device_of(x_o, "backward_warp")
    (D, H, W, C), lo, scale = volume_frame(volume, box, dt)
    fr = torch.zeros(N, dtype=torch.int32, device=dev) if frame is None else frame.to(torch.int32)
    wp.launch(kernels.warp_place, N,
              inputs=[kernels.array(x_o), kernels.array(fr), kernels.array(cand.to(torch.int16)), inv_transforms.shape[-3],
                      kernels.array(inv_transforms[..., :3, :].reshape(-1, 12).to(dt)),
                      kernels.array(transforms[..., :3, :].reshape(-1, 12).to(dt)),
                      kernels.array(channel_last(volume, dt) if volume_last is None else volume_last.to(dt)),
                      kernels.array(lo), kernels.array(scale), D, H, W, C,
                      int(iterations), float(eps), CONVERGED_M, int(final), wp.from_torch(out),
                      wp.from_torch(s)],
              device=wdev, stream=stream)
    return out, s


class StepWarp(torch.autograd.Function):
    """:func:`_skinning_step` (x_c, s) through the Warp kernel ``warp_step``, differentiable with respect to
    the flat channel-last volume (D H W C,) and the transforms' 3x4 table (T K, 12)."""

    @staticmethod
    def forward(ctx, vol_flat: Tensor, table: Tensor, x_o: Tensor, x_bar: Tensor, frame: Tensor, cand: Tensor,
                K: int, lo: Tensor, scale: Tensor, dhw: tuple[int, int, int], eps: float):
        wdev, stream = kernels.device_of(x_o, "backward_warp")
        N = x_o.shape[0]
        x_c = x_o.new_empty(N, 3)
        s = x_o.new_empty(N)
        dummy2, dummy1 = x_o.new_zeros(1, 12), x_o.new_zeros(1)
        wp.launch(kernels.warp_step, N,
                  inputs=[kernels.array(x_o), kernels.array(x_bar), kernels.array(frame), kernels.array(cand), K, kernels.array(table), kernels.array(vol_flat), kernels.array(lo),
                          kernels.array(scale), *dhw, float(eps), 0, kernels.array(x_o.new_zeros(1, 3)), kernels.array(dummy1), 0,
                          wp.from_torch(x_c), wp.from_torch(s), kernels.array(dummy1), kernels.array(dummy2)],
                  device=wdev, stream=stream)
        ctx.save_for_backward(vol_flat, table, x_o, x_bar, frame, cand, lo, scale)
        ctx.K, ctx.dhw, ctx.eps = K, dhw, eps
        return x_c, s

    @staticmethod
    def backward(ctx, g_xc: Tensor, g_s: Tensor):
        vol_flat, table, x_o, x_bar, frame, cand, lo, scale = ctx.saved_tensors
        wdev, stream = kernels.device_of(x_o, "backward_warp")
        want_t = bool(ctx.needs_input_grad[1])
        grad_vol = torch.zeros_like(vol_flat)
        grad_t = torch.zeros_like(table) if want_t else table.new_zeros(1, 12)
        g_xc = torch.zeros_like(x_o) if g_xc is None else g_xc
        g_s = x_o.new_zeros(x_o.shape[0]) if g_s is None else g_s
        wp.launch(kernels.warp_step, x_o.shape[0],
                  inputs=[kernels.array(x_o), kernels.array(x_bar), kernels.array(frame), kernels.array(cand), ctx.K, kernels.array(table), kernels.array(vol_flat),
                          kernels.array(lo), kernels.array(scale), *ctx.dhw, float(ctx.eps), 1, kernels.array(g_xc), kernels.array(g_s), int(want_t),
                          kernels.array(x_o.new_zeros(1, 3)), kernels.array(x_o.new_zeros(1)), wp.from_torch(grad_vol),
                          wp.from_torch(grad_t)],
                  device=wdev, stream=stream)
        return grad_vol, (grad_t if want_t else None), None, None, None, None, None, None, None, None, None


def backward_warp(x_o: Tensor, frame: Tensor | None, inv_transforms: Tensor, cand: Tensor, volume: Tensor,
                  box: Tensor, eps: float = 1e-4, transforms: Tensor | None = None,
                  iterations: int = 0, backend: str = "warp", volume_last: Tensor | None = None) -> WarpResult:
    """Backward warp of observation points over candidate joints (module docstring).

    x_o (N, 3) world points; frame (N,) long index of each point's frame into
    inv_transforms (T, K, 4, 4), or None with inv_transforms (K, 4, 4) for one frame:
    T_k^-1 (world -> canonical per joint); cand (N, M) integer in [0, K] (K = no joint);
    volume (K + 1, D, H, W) motion weights over ``box`` (2, 3).
    ``iterations`` 0: HumanNeRF's blend of the joints' proposals; n > 0: n fixed-point
    iterations of the inverse of forward skinning from the blend, which need ``transforms``
    (T, K, 4, 4) | (K, 4, 4), the inverses of ``inv_transforms``. ``backend``: where the
    blend and the first n - 1 iterations (no gradient) run, ``"warp"`` (one kernel) or
    ``"torch"`` (the reference); the last iteration is torch either way. ``volume_last``: the volume as
    :func:`channel_last` gives it, when the caller has it (rendering: converted once per image).
    """
    K = inv_transforms.shape[-3]
    N = cand.shape[0]
    if iterations > 0:
        if transforms is None:
            raise ValueError("backward_warp: iterations > 0 needs the forward transforms")
        if backend not in ("warp", "torch"):
            raise ValueError(f"backward_warp: backend must be 'warp' or 'torch', got {backend!r}")
        needs_grad = torch.is_grad_enabled() and (volume.requires_grad or transforms.requires_grad)
        if backend == "warp" and not needs_grad:
            # rendering: every step in one kernel
            x_c, s = _place_warp(x_o, frame, inv_transforms, transforms, cand, volume, box, iterations, eps,
                                 volume_last, final=True)
            return WarpResult(x_c=x_c, fg=s.clamp(max=1.0))
    # 0. only (sample, candidate) pairs naming a joint are evaluated (packed)
    n_idx, m_idx = (cand < K).nonzero(as_tuple=True)
    c = cand[n_idx, m_idx].long()
    row = c if frame is None else frame[n_idx] * K + c
    if iterations > 0:
        fwd = transforms[..., :3, :].reshape(-1, 12)[row].view(-1, 3, 4)  # (P, 3, 4)
        # 1. place x_c: the blend, then n - 1 fixed-point steps, without gradient
        with torch.no_grad():
            if backend == "warp":
                x_c = _place_warp(x_o, frame, inv_transforms, transforms, cand, volume, box, iterations - 1, eps,
                                  volume_last)[0]
            else:
                x_c = backward_warp(x_o, frame, inv_transforms, cand, volume, box, eps).x_c
                active = torch.ones(N, dtype=torch.bool, device=x_o.device)
                for _ in range(iterations - 1):
                    new = _skinning_step(x_o, x_c, n_idx, c, fwd, volume, box, eps)[0]
                    moved = (new - x_c).abs().amax(-1)
                    x_c = torch.where(active[:, None], new, x_c)
                    if not needs_grad:  # rendering: converged (or singular) samples stay until the last step
                        active &= moved >= CONVERGED_M
        # 2. the last step carries the gradient (volume weights at x_c, transforms)
        if backend == "warp":
            dhw, lo, scale = volume_frame(volume, box, x_o.dtype)
            fr = torch.zeros(N, dtype=torch.int32, device=x_o.device) if frame is None else frame.to(torch.int32)
            vl = channel_last(volume, x_o.dtype) if volume_last is None else volume_last
            x_c, s = StepWarp.apply(vl, transforms[..., :3, :].reshape(-1, 12), x_o.detach(), x_c,
                                     fr, cand.to(torch.int16), K, lo, scale, dhw, eps)
        else:
            x_c, _, s = _skinning_step(x_o, x_c, n_idx, c, fwd, volume, box, eps)
        return WarpResult(x_c=x_c, fg=s.clamp(max=1.0))
    # 1. per-pair canonical proposals p = T_c^-1 x_o, from a contiguous (T * K, 12) table
    #    of the 3x4 parts
    table = inv_transforms[..., :3, :].reshape(-1, 12)
    A = table[row].view(-1, 3, 4)  # (P, 3, 4)
    xo = x_o[n_idx]
    # p[q, i] = sum_j A[q, i, j] x[q, j] + A[q, i, 3]
    p = (A[:, :, :3] * xo[:, None, :]).sum(-1) + A[:, :, 3]  # (P, 3)
    # 2. volume weight of each candidate at its own proposal
    wq = sample_channels(volume, box, p[:, None], c[:, None])[:, 0]  # (P,)
    # 3. blend: x_c = sum_m w p / sum_m w ; foreground likelihood = sum_m w
    s = x_o.new_zeros(N).index_add(0, n_idx, wq)
    num = x_o.new_zeros(N, 3).index_add(0, n_idx, wq[:, None] * p)
    x_c = num / s.clamp_min(eps)[:, None]
    return WarpResult(x_c=x_c, fg=s.clamp(max=1.0))
