"""Volume rendering of packed samples against a per-ray loop; alpha and depth."""
import torch

from anidress_core.field.render import composite, composite_reference


def _samples(g, R=5, dtype=torch.float64):
    counts = torch.tensor([0, 3, 1, 7, 4])[:R]
    ray = torch.repeat_interleave(torch.arange(R), counts)
    t = torch.cat([torch.sort(torch.rand(int(c), generator=g, dtype=dtype)).values for c in counts])
    sigma = torch.rand(ray.shape[0], generator=g, dtype=dtype) * 50
    rgb = torch.rand(ray.shape[0], 3, generator=g, dtype=dtype)
    return sigma, rgb, t, ray


def test_matches_loop_reference():
    g = torch.Generator().manual_seed(0)
    sigma, rgb, t, ray = _samples(g)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    a = composite(sigma, rgb, t, 0.02, ray, 5, bg)
    b = composite_reference(sigma, rgb, t, 0.02, ray, 5, bg)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-12)
    # a ray without samples shows the background, alpha 0
    assert torch.allclose(a.rgb[0], bg) and a.alpha[0] == 0


def test_opaque_sample_hides_what_is_behind_and_gives_its_depth():
    sigma = torch.tensor([1e6, 1e6], dtype=torch.float64)
    rgb = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)
    t = torch.tensor([2.0, 3.0], dtype=torch.float64)
    out = composite(sigma, rgb, t, 0.01, torch.tensor([0, 0]), 1, torch.zeros(3, dtype=torch.float64))
    assert torch.allclose(out.rgb[0], rgb[0]) and torch.allclose(out.alpha, torch.ones(1, dtype=torch.float64))
    assert torch.allclose(out.depth, torch.tensor([2.0], dtype=torch.float64))


def test_gradients_float64():
    g = torch.Generator().manual_seed(2)
    sigma, rgb, t, ray = _samples(g)
    sigma.requires_grad_()
    rgb.requires_grad_()
    bg = torch.rand(5, 3, generator=g, dtype=torch.float64)  # per-ray background
    f = lambda s, c: composite(s, c, t, 0.05, ray, 5, bg)[:2]  # noqa: E731
    assert torch.autograd.gradcheck(f, (sigma, rgb))


def test_distortion_matches_its_double_sum_and_favours_a_surface():
    from anidress_core.field.render import distortion, distortion_reference

    g = torch.Generator().manual_seed(0)
    ray = torch.tensor([0, 0, 0, 1, 1, 3, 3, 3, 3])  # ray 2 has no samples
    t = torch.rand(9, generator=g, dtype=torch.float64).sort().values + ray.double()
    w = torch.rand(9, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.allclose(distortion(w, t, 0.02, ray, 4), distortion_reference(w, t, 0.02, ray, 4), atol=1e-12)
    assert torch.autograd.gradcheck(lambda w_: distortion(w_, t, 0.02, ray, 4), (w,))
    # the same total weight in one sample costs less than spread over three
    one = distortion(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.1, 0.2]), 0.02, torch.zeros(3, dtype=torch.long), 1)
    spread = distortion(torch.full((3,), 1 / 3), torch.tensor([0.0, 0.1, 0.2]), 0.02, torch.zeros(3, dtype=torch.long), 1)
    assert one < spread
