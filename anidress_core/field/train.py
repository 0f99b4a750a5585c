"""Training loop and full-image rendering of the pose-driven field (AniDress §3.3).

Loss (paper): MSE + lambda LPIPS with lambda = 0.2, LPIPS on image patches rendered
whole; without LPIPS weights the loss is the MSE alone (the caller logs it). Rays
are drawn only inside the dilated mask box of each (frame, camera) image; samples
only inside the occupancy grid; joints only where they have weight
(:mod:`anidress_core.field.sampler`).

Checkpoints: the training state (model, optimiser, scheduler, sampling RNG, step,
history) is handed to a callback every ``checkpoint_every`` steps; resuming from it
gives the same parameters as an uninterrupted run (one RNG, a torch.Generator, draws
every random number of the loop; tested). No file is opened here.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from .deform import channel_last
from .model import AnimatableField, CanonicalOccupancy, render_rays
from .refine import PoseRefiner
from .sampler import OccupancyGrid

__all__ = ["TrainConfig", "TrainData", "TrainResult", "train_field", "render_view", "ViewRender", "psnr"]


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (the ``field/train`` config section)."""

    steps: int = 600
    """Optimiser steps."""
    rays_per_step: int = 2048
    """Random rays per step, spread over ``images_per_step`` (frame, camera) images."""
    images_per_step: int = 8
    """Images the rays of one step come from."""
    step_m: float = 0.02
    """Ray-marching step (metres)."""
    lr: float = 3e-2
    """Adam learning rate of the canonical field (hash table and MLPs). instant-ngp uses
    1e-2 with ~256K samples per step; with ~25K per step on a CPU, 3e-2 converges faster
    (measured on the tiny test scene: 300 steps reach 31-33 dB vs 26 dB)."""
    lr_weights: float = 1e-3
    """Adam learning rate of the motion-weight volume decoder."""
    lr_final_ratio: float = 0.1
    """Learning rates decay exponentially to this fraction at the last step."""
    refine_garment: bool = False
    """Refine the garment bones' poses of the training frames through the image loss (variant ``full``;
    the stage builds the :class:`anidress_core.field.refine.PoseRefiner`)."""
    refine_lr: float = 1e-3
    """Adam learning rate of the pose corrections (:class:`anidress_core.field.refine.PoseRefiner`; radians
    and metres), when the caller refines poses."""
    refine_weight: float = 1.0
    """Weight of the corrections' regulariser (their mean square, rotations as the displacement at 10 cm)."""
    refine_regrid_every: int = 100
    """Steps between rebuilds of the occupancy grid from the refined poses."""
    distortion_weight: float = 0.0
    """Weight of Mip-NeRF 360's distortion loss (mean over the rays; depths in metres): pulls each ray's
    density into one short interval, a surface (0: off)."""
    weights_every: int = 4
    """Steps per decode of the motion-weight volume. In between, the last decoded volume is used and
    its gradients add up; the decoder takes one optimiser step per block with their sum (the decoder
    sees blocks of ``weights_every`` batches, the canonical field every batch)."""
    lpips_weight: float = 0.2
    """lambda of the LPIPS term (paper: 0.2); used only when LPIPS weights are loaded."""
    patch_size: int = 32
    """Side of the patches rendered for the LPIPS term."""
    patches_per_step: int = 2
    """Patches per step for the LPIPS term (in addition to the random rays)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour behind the subject when rendering (and training unless ``random_background``)."""
    random_background: bool = True
    """Train over a random background colour per image and step (HumanNeRF): with a
    fixed background, a dark subject could stay semi-transparent at no cost."""
    checkpoint_every: int = 250
    """Steps between checkpoints (0: none)."""
    seed: int = 0
    """Seeds the model initialisation and the sampling RNG."""
    use_occupancy: bool = True
    """Ablation (benchmark): False samples the whole grid box of each frame."""
    cull_joints: bool = True
    """Ablation (benchmark): False evaluates every joint for every sample."""


