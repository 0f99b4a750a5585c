"""Training: a tiny scene overfits; resuming from a checkpoint equals an uninterrupted run."""
import copy

import pytest
import torch

from anidress_core.field.train import TrainConfig, render_view, train_field
from anidress_core.metrics.image import psnr

from .tiny_scene import new_model, tiny_scene


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
            r = render_view(model, data.ray_origins[c], data.ray_dirs[c], b, t, data.inv_transforms, data.grid,
                            0.01, bg, volume=vol)
            gt = torch.where(data.masks[t, c, ..., None], data.images[t, c].float() / 255, bg)
            m = torch.zeros_like(data.masks[t, c])
            m[b[0]:b[1], b[2]:b[3]] = True
            vals.append(psnr(r.rgb, gt, m))
    return sum(vals) / len(vals)


def test_tiny_scene_overfits(scene):
    data, box, prior = scene
    model = new_model(box, prior)
    before = _train_psnr(model, data)
    cfg = TrainConfig(steps=300, rays_per_step=256, images_per_step=4, step_m=0.01, checkpoint_every=0)
    res = train_field(model, data, cfg, progress=False, log_every=50)
    after = _train_psnr(model, data)
    assert after > before + 6 and after > 22, (before, after)
    assert res.history[-1]["psnr_db"] > res.history[0]["psnr_db"]
    assert 0 < res.history[-1]["samples_per_ray"] < res.history[-1]["considered_per_ray"]


def test_resume_from_checkpoint_equals_uninterrupted_run(scene):
    data, box, prior = scene
    cfg = TrainConfig(steps=24, rays_per_step=128, images_per_step=2, step_m=0.015, checkpoint_every=8)
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
