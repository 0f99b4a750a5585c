"""Training: a tiny scene overfits (PSNR rises over 150 steps); resuming from a checkpoint equals an uninterrupted run."""
import copy
import dataclasses
import functools

import pytest
import torch

from anidress_core.field.train import TrainConfig, render_view, train_field
from anidress_core.metrics.image import psnr

from .tiny_scene import new_model, tiny_scene


def _new_model(box, prior, seed: int = 0, iterations: int = 0):
    m = new_model(box, prior, seed=seed)
    m.cfg = dataclasses.replace(m.cfg, warp_iterations=iterations)
    return m


@pytest.fixture(scope="module")
def scene(small_body):
    torch.set_num_threads(1)
    return tiny_scene(small_body)


def _train_psnr(model, data) -> float:
    """Mean PSNR inside the ray boxes of all training images (black background)."""
    vals = []
    bg = torch.zeros(3)
    vol = model.weights()
    for t in range(data.images.shape[0]):
        for c in range(data.images.shape[1]):
            b = data.boxes[t, c]
            r = render_view(model, data.ray_origins[c], data.ray_dirs[c], b, t, data.transforms, data.grid,
                            0.01, bg, volume=vol)
            gt = torch.where(data.masks[t, c, ..., None], data.images[t, c].float() / 255, bg)
            m = torch.zeros_like(data.masks[t, c])
            m[b[0]:b[1], b[2]:b[3]] = True
            vals.append(psnr(r.rgb, gt, m))
    return sum(vals) / len(vals)


@pytest.fixture(scope="module")
def trained(scene):
    """The tiny scene trained for 150 steps (shared by the tests that need a trained field)."""
    data, box, prior = scene
    model = new_model(box, prior)
    before = _train_psnr(model, data)
    cfg = TrainConfig(steps=150, rays_per_step=256, images_per_step=4, step_m=0.01, checkpoint_every=0)
    res = train_field(model, data, cfg, progress=False, log_every=50)
    return model, before, _train_psnr(model, data), res


def test_tiny_scene_overfits(trained):
    model, before, after, res = trained
    assert after > before + 6 and after > 22, (before, after)
    assert res.history[-1]["psnr_db"] > res.history[0]["psnr_db"]
    assert 0 < res.history[-1]["samples_per_ray"] < res.history[-1]["considered_per_ray"]


@pytest.mark.parametrize("weights_every,iterations", [(1, 0), (3, 3)])
def test_resume_from_checkpoint_equals_uninterrupted_run(scene, weights_every, iterations):
    """Also with the weight volume decoded every 3rd step (the checkpoint at step 16 falls inside a block:
    the volume's gathered gradient is part of the state) and the fixed-point warp."""
    data, box, prior = scene
    cfg = TrainConfig(steps=24, rays_per_step=128, images_per_step=2, step_m=0.015, checkpoint_every=8,
                      weights_every=weights_every)
    new_model = functools.partial(_new_model, iterations=iterations)
    full = new_model(box, prior)
    train_field(full, data, cfg, progress=False)

    class Stop(Exception):
        pass

    saved = {}

    def ckpt(state):
        saved["state"] = copy.deepcopy(state)
        if state["step"] == 16:
            raise Stop

    part = new_model(box, prior)
    with pytest.raises(Stop):
        train_field(part, data, cfg, checkpoint=ckpt, progress=False)
    # a new process would start from a freshly built model and the saved state
    resumed = new_model(box, prior, seed=123)
    train_field(resumed, data, cfg, state=saved["state"], progress=False)
    a, b = full.state_dict(), resumed.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    if weights_every > 1:
        assert saved["state"]["volume_grad"] is not None


def test_early_termination_and_projected_occupancy_change_nothing_visible(scene, trained):
    """Rendering shortcuts: rays stop below transmittance 1e-3, rays only through pixels
    that see occupied voxels, samples in canonical cells without density are not shaded --
    the image equals the exhaustive one within 2e-3."""
    from anidress_core.field.model import canonical_occupancy

    from anidress_core.camera import ring_cameras
    from anidress_core.camera import project
    from anidress_core.field.sampler import occupancy_pixels, occupied_centres

    data = scene[0]
    model = trained[0]
    H, W = data.images.shape[2:4]
    cams = ring_cameras(4, 3.0, 1.0, (0.0, 0.0, 0.9), focal_px=H * 1.2, image_height=H, image_width=W)
    pr = project(occupied_centres(data.grid, 1), cams)
    radius = 1.2 * H * 0.5 * data.grid.voxel[1].norm() / pr.depth.min(1).values
    pix = occupancy_pixels(pr.uv, pr.depth, radius.ceil(), H, W)
    full_box = torch.tensor([0, H, 0, W])
    vol = model.weights()
    skip = canonical_occupancy(model, 32, 0.05)
    for c in range(4):
        ref = render_view(model, data.ray_origins[c], data.ray_dirs[c], full_box, 1, data.transforms, data.grid,
                          0.01, torch.zeros(3), early_stop=0.0, volume=vol)
        fast = render_view(model, data.ray_origins[c], data.ray_dirs[c], full_box, 1, data.transforms, data.grid,
                           0.01, torch.zeros(3), early_stop=1e-3, pixels=pix[c], volume=vol)
        assert fast.num_samples < ref.num_samples and fast.rays < ref.rays
        assert (fast.rgb - ref.rgb).abs().max() < 2e-3 and (fast.alpha - ref.alpha).abs().max() < 2e-3
        assert not pix[c].all() and (ref.alpha[~pix[c]] == 0).all()
        sk = render_view(model, data.ray_origins[c], data.ray_dirs[c], full_box, 1, data.transforms, data.grid,
                         0.01, torch.zeros(3), early_stop=1e-3, pixels=pix[c], volume=vol, skip=skip)
        assert (sk.rgb - ref.rgb).abs().max() < 2e-3 and (sk.alpha - ref.alpha).abs().max() < 2e-3
    # a field that is empty everywhere at the threshold is skipped everywhere: background only
    none = canonical_occupancy(model, 16, 1e12)
    assert not none.occupied.any()
    r = render_view(model, data.ray_origins[0], data.ray_dirs[0], full_box, 1, data.transforms, data.grid, 0.01,
                    torch.zeros(3), early_stop=1e-3, volume=vol, skip=none)
    assert (r.alpha == 0).all()


def test_distortion_loss_trains_and_stays_finite(scene):
    data, box, prior = scene
    model = new_model(box, prior)
    cfg = TrainConfig(steps=6, rays_per_step=128, images_per_step=2, step_m=0.015, checkpoint_every=0,
                      distortion_weight=0.01)
    res = train_field(model, data, cfg, progress=False, log_every=2)
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in res.history)
    assert all(torch.isfinite(p).all() for p in model.parameters())
