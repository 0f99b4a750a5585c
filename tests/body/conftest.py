"""Shared fixtures: one mannequin per test session (built into a temporary cache)
and a tiny synthetic model in the SMPL file format (no real SMPL file is used)."""
from __future__ import annotations

import numpy as np
import pytest

from anidress_core.body.kinematic import SMPL_PARENTS


@pytest.fixture(scope="session")
def mannequin_cache(tmp_path_factory):
    """ANIDRESS_CACHE pointed at a fresh folder for the whole session."""
    d = tmp_path_factory.mktemp("anidress_cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ANIDRESS_CACHE", str(d))
        yield d


@pytest.fixture(scope="session")
def mannequin(mannequin_cache):
    """The default mannequin BodyModel (built once, written to the session cache)."""
    from anidress_core.body.model import mannequin_model

    mannequin_model.cache_clear()
    return mannequin_model()


def make_tiny_smpl(num_vertices: int = 40, num_betas: int = 10, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays in the layout of an SMPL model file, random but well-formed.

    Vertices scatter around SMPL-like joints so the regressed joints are plausible;
    kintree_table uses 2**32 - 1 for the root's parent like the official files.
    """
    rng = np.random.default_rng(seed)
    V = num_vertices
    joints = rng.normal(scale=0.3, size=(24, 3))
    owner = np.arange(V) % 24
    v = joints[owner] + rng.normal(scale=0.05, size=(V, 3))
    f = np.stack([np.arange(V), (np.arange(V) + 1) % V, (np.arange(V) + 2) % V], 1).astype(np.uint32)
    w = rng.random((V, 24)) ** 4
    w[np.arange(V), owner] += 2.0
    w /= w.sum(1, keepdims=True)
    Jr = np.zeros((24, V))
    Jr[owner, np.arange(V)] = rng.random(V) + 0.5
    Jr /= Jr.sum(1, keepdims=True)
    kintree = np.zeros((2, 24), dtype=np.uint32)
    kintree[0] = [p if p >= 0 else 2**32 - 1 for p in SMPL_PARENTS]
    kintree[1] = np.arange(24)
    return {
        "v_template": v,
        "f": f,
        "weights": w,
        "J_regressor": Jr,
        "kintree_table": kintree,
        "shapedirs": rng.normal(scale=0.01, size=(V, 3, num_betas)),
        "posedirs": rng.normal(scale=0.01, size=(V, 3, 207)),
    }


@pytest.fixture
def tiny_smpl():
    return make_tiny_smpl()