class TrainData(NamedTuple):
    """Everything the loop samples from (built by the stage runner)."""

    images: Tensor
    """(T, C, H, W, 3) uint8 target images (background pixels: anything, see ``masks``)."""
    masks: Tensor
    """(T, C, H, W) bool subject mask; the target outside it is the background colour."""
    boxes: Tensor
    """(T, C, 4) long ray boxes y0, y1, x0, x1 (dilated mask boxes; empty = no rays)."""
    ray_origins: Tensor
    """(C, 3) camera centres (world)."""
    ray_dirs: Tensor
    """(C, H, W, 3) unit world direction of every pixel's ray."""
    transforms: Tensor
    """(T, K, 4, 4) canonical -> world transform of every joint of every frame (the unified pose S)."""
    grid: OccupancyGrid
    """Occupancy and candidate joints of the T frames."""


@dataclass
class TrainResult:
    steps: int
    wall_s: float
    """Wall-clock seconds of the loop (over all sessions when resumed)."""
    cpu_s: float = float("nan")
    """CPU seconds of this process in the loop (all threads; over all sessions when resumed).
    On a shared machine the wall time grows with the load, this much less."""
    history: list = field(default_factory=list)
    """Per logged step: step, loss, psnr_db (of the batch), samples per ray, wall_s, cpu_s."""


def psnr(a: Tensor, b: Tensor) -> float:
    """PSNR (dB) of two images/ray colours in [0, 1]."""
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def param_groups(model: AnimatableField, cfg: TrainConfig) -> list[dict]:
    """Adam's parameter groups of the field: the hash table, the MLPs, the weight-volume decoder (their rates)."""
    return [
        {"params": [model.canonical.encoding.table], "lr": cfg.lr, "eps": 1e-15},
        {"params": list(model.canonical.density_net.parameters()) + list(model.canonical.color_net.parameters()),
         "lr": cfg.lr, "eps": 1e-15, "weight_decay": 1e-6},
        {"params": list(model.weights.parameters()), "lr": cfg.lr_weights},
    ]


