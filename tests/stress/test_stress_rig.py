"""Stress tests of the rigging model (issue 8 §3): scales, precision, degenerate sequences.

Every case must give finite weights and transforms or a clear error; nothing NaN/Inf.
Run with the rest of the suite (`make test`) or alone (`make stress`).
"""
import math
import warnings

import numpy as np
import pytest
import torch

from anidress_core import geometry as g
from anidress_core import rig

from tests.test_rig import known_rig, one_thread, tube  # noqa: F401 (one_thread: autouse fixture)


def _finite(model):
    assert torch.isfinite(model.weights).all() and torch.isfinite(model.transforms).all()
    assert math.isfinite(model.rmse) and all(math.isfinite(h) for h in model.history)
    assert (model.weights >= 0).all()
    assert torch.allclose(model.weights.sum(-1), torch.ones_like(model.weights[:, 0]), atol=1e-4)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_scale_invariance(scale):
    # a scene in millimetres (x1000) or kilometres (x0.001) decomposes like one in metres:
    # the relative error is the same (SSDR works in coordinates normalised to unit size)
    rest, faces, W, M, X = known_rig(T=20)
    ref = rig.ssdr(rest, X, faces, num_bones=4, iters=40)
    m = rig.ssdr(rest * scale, X * scale, faces, num_bones=4, iters=40)
    _finite(m)
    assert m.rmse / scale == pytest.approx(ref.rmse, rel=1e-6, abs=1e-12)
    assert torch.allclose(m.weights, ref.weights, atol=1e-8)


def test_float32_and_float64_agree():
    rest, faces, W, M, X = known_rig(T=20)
    a = rig.ssdr(rest, X, faces, num_bones=4, iters=60)
    b = rig.ssdr(rest.float(), X.float(), faces, num_bones=4, iters=60)
    _finite(b)
    assert b.weights.dtype == torch.float32
    assert abs(a.rmse - b.rmse) < 1e-3  # both converge to the exact rig (RMSE ~ 1e-5 m)
    assert (a.weights - b.weights.double()).abs().max() < 1e-2


def test_collinear_vertices_and_frames():
    # every vertex on one line, moving rigidly: rotation about the line is undetermined
    line = torch.stack([torch.linspace(0, 1, 60, dtype=torch.float64), torch.zeros(60, dtype=torch.float64),
                        torch.zeros(60, dtype=torch.float64)], -1)
    gen = torch.Generator().manual_seed(0)
    R = g.axis_angle_to_matrix(torch.randn(8, 3, generator=gen, dtype=torch.float64))
    X = line @ R.transpose(-1, -2) + torch.randn(8, 1, 3, generator=gen, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = rig.ssdr(line, X, None, num_bones=5, iters=5)
    _finite(m)
    assert m.rmse < 1e-9
    # fitting transforms to collinear targets is finite too
    assert torch.isfinite(rig.fit_transforms(m, X)).all()


def test_teleporting_and_exploding_frames_stay_finite():
    # frames with huge jumps (a body teleported 1 km) and a frame collapsed to a point
    rest, faces = tube()
    gen = torch.Generator().manual_seed(2)
    X = rest.expand(6, -1, -1).clone() + 0.01 * torch.randn(6, rest.shape[0], 3, generator=gen, dtype=rest.dtype)
    X[2] += 1000.0
    X[4] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = rig.ssdr(rest, X, faces, num_bones=6, iters=10)
    _finite(m)


def test_duplicated_and_coincident_vertices():
    rest, faces, W, M, X = known_rig(T=10)
    idx = torch.arange(0, rest.shape[0], 3)
    rest2 = torch.cat([rest, rest[idx]])
    X2 = torch.cat([X, X[:, idx]], 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = rig.ssdr(rest2, X2, None, num_bones=4, iters=20)
    _finite(m)
    # a duplicated vertex gets the same weights as its original
    assert (m.weights[rest.shape[0]:] - m.weights[idx]).abs().max() < 1e-3


def test_more_bones_than_motions_and_single_frame():
    rest, faces = tube()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m1 = rig.ssdr(rest, rest[None] + 0.5, faces, num_bones=25, iters=3)  # one frame, pure translation
    _finite(m1)
    assert m1.rmse < 1e-9 and m1.num_bones == 1


def test_nan_input_is_a_clear_error():
    rest, faces, W, M, X = known_rig(T=4)
    X = X.clone()
    X[3, 10, 1] = float("inf")
    with pytest.raises(ValueError, match=r"frames contains NaN or inf \(first at index \(3, 10, 1\)\)"):
        rig.ssdr(rest, X, faces, num_bones=3, iters=2)
    model = rig.RigModel(rest=rest, weights=W, transforms=M, bone_centres=rest[:4], rmse=0.0)
    with pytest.raises(ValueError, match="verts contains NaN"):
        rig.fit_transforms(model, X)


def test_large_sequence_memory_is_linear():
    # 30K vertex-frames x 25 bones (a paper-scale block) in float32: finite and fast
    rest, faces = tube(nr=40, nh=25, dtype=torch.float32)
    gen = torch.Generator().manual_seed(3)
    T = 30
    aa = 0.3 * torch.randn(T, 3, generator=gen)
    R = g.axis_angle_to_matrix(aa)
    z = rest[:, 2:3]
    X = torch.where(z > 0.75, rest @ R.transpose(-1, -2)[:, None].squeeze(1), rest.expand(T, -1, -1))
    m = rig.ssdr(rest, X, faces, num_bones=25, iters=5)
    _finite(m)
    assert np.isfinite(m.rmse)
