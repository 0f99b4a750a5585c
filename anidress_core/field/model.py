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

from .deform import backward_warp
from .encoding import HashGridConfig
from .mlp import CanonicalField
from .render import composite
from .sampler import OccupancyGrid, march
from .weights import MotionWeightVolume

__all__ = ["FieldConfig", "AnimatableField", "RayBatchResult", "render_rays"]


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
    warp_iterations: int = 0
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


def render_rays(model: AnimatableField, origins: Tensor, dirs: Tensor, frame: Tensor, transforms: Tensor,
                grid: OccupancyGrid, step: float, background: Tensor, generator: torch.Generator | None = None,
                jitter: bool = False, volume: Tensor | None = None, use_occupancy: bool = True,
                cull_joints: bool = True, early_stop: float = 0.0, round_samples: int = 4) -> RayBatchResult:
    """Render rays (R, 3) of frames (R,) (indices into transforms (T, K, 4, 4) and grid).

    ``transforms``: the unified pose S of every frame, canonical -> world per joint.

    ``volume``: the decoded motion-weight volume, when the caller already has it
    (rendering many chunks of one image decodes it once). ``early_stop`` > 0 (inference
    only): samples are evaluated front to back in rounds of ``round_samples`` per ray and
    a ray stops once its transmittance falls below ``early_stop`` (what it leaves out
    weighs less than that).
    """
    R = origins.shape[0]
    # 1. samples where the posed subject can be, with their candidate joints
    s = march(origins, dirs, frame, grid, step, generator=generator, jitter=jitter, use_occupancy=use_occupancy,
              cull_joints=cull_joints)
    if volume is None:
        volume = model.weights()
    inv_transforms = torch.linalg.inv(transforms)
    iterations = model.cfg.warp_iterations

    def shade(sel: Tensor | None) -> tuple[Tensor, Tensor]:
        x, r, c = (s.x, s.ray, s.cand) if sel is None else (s.x[sel], s.ray[sel], s.cand[sel])
        # 2. observation -> canonical through the unified pose
        warp = backward_warp(x, frame[r], inv_transforms, c, volume, model.weights.box, transforms=transforms,
                             iterations=iterations)
        # 3. canonical colour and density; density gated by the foreground likelihood (HumanNeRF)
        rgb, sigma = model.canonical(warp.x_c)
        return rgb, sigma * warp.fg

    if early_stop <= 0 or torch.is_grad_enabled() or s.ray.numel() == 0:
        rgb, sigma = shade(None)
        # 4. compositing
        out = composite(sigma, rgb, s.t, step, s.ray, R, background)
        return RayBatchResult(out.rgb, out.alpha, out.depth, int(s.ray.shape[0]), s.considered)
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
    for r0 in range(0, int(rank.max()) + 1, round_samples):
        sel = ((rank >= r0) & (rank < r0 + round_samples) & alive[s.ray]).nonzero()[:, 0]
        if sel.numel() == 0:
            break
        rgb, sigma = shade(sel)
        evaluated += int(sel.numel())
        part = composite(sigma, rgb, s.t[sel], step, s.ray[sel], R, torch.zeros(3, dtype=rgb.dtype,
                                                                                 device=rgb.device), offset=tau)
        col += part.rgb  # (black background inside the rounds; the real one is added once below)
        acc += part.alpha
        dep += part.depth * part.alpha
        tau += part.optical_depth
        alive &= torch.exp(-tau) > early_stop
    rgb = col + (1 - acc)[:, None] * background.to(col.dtype).expand(R, 3)
    return RayBatchResult(rgb, acc, dep / acc.clamp_min(1e-8), evaluated, s.considered)