def sample_batch(data: TrainData, valid: Tensor, cfg: TrainConfig, gen: torch.Generator, patches: int):
    """Random rays in the boxes of random images (+ ``patches`` whole patches).

    Returns origins (R, 3), dirs (R, 3), frame (R,), target (R, 3), background (R, 3)
    and the number of patch rays at the end of the batch (patches x P x P, row-major
    per patch).
    """
    T, C, H, W, _ = data.images.shape
    dev = data.images.device
    n_img = cfg.images_per_step
    per = max(1, cfg.rays_per_step // n_img)
    # random numbers come from the CPU generator (one stream on any device), then move
    pick = valid[torch.randint(valid.shape[0], (n_img + patches,), generator=gen).to(dev)]  # (n, 2) frame, cam
    b = data.boxes[pick[:, 0], pick[:, 1]]  # (n, 4)
    # 1. random pixels inside the boxes
    u = torch.rand(n_img, per, 2, generator=gen).to(dev)
    ys = b[:n_img, 0, None] + (u[..., 0] * (b[:n_img, 1] - b[:n_img, 0])[:, None]).long()
    xs = b[:n_img, 2, None] + (u[..., 1] * (b[:n_img, 3] - b[:n_img, 2])[:, None]).long()
    fr = pick[:n_img, 0, None].expand(n_img, per)
    cm = pick[:n_img, 1, None].expand(n_img, per)
    ys, xs, fr, cm = ys.reshape(-1), xs.reshape(-1), fr.reshape(-1), cm.reshape(-1)
    # 2. patches (LPIPS): P x P windows placed inside the box where it is large enough
    if patches:
        P = cfg.patch_size
        pb = b[n_img:]
        lo_y = pb[:, 0].clamp(max=H - P)
        lo_x = pb[:, 2].clamp(max=W - P)
        hi_y = (pb[:, 1] - P).clamp(min=0).maximum(lo_y)
        hi_x = (pb[:, 3] - P).clamp(min=0).maximum(lo_x)
        v = torch.rand(patches, 2, generator=gen).to(dev)
        y0 = lo_y + torch.minimum((v[:, 0] * (hi_y - lo_y + 1)).long(), hi_y - lo_y)
        x0 = lo_x + torch.minimum((v[:, 1] * (hi_x - lo_x + 1)).long(), hi_x - lo_x)
        dy, dx = torch.meshgrid(torch.arange(P, device=dev), torch.arange(P, device=dev), indexing="ij")
        py = (y0[:, None, None] + dy).reshape(-1)
        px = (x0[:, None, None] + dx).reshape(-1)
        pf = pick[n_img:, 0, None].expand(patches, P * P).reshape(-1)
        pc = pick[n_img:, 1, None].expand(patches, P * P).reshape(-1)
        ys, xs, fr, cm = torch.cat([ys, py]), torch.cat([xs, px]), torch.cat([fr, pf]), torch.cat([cm, pc])
    # 3. targets: the subject over the background colour of its image (random per image
    #    and step when ``random_background``)
    n_all = n_img + patches
    if cfg.random_background:
        bgs = torch.rand(n_all, 3, generator=gen).to(dev)
    else:
        bgs = torch.tensor(cfg.background, dtype=torch.float32, device=dev).expand(n_all, 3)
    per_ray = torch.cat([torch.arange(n_img, device=dev).repeat_interleave(per),
                         n_img + torch.arange(patches, device=dev).repeat_interleave(cfg.patch_size ** 2 if patches else 0)])
    bg = bgs[per_ray]
    m = data.masks[fr, cm, ys, xs][:, None]
    target = torch.where(m, data.images[fr, cm, ys, xs].float() / 255.0, bg)
    return (data.ray_origins[cm], data.ray_dirs[cm, ys, xs], fr, target, bg,
            patches * (cfg.patch_size ** 2 if patches else 0))


def train_field(model: AnimatableField, data: TrainData, cfg: TrainConfig, state: dict | None = None,
                checkpoint: Callable[[dict], None] | None = None, lpips: Callable[[Tensor, Tensor], Tensor] | None = None,
                progress: bool = True, log_every: int = 50, refiner: PoseRefiner | None = None,
                regrid: Callable[[Tensor], OccupancyGrid] | None = None) -> TrainResult:
    """Optimise ``model`` on ``data``; resume from ``state`` (a checkpoint) when given.

    lpips: None (MSE only) or a callable (B, 3, P, P) x 2 in [0, 1] -> (B,) distances.
    checkpoint: called with the training state every ``cfg.checkpoint_every`` steps.
    refiner: pose corrections optimised with the field (the unified pose is ``refiner(data.transforms)``), with
    ``regrid`` (refined unified pose (T, K, 4, 4) -> occupancy grid) called every ``cfg.refine_regrid_every``
    steps so that the sampled region follows them.
    """
    valid = ((data.boxes[..., 1] > data.boxes[..., 0]) & (data.boxes[..., 3] > data.boxes[..., 2])).nonzero()
    if valid.shape[0] == 0:
        raise ValueError("train_field: every ray box is empty (no subject in any mask)")
    # fused: one kernel over each parameter tensor; the hash table has millions of entries and the
    # per-element Adam loop was about a tenth of a CPU training step
    groups = param_groups(model, cfg)
    if refiner is not None:
        groups.append({"params": list(refiner.parameters()), "lr": cfg.refine_lr})
    opt = torch.optim.Adam(groups, betas=(0.9, 0.99), fused=True)
    grid_pose = None  # the refined pose the current grid was built from
    gamma = cfg.lr_final_ratio ** (1.0 / max(1, cfg.steps))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: gamma**k)
    gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
    history: list = []
    start, wall0, cpu0 = 0, 0.0, 0.0
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        gen.set_state(state["generator"])
        start, history, wall0 = int(state["step"]), list(state["history"]), float(state.get("wall_s", 0.0))
        cpu0 = float(state.get("cpu_s", 0.0))
        if refiner is not None:
            refiner.load_state_dict(state["refiner"])
            grid_pose = state.get("grid_pose")
            if grid_pose is not None:
                data = data._replace(grid=regrid(grid_pose.to(data.transforms)))
    patches = cfg.patches_per_step if lpips is not None else 0
    steps = range(start, cfg.steps)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.steps, initial=start, desc="train", unit="step")
    t0, c0 = time.perf_counter(), time.process_time()
    model.train()
    every = max(1, int(cfg.weights_every))
    decoded = volume = None
    for k in steps:
        if volume is None:
            # 1. the weight volume of this block: decoded once, its gradient gathered over the block
            decoded = model.weights()
            volume = decoded.detach().requires_grad_()
            if state is not None and state.get("volume_grad") is not None:  # resumed inside a block
                volume.grad = state["volume_grad"].to(volume)
                state = None
        pose = data.transforms
        if refiner is not None:
            pose = refiner(data.transforms)
            if regrid is not None and k > 0 and k % max(1, cfg.refine_regrid_every) == 0:
                grid_pose = pose.detach()
                data = data._replace(grid=regrid(grid_pose))
        o, d, fr, target, bgr, n_patch = sample_batch(data, valid, cfg, gen, patches)
        out = render_rays(model, o, d, fr, pose, data.grid, cfg.step_m, bgr, generator=gen, jitter=True,
                          volume=volume, use_occupancy=cfg.use_occupancy, cull_joints=cfg.cull_joints,
                          with_distortion=cfg.distortion_weight > 0)
        n_rand = o.shape[0] - n_patch
        loss = ((out.rgb[:n_rand] - target[:n_rand]) ** 2).mean()
        if cfg.distortion_weight > 0:
            loss = loss + cfg.distortion_weight * out.distortion.mean()
        if refiner is not None:
            loss = loss + cfg.refine_weight * refiner.regulariser()
        if n_patch:
            P = cfg.patch_size
            pr = out.rgb[n_rand:].view(patches, P, P, 3).permute(0, 3, 1, 2)
            pt = target[n_rand:].view(patches, P, P, 3).permute(0, 3, 1, 2)
            loss = loss + ((out.rgb[n_rand:] - target[n_rand:]) ** 2).mean() + cfg.lpips_weight * lpips(pr, pt).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if (k + 1) % every == 0 or k + 1 == cfg.steps:
            # 2. end of the block: the decoder's gradient from the volume's (the decoder is skipped by
            #    the optimiser at the other steps: its gradients are None there)
            if volume.grad is not None:
                decoded.backward(volume.grad)
            decoded = volume = None
        opt.step()
        sched.step()
        if (k + 1) % log_every == 0 or k + 1 == cfg.steps:
            history.append({"step": k + 1, "loss": float(loss.detach()), "psnr_db": psnr(out.rgb.detach(), target),
                            "samples_per_ray": out.num_samples / max(1, o.shape[0]),
                            "considered_per_ray": out.considered / max(1, o.shape[0]),
                            "wall_s": wall0 + time.perf_counter() - t0, "cpu_s": cpu0 + time.process_time() - c0})
            if bar is not None:
                bar.set_postfix(loss=f"{float(loss):.4f}", psnr=f"{history[-1]['psnr_db']:.1f}")
        if bar is not None:
            bar.update(1)
        if checkpoint is not None and cfg.checkpoint_every and (k + 1) % cfg.checkpoint_every == 0 \
                and k + 1 < cfg.steps:
            checkpoint({"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                        "generator": gen.get_state(), "step": k + 1, "history": history,
                        "wall_s": wall0 + time.perf_counter() - t0, "cpu_s": cpu0 + time.process_time() - c0,
                        "train_config": asdict(cfg),
                        "volume_grad": None if volume is None or volume.grad is None else volume.grad.detach().cpu(),
                        "refiner": None if refiner is None else refiner.state_dict(),
                        "grid_pose": None if grid_pose is None else grid_pose.cpu()})
    if bar is not None:
        bar.close()
    model.eval()
    return TrainResult(steps=cfg.steps, wall_s=wall0 + time.perf_counter() - t0,
                       cpu_s=cpu0 + time.process_time() - c0, history=history)


