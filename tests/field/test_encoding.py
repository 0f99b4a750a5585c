"""Hash encoding: the Warp kernels and the torch path against the slow reference, float64 gradients, shapes."""
import pytest
import torch

from anidress_core.field.encoding import (HashGrid, HashGridConfig, hash_encode, hash_encode_reference, hash_encode_torch,
                                          level_resolutions)

ENCODERS = {"warp": hash_encode, "torch": hash_encode_torch}

# coarse levels dense, fine levels hashed (table of 2^8 entries per level)
CFG = HashGridConfig(levels=4, features=2, log2_size=8, base_resolution=2, max_resolution=16)


def test_level_resolutions_grow_geometrically():
    r = level_resolutions(HashGridConfig(levels=8, base_resolution=16, max_resolution=256))
    assert r[0] == 16 and r[-1] == 256 and all(a < b for a, b in zip(r, r[1:]))


@pytest.mark.parametrize("encoder", ENCODERS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_reference_on_dense_and_hashed_levels(dtype, encoder):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(200, 3, generator=g, dtype=dtype)
    x[:3] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5]], dtype=dtype)  # cube corners
    table = torch.randn(4 * 256, 2, generator=g, dtype=dtype)
    assert any((r + 1) ** 3 <= 256 for r in level_resolutions(CFG))
    assert any((r + 1) ** 3 > 256 for r in level_resolutions(CFG))
    x[3:6] = torch.tensor([[-0.2, 0.5, 0.5], [0.5, 1.3, 0.5], [2.0, -1.0, 0.2]], dtype=dtype)  # outside: clamped
    out = ENCODERS[encoder](x, table, CFG)
    assert out.shape == (200, CFG.out_dim) and out.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.allclose(out, hash_encode_reference(x, table, CFG), atol=tol)


@pytest.mark.parametrize("encoder", ENCODERS)
def test_gradients_wrt_table_and_points_float64(encoder):
    # a small table (the numerical Jacobian costs one forward per entry): dense and hashed levels
    cfg = HashGridConfig(levels=3, features=2, log2_size=6, base_resolution=2, max_resolution=8)
    g = torch.Generator().manual_seed(1)
    # keep points off cell borders, where the trilinear interpolation is not differentiable
    x = (torch.rand(6, 3, generator=g, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table = torch.randn(3 * 64, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert any((r + 1) ** 3 > 64 for r in level_resolutions(cfg))
    assert torch.autograd.gradcheck(lambda a, b: ENCODERS[encoder](a, b, cfg), (x, table))


def test_kernel_gradients_match_the_torch_path():
    """Warp's backward pass against the torch path's: many points (shared table entries, so the
    scatter-add accumulates), points outside the cube (zero gradient there), float64."""
    cfg = HashGridConfig(levels=4, features=2, log2_size=8, base_resolution=2, max_resolution=16)
    g = torch.Generator().manual_seed(2)
    x0 = torch.rand(500, 3, generator=g, dtype=torch.float64) * 1.4 - 0.2
    t0 = torch.randn(4 * 256, 2, generator=g, dtype=torch.float64)
    w = torch.randn(500, cfg.out_dim, generator=g, dtype=torch.float64)
    grads = {}
    for name, enc in ENCODERS.items():
        x, t = x0.clone().requires_grad_(), t0.clone().requires_grad_()
        (enc(x, t, cfg) * w).sum().backward()
        grads[name] = (x.grad, t.grad)
    assert torch.allclose(grads["warp"][0], grads["torch"][0], atol=1e-10)
    assert torch.allclose(grads["warp"][1], grads["torch"][1], atol=1e-10)
    outside = ((x0 < 0) | (x0 > 1))
    assert outside.any() and (grads["warp"][0][outside] == 0).all()
    # only the table (points without gradient) and an empty batch
    t = t0.clone().requires_grad_()
    (hash_encode(x0, t, cfg) * w).sum().backward()
    assert torch.allclose(t.grad, grads["torch"][1], atol=1e-10)
    e = hash_encode(torch.zeros(0, 3, dtype=torch.float64, requires_grad=True), t, cfg)
    assert e.shape == (0, cfg.out_dim)


def test_module_and_shape_errors():
    m = HashGrid(CFG)
    assert m(torch.rand(5, 3)).shape == (5, 8)
    assert m(torch.zeros(0, 3)).shape == (0, 8)
    assert m.table.abs().max() <= 1e-4  # instant-ngp initialisation
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        m(torch.rand(5, 2))
    with pytest.raises(ValueError, match="table"):
        hash_encode(torch.rand(5, 3), torch.zeros(10, 3), CFG)
