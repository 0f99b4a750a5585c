"""Hash encoding: agreement with the slow reference, float64 gradients, shapes."""
import pytest
import torch

from anidress_core.field.encoding import HashGrid, HashGridConfig, hash_encode, hash_encode_reference, level_resolutions

# coarse levels dense, fine levels hashed (table of 2^8 entries per level)
CFG = HashGridConfig(levels=4, features=2, log2_size=8, base_resolution=2, max_resolution=16)


def test_level_resolutions_grow_geometrically():
    r = level_resolutions(HashGridConfig(levels=8, base_resolution=16, max_resolution=256))
    assert r[0] == 16 and r[-1] == 256 and all(a < b for a, b in zip(r, r[1:]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_reference_on_dense_and_hashed_levels(dtype):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(200, 3, generator=g, dtype=dtype)
    x[:3] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5]], dtype=dtype)  # cube corners
    table = torch.randn(2, 4 * 256, generator=g, dtype=dtype)
    assert any((r + 1) ** 3 <= 256 for r in level_resolutions(CFG))
    assert any((r + 1) ** 3 > 256 for r in level_resolutions(CFG))
    out = hash_encode(x, table, CFG)
    assert out.shape == (200, CFG.out_dim)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.allclose(out, hash_encode_reference(x, table, CFG), atol=tol)


def test_gradients_wrt_table_and_points_float64():
    # a small table (the numerical Jacobian costs one forward per entry): dense and hashed levels
    cfg = HashGridConfig(levels=3, features=2, log2_size=6, base_resolution=2, max_resolution=8)
    g = torch.Generator().manual_seed(1)
    # keep points off cell borders, where the trilinear interpolation is not differentiable
    x = (torch.rand(6, 3, generator=g, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    table = torch.randn(2, 3 * 64, generator=g, dtype=torch.float64, requires_grad=True)
    assert any((r + 1) ** 3 > 64 for r in level_resolutions(cfg))
    assert torch.autograd.gradcheck(lambda a, b: hash_encode(a, b, cfg), (x, table))


def test_module_and_shape_errors():
    m = HashGrid(CFG)
    assert m(torch.rand(5, 3)).shape == (5, 8)
    assert m(torch.zeros(0, 3)).shape == (0, 8)
    assert m.table.abs().max() <= 1e-4  # instant-ngp initialisation
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        m(torch.rand(5, 2))
    with pytest.raises(ValueError, match="table"):
        hash_encode(torch.rand(5, 3), torch.zeros(3, 10), CFG)