class ViewRender(NamedTuple):
    rgb: Tensor
    """(H, W, 3) in [0, 1]; background colour outside the rendered box."""
    alpha: Tensor
    """(H, W) accumulated opacity."""
    depth: Tensor
    """(H, W) expected depth along the ray (metres), 0 where nothing was hit."""
    num_samples: int
    considered: int
    rays: int


@torch.no_grad()
def render_view(model: AnimatableField, origin: Tensor, dirs: Tensor, box: Tensor, frame: int,
                transforms: Tensor, grid: OccupancyGrid, step: float, background: Tensor,
                chunk: int = 8192, volume: Tensor | None = None, use_occupancy: bool = True,
                cull_joints: bool = True, early_stop: float = 1e-3, pixels: Tensor | None = None,
                skip: CanonicalOccupancy | None = None, volume_last: Tensor | None = None) -> ViewRender:
    """Render one image: origin (3,), dirs (H, W, 3), box (4,) y0, y1, x0, x1 of the rays cast.

    ``frame`` indexes transforms (T, K, 4, 4) (the unified pose) and ``grid``. ``early_stop``: rays stop
    once their transmittance is below it (0: every sample). ``pixels`` (H, W) bool:
    cast rays only there (inside the box); elsewhere the background. ``skip``: the canonical cells
    without density (:func:`anidress_core.field.model.canonical_occupancy`), not shaded. ``volume_last``: the
    weight volume channel-last (:func:`anidress_core.field.deform.channel_last`), made once per image otherwise.
    """
    H, W, _ = dirs.shape
    dev = dirs.device
    rgb = background.to(dirs.dtype).expand(H, W, 3).clone()
    alpha = torch.zeros(H, W, dtype=dirs.dtype, device=dev)
    depth = torch.zeros(H, W, dtype=dirs.dtype, device=dev)
    y0, y1, x0, x1 = (int(v) for v in box)
    if y1 <= y0 or x1 <= x0:
        return ViewRender(rgb, alpha, depth, 0, 0, 0)
    if volume is None:
        volume = model.weights()
    if volume_last is None and model.cfg.warp_iterations > 0:
        volume_last = channel_last(volume)
    d = dirs[y0:y1, x0:x1].reshape(-1, 3)
    keep = None
    if pixels is not None:
        keep = pixels[y0:y1, x0:x1].reshape(-1).nonzero()[:, 0]
        d = d[keep]
    n = d.shape[0]
    cols, alps, deps = [], [], []
    ns = nc = 0
    for s in range(0, n, chunk):
        dd = d[s:s + chunk]
        o = origin.expand_as(dd)
        fr = torch.full((dd.shape[0],), frame, dtype=torch.long, device=dev)
        out = render_rays(model, o, dd, fr, transforms, grid, step, background, volume=volume,
                          use_occupancy=use_occupancy, cull_joints=cull_joints, early_stop=early_stop, skip=skip,
                          volume_last=volume_last)
        cols.append(out.rgb)
        alps.append(out.alpha)
        deps.append(out.depth)
        ns += out.num_samples
        nc += out.considered
    if n == 0:
        return ViewRender(rgb, alpha, depth, 0, 0, 0)
    hb, wb = y1 - y0, x1 - x0
    if keep is None:
        rgb[y0:y1, x0:x1] = torch.cat(cols).view(hb, wb, 3)
        alpha[y0:y1, x0:x1] = torch.cat(alps).view(hb, wb)
        depth[y0:y1, x0:x1] = torch.cat(deps).view(hb, wb)
    else:
        sub = rgb[y0:y1, x0:x1].reshape(-1, 3).clone()
        sub[keep] = torch.cat(cols)
        rgb[y0:y1, x0:x1] = sub.view(hb, wb, 3)
        for dst, src in ((alpha, alps), (depth, deps)):
            sub = dst[y0:y1, x0:x1].reshape(-1).clone()
            sub[keep] = torch.cat(src)
            dst[y0:y1, x0:x1] = sub.view(hb, wb)
    return ViewRender(rgb, alpha, depth, ns, nc, n)
