"""The axis convention of predicted normal maps (anidress_core.cues.normals)."""
from __future__ import annotations

import numpy as np
import pytest

from anidress_core.cues import normals as cn


def _facing(rng, n):
    """(n, 3) unit normals facing an OpenCV camera (z < 0), spread over the hemisphere."""
    v = rng.standard_normal((n, 3))
    v[:, 2] = -np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_candidates_are_the_24_right_handed_axis_permutations_with_the_identity_first():
    P = cn.SIGNED_PERMUTATIONS
    assert P.shape == (24, 3, 3) and np.array_equal(P[0], np.eye(3))
    assert len({p.tobytes() for p in P}) == 24
    assert np.allclose(np.einsum("mij,mkj->mik", P, P), np.eye(3))  # orthogonal
    assert np.allclose(np.linalg.det(P), 1.0)  # no mirror: OpenGL's diag(1, -1, -1) is one, a lone y flip not
    assert set(np.abs(P).sum(1).ravel()) == {1.0}


def test_scores_match_a_loop_over_the_permutations():
    rng = np.random.default_rng(0)
    ref = _facing(rng, 200)
    pred = _facing(rng, 200)
    slow = [np.mean(np.sum((pred @ M.T) * ref, 1)) for M in cn.SIGNED_PERMUTATIONS]
    assert np.allclose(cn.convention_scores(pred, ref), slow)


@pytest.mark.parametrize("axes", ["opengl", "identity", "swapped"])
def test_the_convention_of_noisy_normals_is_found(axes):
    rng = np.random.default_rng(1)
    ref = _facing(rng, 2000)
    M = {"opengl": np.diag([1.0, -1.0, -1.0]), "identity": np.eye(3),
         "swapped": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])}[axes]
    # the file holds M^T n (so that M turns it back), blurred by noise
    pred = ref @ M + 0.3 * rng.standard_normal(ref.shape)
    conv = cn.find_convention(pred, ref, np.arange(2000) // 100)
    assert np.array_equal(conv.matrix, M) and conv.score > cn.AGREEMENT and conv.consistency == 1.0
    assert conv.pixels == 2000
    assert cn.describe(np.diag([1.0, -1.0, -1.0])) == "x, -y, -z"


def test_unrelated_normals_are_a_clear_error():
    rng = np.random.default_rng(2)
    with pytest.raises(ValueError, match="no axis convention .* agrees"):
        cn.find_convention(rng.standard_normal((500, 3)), _facing(rng, 500), where="normals/")


def test_an_ambiguous_convention_is_an_error():
    # every normal facing the camera straight on, blurred by noise: x and y flips cannot be told apart
    rng = np.random.default_rng(3)
    ref = np.tile([0.0, 0.0, -1.0], (2000, 1))
    with pytest.raises(ValueError, match="ambiguous"):
        cn.find_convention(ref + 0.3 * rng.standard_normal(ref.shape), ref, np.arange(2000) // 100)


def test_a_mirrored_y_is_no_candidate_so_an_upright_body_is_not_ambiguous():
    """An upright body: y components small, so a lone y flip would cost little cosine; it is a mirror, not a
    candidate, and the right convention stands well clear of every rotation."""
    rng = np.random.default_rng(4)
    ref = _facing(rng, 3000) * np.array([1.0, 0.15, 1.0])
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    pred = ref + 0.05 * rng.standard_normal(ref.shape)
    mirrored = np.mean(np.sum((pred @ np.diag([1.0, -1, 1]).T) * ref, 1))
    s = np.sort(cn.convention_scores(pred, ref))
    assert s[-1] - mirrored < 0.1 and s[-1] - s[-2] > 0.3
    conv = cn.find_convention(pred, ref, np.arange(3000) // 100)
    assert np.array_equal(conv.matrix, np.eye(3)) and conv.consistency == 1.0
