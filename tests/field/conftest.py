"""Shared fixtures of the field tests: a small mannequin (built once into a temporary cache)."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_body(tmp_path_factory):
    """The procedural mannequin at 1,500 vertices (same joint tree and weights as the default)."""
    from anidress_core.body.model import mannequin_model

    d = tmp_path_factory.mktemp("anidress_cache_field")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ANIDRESS_CACHE", str(d))
        mannequin_model.cache_clear()
        body = mannequin_model(1.70, 1500)
    mannequin_model.cache_clear()
    return body


def bent_pose(dtype=None):
    """(1, 72) axis-angle pose bending hips, knees, shoulders, elbows and the spine (~25-60 degrees)."""
    import torch

    from anidress_core.body.kinematic import JOINT_INDEX

    p = torch.zeros(1, 24, 3)
    p[0, JOINT_INDEX["left_hip"]] = torch.tensor([-0.6, 0.0, 0.1])
    p[0, JOINT_INDEX["right_hip"]] = torch.tensor([0.4, 0.0, -0.1])
    p[0, JOINT_INDEX["left_knee"]] = torch.tensor([0.8, 0.0, 0.0])
    p[0, JOINT_INDEX["left_shoulder"]] = torch.tensor([0.0, 0.0, -0.9])
    p[0, JOINT_INDEX["right_shoulder"]] = torch.tensor([0.0, 0.3, 0.9])
    p[0, JOINT_INDEX["left_elbow"]] = torch.tensor([0.0, -1.0, 0.0])
    p[0, JOINT_INDEX["spine2"]] = torch.tensor([0.2, 0.3, 0.0])
    return p.reshape(1, 72) if dtype is None else p.reshape(1, 72).to(dtype)
