import math

import pytest
import torch

from anidress_core import geometry as g


def _random_aa(n, dtype=torch.float64, max_angle=3.0):
    axis = torch.nn.functional.normalize(torch.randn(n, 3, dtype=dtype), dim=-1)
    angle = torch.rand(n, 1, dtype=dtype) * max_angle
    return axis * angle


def _rodrigues_reference(aa):
    """Slow reference: matrix exponential of the skew matrix."""
    return torch.linalg.matrix_exp(g.skew(aa))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_axis_angle_matches_matrix_exp(dtype):
    aa = _random_aa(64, dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(g.axis_angle_to_matrix(aa), _rodrigues_reference(aa), atol=tol)


def test_axis_angle_round_trip_and_small_angles():
    aa = torch.cat([_random_aa(64), torch.zeros(1, 3, dtype=torch.float64), 1e-9 * torch.ones(1, 3, dtype=torch.float64)])
    back = g.matrix_to_axis_angle(g.axis_angle_to_matrix(aa))
    assert torch.allclose(back, aa, atol=1e-9)


def test_axis_angle_gradcheck_including_zero():
    aa = torch.cat([_random_aa(4), torch.zeros(1, 3, dtype=torch.float64)]).requires_grad_()
    assert torch.autograd.gradcheck(g.axis_angle_to_matrix, (aa,))


def test_quaternion_and_6d_round_trips():
    R = g.axis_angle_to_matrix(_random_aa(128, max_angle=math.pi))
    assert torch.allclose(g.quaternion_to_matrix(g.matrix_to_quaternion(R)), R, atol=1e-12)
    assert torch.allclose(g.rotation_6d_to_matrix(g.matrix_to_rotation_6d(R)), R, atol=1e-12)
    # 180-degree rotations are the hard case for quaternion extraction
    Rpi = g.axis_angle_to_matrix(torch.tensor([[math.pi, 0, 0], [0, math.pi, 0], [0, 0, math.pi]], dtype=torch.float64))
    assert torch.allclose(g.quaternion_to_matrix(g.matrix_to_quaternion(Rpi)), Rpi, atol=1e-12)


def test_transforms_and_lbs():
    R = g.axis_angle_to_matrix(_random_aa(3))
    t = torch.randn(3, 3, dtype=torch.float64)
    M = g.make_transform(R, t)
    x = torch.randn(10, 3, dtype=torch.float64)
    assert torch.allclose(g.transform_points(g.invert_transform(M), g.transform_points(M, x)), x.expand(3, 10, 3))
    # LBS with one-hot weights equals the rigid transform of each bone
    w = torch.zeros(10, 3, dtype=torch.float64)
    w[torch.arange(10), torch.arange(10) % 3] = 1
    out = g.lbs(x, w, M[None])  # (1, 10, 3)
    ref = torch.stack([g.transform_points(M[i % 3], x[i : i + 1])[0] for i in range(10)])
    assert torch.allclose(out[0], ref)
    with pytest.raises(ValueError, match="weights"):
        g.lbs(x, w[:, :2], M)


def test_normals_and_laplacian():
    # unit cube-ish tetrahedron: normals point outwards
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    f = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    vn = g.vertex_normals(v, f)
    centroid = v.mean(0)
    assert ((vn * (v - centroid)).sum(-1) > 0).all()
    L = g.uniform_laplacian(f, 4, dtype=torch.float64).to_dense()
    assert torch.allclose(L.sum(1), torch.zeros(4, dtype=torch.float64))
    assert g.edges_of_faces(f).shape == (6, 2)


def test_nearest_rotation_is_the_kabsch_rotation():
    gen = torch.Generator().manual_seed(3)
    R = g.axis_angle_to_matrix(torch.randn(50, 3, generator=gen, dtype=torch.float64))
    torch.testing.assert_close(g.nearest_rotation(R), R, rtol=0, atol=1e-14)  # a rotation is kept
    noisy = R + 1e-4 * torch.randn(50, 3, 3, generator=gen, dtype=torch.float64)
    Q = g.nearest_rotation(noisy)
    eye = torch.eye(3, dtype=torch.float64)
    assert float((Q @ Q.transpose(-1, -2) - eye).abs().max()) < 1e-13
    assert float((torch.linalg.det(Q) - 1).abs().max()) < 1e-13
    assert float((Q - R).abs().max()) < 1e-3
    # it maximises tr(Q^T H): no rotation near it does better
    H = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    Q = g.nearest_rotation(H)
    best = float((Q * H).sum())
    for _ in range(200):
        P = g.axis_angle_to_matrix(0.1 * torch.randn(3, generator=gen, dtype=torch.float64)) @ Q
        assert float((P * H).sum()) <= best + 1e-12
    # a reflection gives a proper rotation (det +1), not the reflection
    F = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert float(torch.linalg.det(g.nearest_rotation(F))) > 0.999
