"""Volume rendering of packed samples (Mildenhall et al. 2020, NeRF eq. 3).

Samples are a flat list sorted by ray then depth; each represents an interval of
length ``delta`` (the marching step: the gaps between occupied segments are empty by
construction). Per ray:

    alpha_i = 1 - exp(-sigma_i delta_i),  T_i = exp(-sum_{j<i} sigma_j delta_j),
    w_i = T_i alpha_i,  C = sum_i w_i c_i + (1 - sum_i w_i) background

and the accumulated opacity (alpha) and expected depth are kept.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["RenderResult", "composite", "composite_reference", "distortion", "distortion_reference"]


class RenderResult(NamedTuple):
    rgb: Tensor
    """(R, 3) colour composited over the background."""
    alpha: Tensor
    """(R,) accumulated opacity in [0, 1]."""
    depth: Tensor
    """(R,) expected distance along the ray of the visible surface (0 where alpha is 0),
    normalised by alpha (i.e. the depth of what is there, not blended with infinity)."""
    weights: Tensor
    """(S,) compositing weight of every sample."""
    optical_depth: Tensor
    """(R,) sum of sigma * delta over each ray's samples (not counting ``offset``)."""


def composite(sigma: Tensor, rgb: Tensor, t: Tensor, delta: float | Tensor, ray: Tensor, num_rays: int,
              background: Tensor, offset: Tensor | None = None) -> RenderResult:
    """Composite packed samples: sigma (S,), rgb (S, 3), t (S,), ray (S,) sorted -> per ray (R,).

    background (3,) colour or (R, 3) per ray. ``offset`` (R,): optical depth already in
    front of these samples (rendering in rounds with early ray termination); the
    returned rgb then holds only these samples' contribution plus the background seen
    through them. Differentiable w.r.t. sigma and rgb.
    """
    S = sigma.shape[0]
    tau = sigma * delta  # optical depth of each interval
    # 1. exclusive cumulative optical depth within each ray: global cumsum minus the
    #    cumsum at the ray's first sample
    csum = torch.cumsum(tau, 0)
    excl = csum - tau
    first = torch.ones(S, dtype=torch.bool, device=sigma.device)
    if S > 1:
        first[1:] = ray[1:] != ray[:-1]
    start_idx = torch.cummax(torch.where(first, torch.arange(S, device=sigma.device), torch.zeros_like(ray)), 0)[0]
    excl = excl - excl[start_idx]
    if offset is not None:
        excl = excl + offset[ray]
    # 2. weights w_i = T_i (1 - exp(-tau_i))
    w = torch.exp(-excl) * (1 - torch.exp(-tau))
    # 3. per-ray sums
    acc = torch.zeros(num_rays, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, w)
    col = torch.zeros(num_rays, 3, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, w[:, None] * rgb)
    dep = torch.zeros(num_rays, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, w * t)
    depth = dep / acc.clamp_min(1e-8)
    out = col + (1 - acc)[:, None] * background.to(col.dtype).expand(num_rays, 3)
    total = torch.zeros(num_rays, dtype=sigma.dtype, device=sigma.device).index_add(0, ray, tau)
    return RenderResult(out, acc, depth, w, total)


def composite_reference(sigma: Tensor, rgb: Tensor, t: Tensor, delta: float, ray: Tensor, num_rays: int,
                        background: Tensor) -> RenderResult:
    """Slow reference of :func:`composite`: a Python loop over rays and samples."""
    cols, accs, deps = [], [], []
    ws = torch.zeros_like(sigma)
    for r in range(num_rays):
        idx = (ray == r).nonzero()[:, 0]
        T, c, a, d = 1.0, torch.zeros(3, dtype=sigma.dtype), 0.0, 0.0
        for i in idx.tolist():
            al = 1 - torch.exp(-sigma[i] * delta)
            w = T * al
            ws[i] = w
            c = c + w * rgb[i]
            a = a + w
            d = d + w * t[i]
            T = T * (1 - al)
        cols.append(c + (1 - a) * background.to(sigma.dtype))
        accs.append(torch.as_tensor(a, dtype=sigma.dtype))
        deps.append(torch.as_tensor(d, dtype=sigma.dtype) / max(float(a), 1e-8))
    tot = torch.zeros(num_rays, dtype=sigma.dtype).index_add(0, ray, sigma * delta)
    return RenderResult(torch.stack(cols), torch.stack(accs), torch.stack(deps), ws, tot)


def _exclusive_in_ray(v: Tensor, ray: Tensor) -> Tensor:
    """sum_{j < i, ray_j = ray_i} v_j for packed samples sorted by ray: (S, ...) -> (S, ...)."""
    S = v.shape[0]
    c = torch.cumsum(v, 0) - v
    first = torch.ones(S, dtype=torch.bool, device=v.device)
    if S > 1:
        first[1:] = ray[1:] != ray[:-1]
    start = torch.cummax(torch.where(first, torch.arange(S, device=v.device), torch.zeros_like(ray)), 0)[0]
    return c - c[start]


def distortion(w: Tensor, t: Tensor, delta: float, ray: Tensor, num_rays: int) -> Tensor:
    """Mip-NeRF 360's distortion loss of every ray (Barron et al. 2022, eq. 15), (R,):

        sum_{i,j} w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 delta

    for packed samples sorted by ray then depth: weights w (S,), depths t (S,) (metres), intervals of
    length ``delta``. Small when a ray's weight sits in one short interval (a surface), large when it is
    spread along the ray (haze, floaters). The double sum is 2 sum_i w_i (t_i W_i - U_i) with W_i, U_i
    the sums of w_j and w_j t_j over the ray's samples before i. Differentiable w.r.t. w.
    """
    W = _exclusive_in_ray(w, ray)
    U = _exclusive_in_ray(w * t, ray)
    per = 2 * w * (t * W - U) + w * w * (delta / 3)
    return torch.zeros(num_rays, dtype=w.dtype, device=w.device).index_add(0, ray, per)


def distortion_reference(w: Tensor, t: Tensor, delta: float, ray: Tensor, num_rays: int) -> Tensor:
    """Slow reference of :func:`distortion`: the double sum, ray by ray."""
    out = []
    for r in range(num_rays):
        i = (ray == r).nonzero()[:, 0]
        wi, ti = w[i], t[i]
        out.append((wi[:, None] * wi[None] * (ti[:, None] - ti[None]).abs()).sum() + (wi * wi).sum() * delta / 3)
    return torch.stack(out) if out else w.new_zeros(0)
