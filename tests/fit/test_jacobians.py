"""anidress_core.fit.jacobians: bone increments, skinning and projection Jacobians; Views."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from anidress_core import fit, raster
from anidress_core.camera import ring_cameras
from anidress_core.geometry import lbs
from tests.fit.scenes import pose, toy

torch.set_num_threads(1)


def test_views_make_camera_rotations_orthonormal_and_reject_non_rotations():
    """float32 camera files give rotations orthonormal to ~1e-7 only; the fit's normal term
    needs R^T = R^-1, so from_cameras projects them onto SO(3), and refuses a matrix that is
    not a rotation at all."""
    cams = ring_cameras(n=3, radius=2.0, height=1.0, target=(0, 0, 0.8), focal_px=50.0, image_height=48,
                        image_width=48)  # float32
    R32 = cams.world_to_cam[:, :3, :3].double()
    assert float((R32 @ R32.transpose(1, 2) - torch.eye(3)).abs().max()) > 1e-9
    v = fit.Views.from_cameras(cams)
    R = v.world_to_cam[:, :3, :3]
    assert float((R @ R.transpose(1, 2) - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-14
    assert float((R - R32).abs().max()) < 1e-6  # the nearest rotation: a round-off change
    torch.testing.assert_close(v.world_to_cam[:, :3, 3], cams.world_to_cam[:, :3, 3].double())
    R_bad = cams.R.clone()
    R_bad[1] *= 1.1
    bad = dataclasses.replace(cams, R=R_bad)
    with pytest.raises(ValueError, match="not a rotation"):
        fit.Views.from_cameras(bad)


def test_skin_and_projection_jacobians_match_autograd():
    rig, views = toy()
    g = torch.Generator().manual_seed(0)
    G = pose(rig, g, 0.3, 0.05)
    J = fit.skin_jacobian(rig, G)  # (V, 3, P)
    want = torch.autograd.functional.jacobian(
        lambda d: lbs(rig.rest, rig.weights, fit.apply_increment(G, rig.centres, d.view(-1, 6))),
        torch.zeros(rig.weights.shape[1] * 6, dtype=torch.float64))
    torch.testing.assert_close(J, want)
    x = lbs(rig.rest, rig.weights, G)
    uv, P = fit.projection_jacobian(x, views)
    uv_ref, _ = raster.project_vertices(x, views.K, views.world_to_cam)
    torch.testing.assert_close(uv, uv_ref)
    Pref = torch.autograd.functional.jacobian(lambda y: raster.project_vertices(y[None], views.K[:1],
                                                                              views.world_to_cam[:1])[0][0, 0], x[5])
    torch.testing.assert_close(P[0, 5], Pref)


def test_apply_increment_rotates_about_the_bone_centre():
    rig, _ = toy()
    g = torch.Generator().manual_seed(1)
    G = pose(rig, g, 0.4, 0.1)
    B = G.shape[0]
    torch.testing.assert_close(fit.apply_increment(G, rig.centres, torch.zeros(B, 6, dtype=torch.float64)), G)
    cw = lambda M: torch.einsum("bij,bj->bi", M[:, :3, :3], rig.centres) + M[:, :3, 3]  # noqa: E731
    rot = torch.zeros(B, 6, dtype=torch.float64)
    rot[:, :3] = torch.tensor([0.0, 0.0, math.pi])  # a half turn: still finite, centre fixed
    G2 = fit.apply_increment(G, rig.centres, rot)
    torch.testing.assert_close(cw(G2), cw(G))
    R = G2[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(B, 3, 3))
    tr = torch.zeros(B, 6, dtype=torch.float64)
    tr[:, 3:] = 0.2
    torch.testing.assert_close(cw(fit.apply_increment(G, rig.centres, tr)), cw(G) + 0.2)
