"""Where a training step and a rendered image of the field spend their time, part by part.

Runs in whichever ``anidress_core`` is first on the path (this checkout, or an earlier commit's worktree
put first on PYTHONPATH by :mod:`benchmarks.bench_field`), on the demo skirt's training data as rule
train_field builds it (the pipeline's masks, rig and fitted garment poses):

* the whole training step: ``train_field`` for ``--steps`` steps, CPU seconds per step after a warm-up;
* each part alone, forward and backward with the gradients it receives in a step: ray sampling and
  occupancy (no gradient); the backward warp with its joint candidates; the motion-weight volume's
  decode (per step: divided by ``field/train/weights_every`` where the code has it); the hash
  encoding; the MLPs; compositing, the loss and the optimiser step. What the whole step spends beyond
  the parts is Python and launch overhead;
* one rendered image: ``render_view`` of test cameras on training frames, CPU seconds per image;
* what the skipping saves: a step without the occupancy grid and without joint culling.

Writes one JSON (``--out``). Not a test.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _api(module, name: str):
    """``module.name``, or ``module._name`` in code from before fc817fc made these helpers public (6aee398)."""
    return getattr(module, name) if hasattr(module, name) else getattr(module, "_" + name)


def prepare(scene: str, variant: str):
    """(model, TrainData, TrainConfig, render params) as rule train_field builds them, in either code version."""
    from anidress_core.camera import pixel_rays
    from anidress_core.config import load_config
    from anidress_core.field.model import AnimatableField
    from anidress_core.field.sampler import build_occupancy, mask_boxes
    from anidress_core.field.subject import canonical_setup, posed_parts, unified_pose
    from anidress_core.field.train import TrainData
    from anidress_core.io.garment_poses import read_garment_poses
    from anidress_core.io.scene import load_body, load_sequence_motion, read_scene, scene_cameras
    from anidress_core.stages import field as SF

    import anidress_core

    cfg = load_config(Path(anidress_core.__file__).resolve().parents[1] / "config" / "config.yaml")
    params = cfg["field"]
    scene_dir, res = ROOT / "data" / scene, ROOT / "results" / scene
    info = read_scene(scene_dir)
    seq = [s["name"] for s in info["sequences"] if s["role"] == "train"][0]
    sp = _api(SF, "sampler_params")(params)
    tcfg, fcfg = SF.train_config_from_params(params), SF.field_config_from_params(params)
    motion = load_sequence_motion(scene_dir, seq, info["fps"], None)
    T = motion.poses.shape[0]
    cams = info["cameras"]["train"]
    garment = (scene_dir / "garment").is_dir()
    inp = _api(SF, "rest_inputs")(scene_dir, info, res / "template.npz" if garment else None,
                                 res / "rig.npz" if garment else None, variant, motion.shapes)
    posed = load_body(scene_dir, info).pose(motion.poses, motion.Rh, motion.Th, motion.shapes)
    G = None
    if variant == "full" and garment:
        G = torch.as_tensor(read_garment_poses(res / seq / "garment_poses.npz", T, inp.num_bones).transforms).float()
    S = unified_pose(posed.transforms.float(), G, variant)
    parts = posed_parts(inp.body, posed.vertices.float(), inp.garment, variant, posed.transforms.float(), G,
                        sp["dilate_m"], sp["body_only_garment_dilate_m"])
    pr = params["priors"]
    box, prior = canonical_setup(inp.body, inp.garment, variant, fcfg.volume_res, pr["garment_sigma_m"],
                                 pr["box_pad_m"], pr["ellipsoid_scale"])
    grid = build_occupancy(parts, (sp["res"],) * 3, sp["max_joints"], sp["min_weight"])
    cameras = scene_cameras(scene_dir, seq, list(cams), info).to(dtype=torch.float32)
    imgs, labels = _api(SF, "read_views")(scene_dir / seq, cams, list(range(T)), res / seq / "masks", tcfg.background)
    Tn, C, H, W, _ = imgs.shape
    boxes = mask_boxes((labels > 0).reshape(Tn * C, H, W), sp["mask_dilate_px"]).reshape(Tn, C, 4)
    rays = pixel_rays(cameras)
    # this code's TrainData holds the unified pose (``transforms``), older code its inverse
    pose = S if "transforms" in TrainData._fields else torch.linalg.inv(S)
    data = TrainData(imgs, labels > 0, boxes, rays.origins[:, 0, 0], rays.directions, pose, grid)
    model = AnimatableField(box, prior, fcfg, seed=tcfg.seed)
    return model, data, tcfg, sp


def _cpu(fn, reps: int) -> float:
    """CPU seconds per call of fn() (after one warm-up call)."""
    fn()
    c = time.process_time()
    for _ in range(reps):
        fn()
    return (time.process_time() - c) / reps


def profile(scene: str, variant: str, steps: int, reps: int, images: int) -> dict:
    from anidress_core.field import train as TR
    from anidress_core.field.deform import backward_warp
    from anidress_core.field.render import composite
    from anidress_core.field.sampler import march

    model, data, cfg, sp = prepare(scene, variant)
    cfg = dataclasses.replace(cfg, steps=steps, checkpoint_every=0)
    # 1. the whole step (the first steps warm up kernels and allocations)
    res = TR.train_field(model, data, cfg, progress=False, log_every=5)
    h = res.history
    step_s = (h[-1]["cpu_s"] - h[1]["cpu_s"]) / (h[-1]["step"] - h[1]["step"])
    # 2. the parts, on one batch of the trained model
    valid = ((data.boxes[..., 1] > data.boxes[..., 0]) & (data.boxes[..., 3] > data.boxes[..., 2])).nonzero()
    gen = torch.Generator().manual_seed(5)
    new_code = "transforms" in TR.TrainData._fields
    pose = data.transforms if new_code else data.inv_transforms
    iters = getattr(model.cfg, "warp_iterations", 0)
    every = getattr(cfg, "weights_every", 1)

    def sample():
        o, d, fr, target, bg, _ = _api(TR, "sample_batch")(data, valid, cfg, gen, 0)
        return o, d, fr, target, bg, march(o, d, fr, data.grid, cfg.step_m, generator=gen, jitter=True)

    o, d, fr, target, bg, s = sample()
    vol0 = model.weights().detach()

    def warp():
        vol = vol0.clone().requires_grad_()
        if new_code:
            w = backward_warp(s.x, fr[s.ray], torch.linalg.inv(pose), s.cand, vol, model.weights.box, transforms=pose,
                              iterations=iters)
        else:
            w = backward_warp(s.x, fr[s.ray], pose, s.cand, vol, model.weights.box)
        (w.x_c.sum() + w.fg.sum()).backward()
        return w

    w = warp()
    xc = w.x_c.detach()

    def decode():
        model.weights().sum().backward()

    def encode():
        x = model.canonical.normalise(xc).requires_grad_()
        model.canonical.encoding(x).sum().backward()

    enc = model.canonical.encoding(model.canonical.normalise(xc)).detach()

    def mlps():
        h = model.canonical.density_net(enc)
        rgb = torch.sigmoid(model.canonical.color_net(h[:, 1:]))
        (h[:, 0].sum() + rgb.sum()).backward()

    opt = torch.optim.Adam(_api(TR, "param_groups")(model, cfg), betas=(0.9, 0.99), fused=True)
    sig = torch.rand(s.ray.shape[0], requires_grad=True)
    col = torch.rand(s.ray.shape[0], 3, requires_grad=True)

    def comp_opt():
        out = composite(sig, col, s.t, cfg.step_m, s.ray, o.shape[0], bg)
        ((out.rgb - target) ** 2).mean().backward()
        for p in model.parameters():
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        opt.step()

    parts = {"ray sampling and occupancy": _cpu(sample, reps), "joint candidates and backward warp": _cpu(warp, reps),
             "motion-weight volume decode": _cpu(decode, reps) / every, "hash encoding": _cpu(encode, reps),
             "MLPs": _cpu(mlps, reps), "compositing, loss and optimiser": _cpu(comp_opt, reps)}
    parts["Python and launch overhead"] = step_s - sum(parts.values())
    # what skipping saves (DESIGN.md section 6): the step without the occupancy grid, without joint culling
    ablations = {}
    for name, flag in (("occupancy off", {"use_occupancy": False}), ("joint culling off", {"cull_joints": False})):
        r = TR.train_field(model, data, dataclasses.replace(cfg, steps=6, **flag), progress=False, log_every=1)
        ablations[name] = (r.history[-1]["cpu_s"] - r.history[1]["cpu_s"]) / (r.history[-1]["step"] - r.history[1]["step"])
    # 3. rendering: test cameras of training frames, as rule render_novel_view (early termination)
    from anidress_core.config import load_config

    import anidress_core

    rparams = load_config(Path(anidress_core.__file__).resolve().parents[1] / "config" / "config.yaml")["field"]["render"]
    kw = {"early_stop": float(rparams.get("early_stop", 1e-3)), "chunk": int(rparams.get("chunk", 8192))}
    if "pixels" in inspect.signature(TR.render_view).parameters:
        kw["pixels"] = None
    vol = model.weights().detach()
    H, W = data.images.shape[2:4]
    times, rays, samples = [], 0, 0
    with torch.no_grad():
        for i in range(images + 1):
            t, c = (7 * i) % data.images.shape[0], i % data.images.shape[1]
            c0 = time.process_time()
            r = TR.render_view(model, data.ray_origins[c], data.ray_dirs[c], data.boxes[t, c], t, pose, data.grid,
                               cfg.step_m, torch.zeros(3), volume=vol, **kw)
            if i:
                times.append(time.process_time() - c0)
                rays += r.rays
                samples += r.num_samples
    return {"scene": scene, "variant": variant, "threads": torch.get_num_threads(), "train_cpu_s_per_step": step_s,
            "rays_per_step": cfg.rays_per_step, "samples_per_step": int(s.ray.shape[0]), "parts_cpu_s": parts,
            "render_cpu_s_per_image": sorted(times)[len(times) // 2], "render_rays": rays / len(times),
            "render_samples_per_ray": samples / max(1, rays), "warp_iterations": iters, "weights_every": every,
            "ablations_cpu_s_per_step": ablations}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="skirt")
    ap.add_argument("--variant", default="full")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=40, help="training steps timed (the first 5 are a warm-up)")
    ap.add_argument("--reps", type=int, default=10, help="repetitions of each part")
    ap.add_argument("--images", type=int, default=8, help="images rendered")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    r = profile(args.scene, args.variant, args.steps, args.reps, args.images)
    Path(args.out).write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
