"""The pose-driven deformable radiance field of AniDress (§3.3): canonical field F_c +
motion-weight volume W, driven by the unified pose S = body joints (+) garment bones.

:class:`AnimatableField` holds the learnable parts; :func:`render_rays` runs the whole
chain for a batch of rays: march (occupancy, joint candidates) -> backward warp ->
canonical field -> density gated by the foreground likelihood -> compositing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from .deform import backward_warp, channel_last
from .encoding import HashGridConfig
from .mlp import CanonicalField, trunc_exp
from .render import composite, distortion
from .sampler import OccupancyGrid, march
from .weights import MotionWeightVolume

__all__ = ["FieldConfig", "AnimatableField", "RayBatchResult", "render_rays", "CanonicalOccupancy",
           "canonical_occupancy"]


@dataclass(frozen=True)
class FieldConfig:
    """Architecture of :class:`AnimatableField` (stored in the checkpoint)."""

    grid: HashGridConfig = HashGridConfig()
    """Hash encoding of the canonical field."""
    width: int = 64
    """Hidden units of the density and colour MLPs."""
    volume_res: int = 32
    """Motion-weight volume resolution (HumanNeRF: 32)."""
    latent: int = 256
    """Size of the fixed random latent the weight volume is decoded from."""
    decoder_width: int = 64
    """Channels of the 4^3 volume the decoder starts from."""
    density_bias: float = 3.0
    """Added to the log-density before the exponential: the field starts at sigma ~ e^3 / m,
    a haze that becomes opaque within a few centimetres (a start near 0 trains several
    times slower: the density has to grow through many steps of small gradients)."""
    warp_iterations: int = 3
    """Backward warp (:func:`anidress_core.field.deform.backward_warp`): 0 blends the joints'
    proposals (HumanNeRF, the paper); n > 0 solves forward skinning by n fixed-point iterations."""


class AnimatableField(nn.Module):
    """Canonical field over ``box`` (2, 3) + motion-weight volume with ``prior`` (K + 1, R, R, R)."""

    def __init__(self, box: Tensor, prior: Tensor, cfg: FieldConfig = FieldConfig(), seed: int = 0):
        super().__init__()
        self.cfg = cfg
        # initialised from the global RNG forked and seeded here: two fields built with one
        # seed are identical, and the caller's RNG state is left alone
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            self.canonical = CanonicalField(box, cfg.grid, cfg.width, density_bias=cfg.density_bias)
            self.weights = MotionWeightVolume(prior, box, cfg.latent, cfg.decoder_width)

    @property
    def num_joints(self) -> int:
        """K (joints of the unified pose; the volume has K + 1 channels)."""
        return self.weights.num_channels - 1


class CanonicalOccupancy(NamedTuple):
    """Cells of the canonical box where the trained field has density (rendering skips the others)."""

    occupied: Tensor
    """(R, R, R) bool over the box, indexed (x, y, z)."""
    box: Tensor
    """(2, 3) the canonical box."""

    def lookup(self, x_c: Tensor) -> Tensor:
        """(N,) bool: canonical points (N, 3) in an occupied cell (outside the box: False)."""
        R = self.occupied.shape[0]
        u = ((x_c - self.box[0]) / (self.box[1] - self.box[0]) * R).floor().long()
        inside = ((u >= 0) & (u < R)).all(-1)
        u = u.clamp(0, R - 1)
        return inside & self.occupied[u[:, 0], u[:, 1], u[:, 2]]


@torch.no_grad()
def canonical_occupancy(model: AnimatableField, res: int = 128, min_density: float = 0.05,
                        chunk: int = 65536) -> CanonicalOccupancy:
    """The canonical cells (res^3 over the box) whose density exceeds ``min_density`` (1/m) at any of their
    corners, grown by one cell on every side. A sample in another cell would add less than
    ``min_density * step`` to its ray's optical depth; rendering skips its hash encoding and MLPs."""
    box = model.canonical.box
    t = torch.linspace(0, 1, res + 1, device=box.device)
    occ = torch.zeros((res + 1) ** 3, dtype=torch.bool, device=box.device)
    gx, gy, gz = torch.meshgrid(t, t, t, indexing="ij")
    pts = box[0] + torch.stack([gx, gy, gz], -1).reshape(-1, 3) * (box[1] - box[0])
    for i in range(0, pts.shape[0], chunk):
        h = model.canonical.density_net(model.canonical.encoding(model.canonical.normalise(pts[i:i + chunk])))
        occ[i:i + chunk] = trunc_exp(h[:, 0] + model.canonical.density_bias) > min_density
    # a cell is occupied when one of its 8 corners is; then one cell of margin (max filter 3)
    c = occ.view(1, 1, res + 1, res + 1, res + 1).float()
    cell = torch.nn.functional.max_pool3d(c, 2, stride=1)  # (res, res, res): any of the corners
    cell = torch.nn.functional.max_pool3d(cell, 3, stride=1, padding=1)
    return CanonicalOccupancy(cell[0, 0] > 0, box)


class RayBatchResult(NamedTuple):
    rgb: Tensor
    """(R, 3)"""
    alpha: Tensor
    """(R,)"""
    depth: Tensor
    """(R,)"""
    num_samples: int
    """Samples evaluated (after the occupancy test)."""
    considered: int
    """Samples inside the grid boxes before the occupancy test."""
    distortion: Tensor | None = None
    """(R,) Mip-NeRF 360's distortion loss of every ray, when asked for (:func:`anidress_core.field.render.distortion`)."""


def render_rays(model: AnimatableField, origins: Tensor, dirs: Tensor, frame: Tensor, transforms: Tensor,
                grid: OccupancyGrid, step: float, background: Tensor, generator: torch.Generator | None = None,
                jitter: bool = False, volume: Tensor | None = None, use_occupancy: bool = True,
                cull_joints: bool = True, early_stop: float = 0.0, round_samples: int = 4,
                skip: CanonicalOccupancy | None = None, with_distortion: bool = False,
                volume_last: Tensor | None = None) -> RayBatchResult:
    """Render rays (R, 3) of frames (R,) (indices into transforms (T, K, 4, 4) and grid).

    ``transforms``: the unified pose S of every frame, canonical -> world per joint.

    ``volume``: the decoded motion-weight volume, when the caller already has it
    (rendering many chunks of one image decodes it once). ``early_stop`` > 0 (inference
    only): samples are evaluated front to back in rounds of ``round_samples`` per ray and
    a ray stops once its transmittance falls below ``early_stop`` (what it leaves out
    weighs less than that). ``skip`` (inference only): samples whose canonical point falls in an empty
    cell of this occupancy get no density and skip the canonical field. ``with_distortion`` (training, without
    early termination): also the rays' distortion loss. ``volume_last``: ``volume`` as
    :func:`anidress_core.field.deform.channel_last` gives it, when the caller renders many batches with it.
    """
    R = origins.shape[0]
    # 1. samples where the posed subject can be, with their candidate joints
    s = march(origins, dirs, frame, grid, step, generator=generator, jitter=jitter, use_occupancy=use_occupancy,
              cull_joints=cull_joints)
    if volume is None:
        volume = model.weights()
    iterations = model.cfg.warp_iterations
    # the blend differentiates through the inverses; the fixed point only places with them
    inv_transforms = torch.linalg.inv(transforms if iterations == 0 else transforms.detach())
    if volume_last is None and iterations > 0:
        volume_last = channel_last(volume)  # once for every round below

    def shade(sel: Tensor | None) -> tuple[Tensor, Tensor]:
        x, r, c = (s.x, s.ray, s.cand) if sel is None else (s.x[sel], s.ray[sel], s.cand[sel])
        # 2. observation -> canonical through the unified pose
        warp = backward_warp(x, frame[r], inv_transforms, c, volume, model.weights.box, transforms=transforms,
                             iterations=iterations, volume_last=volume_last)
        # 3. canonical colour and density; density gated by the foreground likelihood (HumanNeRF)
        if skip is None:
            rgb, sigma = model.canonical(warp.x_c)
            return rgb, sigma * warp.fg
        keep = skip.lookup(warp.x_c).nonzero()[:, 0]
        rgb = warp.x_c.new_zeros(x.shape[0], 3)
        sigma = warp.x_c.new_zeros(x.shape[0])
        rgb[keep], sigma[keep] = model.canonical(warp.x_c[keep])
        return rgb, sigma * warp.fg

    if early_stop <= 0 or torch.is_grad_enabled() or s.ray.numel() == 0:
        rgb, sigma = shade(None)
        # 4. compositing
        out = composite(sigma, rgb, s.t, step, s.ray, R, background)
        dist = distortion(out.weights, s.t, step, s.ray, R) if with_distortion else None
        return RayBatchResult(out.rgb, out.alpha, out.depth, int(s.ray.shape[0]), s.considered, dist)
    # front-to-back rounds with early termination
    S = s.ray.shape[0]
    first = torch.ones(S, dtype=torch.bool, device=s.ray.device)
    first[1:] = s.ray[1:] != s.ray[:-1]
    idx = torch.arange(S, device=s.ray.device)
    rank = idx - torch.cummax(torch.where(first, idx, torch.zeros_like(idx)), 0)[0]  # sample's index in its ray
    tau = origins.new_zeros(R)
    col = origins.new_zeros(R, 3)
    acc = origins.new_zeros(R)
    dep = origins.new_zeros(R)
    alive = torch.ones(R, dtype=torch.bool, device=origins.device)
    evaluated = 0
    todo = idx  # samples not evaluated yet, of rays still alive, in order
    r0, size = 0, round_samples
    black = torch.zeros(3, dtype=origins.dtype, device=origins.device)
    while todo.numel():
        now = rank[todo] < r0 + size
        sel, todo = todo[now], todo[~now]
        rgb, sigma = shade(sel)
        evaluated += int(sel.numel())
        part = composite(sigma, rgb, s.t[sel], step, s.ray[sel], R, black, offset=tau)
        col += part.rgb  # (black background inside the rounds; the real one is added once below)
        acc += part.alpha
        dep += part.depth * part.alpha
        tau += part.optical_depth
        alive &= torch.exp(-tau) > early_stop
        todo = todo[alive[s.ray[todo]]]
        r0 += size
    rgb = col + (1 - acc)[:, None] * background.to(col.dtype).expand(R, 3)
    return RayBatchResult(rgb, acc, dep / acc.clamp_min(1e-8), evaluated, s.considered)
