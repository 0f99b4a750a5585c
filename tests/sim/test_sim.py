"""Tests of the XPBD cloth solver (anidress_core.sim). Small meshes, few frames."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

pytest.importorskip("warp")

from anidress_core.body import make_motion, mannequin_model  # noqa: E402
from anidress_core.geometry import lbs  # noqa: E402
from anidress_core.sim import ClothParams, SimulationError, edge_stretch, penetration_depth, simulate  # noqa: E402
from anidress_core.sim.setup import (  # noqa: E402
    bending_pairs, color_constraints, interpolate_transforms, long_range_attachments, mesh_edges, substeps_for,
)

from .skirt import flared_skirt, nearest_weights, sphere_body, square_cloth  # noqa: E402


def _static(T: int) -> np.ndarray:
    return np.tile(np.eye(4), (T, 24, 1, 1))


@pytest.fixture(scope="module")
def body():
    return mannequin_model()


def _skirt_on(body, motion: str, T: int, around=24, rows=12, params=ClothParams(settle_frames=8)):
    m = make_motion(motion, 90)  # the twirl's speed depends on its length: fix it, then cut
    posed = body.pose(m.poses[:T], m.Rh[:T], m.Th[:T])
    v, f, band = flared_skirt(around, rows)
    gw = nearest_weights(v, body.v_template.numpy(), body.weights.numpy())
    res = simulate(v, f, band, gw, body.v_template, body.faces, body.weights, posed.transforms, m.fps, params)
    return res, v, f, band, gw, posed


# ----------------------------------------------------------------- setup pieces
def test_colouring_is_proper():
    v, f = square_cloth(8)
    pairs = np.concatenate([mesh_edges(f), bending_pairs(f)])
    color, order = color_constraints(pairs, len(v))
    for c in np.unique(color):
        p = pairs[color == c].reshape(-1)
        assert len(np.unique(p)) == len(p)
    assert (np.diff(color[order]) >= 0).all()


def test_long_range_attachment_distances():
    v, f = square_cloth(5, size=0.4)
    band = np.zeros(len(v), bool)
    band[:5] = True  # first row (x = -0.2)
    anchor, dist = long_range_attachments(v, mesh_edges(f), band)
    assert (anchor[band] == -1).all()
    free = ~band
    # Straight rows: the graph distance to the band row equals the x distance.
    np.testing.assert_allclose(dist[free], v[free, 0] + 0.2, atol=1e-9)
    assert band[anchor[free]].all()


def test_interpolation_endpoints_and_rigidity():
    g = torch.Generator().manual_seed(0)
    from anidress_core.geometry import axis_angle_to_matrix, make_transform

    A0 = make_transform(axis_angle_to_matrix(torch.randn(24, 3, generator=g, dtype=torch.float64)),
                        torch.randn(24, 3, generator=g, dtype=torch.float64))
    A1 = make_transform(axis_angle_to_matrix(torch.randn(24, 3, generator=g, dtype=torch.float64)),
                        torch.randn(24, 3, generator=g, dtype=torch.float64))
    piv = torch.randn(24, 3, generator=g, dtype=torch.float64)
    M = interpolate_transforms(A0, A1, piv, torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64))
    torch.testing.assert_close(M[0], A0)
    torch.testing.assert_close(M[2], A1)
    R = M[1, :, :3, :3]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(24, 3, 3))


def test_substeps_from_fps_and_time_scale():
    assert substeps_for(30, 1.0, 1 / 900) == 30
    assert substeps_for(60, 1.0, 1 / 900) == 15
    assert substeps_for(30, 2.0, 1 / 900) == 60


# ---------------------------------------------------------------------- physics
def test_hanging_cloth_settles():
    v, f = square_cloth(16, size=0.4, height=1.0)
    v = v[:, [2, 1, 0]] * [1, 1, 1]  # vertical sheet: x -> z
    v[:, 2] += 1.0
    band = v[:, 2] >= v[:, 2].max() - 1e-9  # top row pinned
    bv, bf, bw = sphere_body(0.1, center=(0.0, 0.0, -3.0))
    gw = np.zeros((len(v), 24))
    gw[:, 0] = 1
    # Tilt it 60 degrees so it has to swing down and settle.
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    top = v[band].mean(0)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    v = (v - top) @ R.T + top
    T = 45
    res = simulate(v, f, band, gw, bv, bf, bw, _static(T), 30.0, ClothParams(settle_frames=0, damping=4.0))
    s = res.stats
    assert s.nan_count.sum() == 0
    assert s.max_stretch.max() < 1.15
    assert s.recoveries == []
    np.testing.assert_allclose(res.frames[:, band], np.broadcast_to(v[band], (T, band.sum(), 3)), atol=1e-6)
    # It has swung towards vertical: free vertices below the band, speed small at the end.
    free = ~band
    assert res.frames[-1, free, 2].mean() < v[free, 2].mean() - 0.05
    assert np.abs(res.frames[-1] - res.frames[-2]).max() < 0.02
    st = edge_stretch(res.frames, v, f)
    np.testing.assert_allclose(st.max(1), s.max_stretch, rtol=1e-5)


def test_cloth_dropped_on_sphere_does_not_penetrate():
    p = ClothParams(settle_frames=0)
    v, f = square_cloth(18, size=0.7, height=0.25)
    bv, bf, bw = sphere_body(0.2, subdivisions=3)
    band = np.zeros(len(v), bool)
    gw = np.zeros((len(v), 24))
    gw[:, 0] = 1
    T = 24
    res = simulate(v, f, band, gw, bv, bf, bw, _static(T), 30.0, p)
    assert res.stats.nan_count.sum() == 0
    pen = penetration_depth(res.frames, np.broadcast_to(bv, (T,) + bv.shape), bf)
    assert pen.max() <= p.thickness  # at most the shell thickness (in fact pushed out to it)
    # The cloth fell and drapes: the centre rests on top of the sphere.
    centre = res.frames[-1, np.argmin(np.linalg.norm(v[:, :2], axis=1))]
    assert 0.2 <= centre[2] < 0.2 + 3 * p.thickness
    assert res.stats.max_stretch.max() < 1.3


def test_skirt_follows_band_skinning_exactly(body):
    res, v, f, band, gw, posed = _skirt_on(body, "walk", 6)
    want = lbs(torch.from_numpy(v).float(), torch.from_numpy(gw).float(), posed.transforms).numpy()
    np.testing.assert_allclose(res.frames[:, band], want[:, band], atol=2e-5)
    assert res.frames.shape == (6, len(v), 3) and res.frames.dtype == np.float32


def test_fast_motion_is_stable(body):
    T = 24
    p = ClothParams(settle_frames=8)
    res, v, f, band, gw, posed = _skirt_on(body, "run", T, params=p)
    s = res.stats
    assert s.nan_count.sum() == 0
    assert s.max_stretch.max() < p.max_stretch
    pen = penetration_depth(res.frames, posed.vertices, body.faces)[:, ~band]
    assert pen.max() < 0.01
    assert (s.substeps >= 30).all()


def test_recovery_refines_and_logs(caplog):
    # A wide, unpinned cloth falling 1 m per frame in a single substep: tiny stretch bound forces refinement.
    v, f = square_cloth(10, size=0.4, height=0.5)
    bv, bf, bw = sphere_body(0.2)
    band = np.zeros(len(v), bool)
    gw = np.zeros((len(v), 24))
    gw[:, 0] = 1
    p = ClothParams(substeps=1, iterations=1, settle_frames=0, max_stretch=1.02, max_refinements=6,
                    gravity=(0.0, 0.0, -300.0))
    with caplog.at_level(logging.WARNING, logger="anidress.sim"):
        res = simulate(v, f, band, gw, bv, bf, bw, _static(6), 30.0, p)
    assert len(res.stats.recoveries) > 0
    assert res.stats.substeps.max() > 1
    assert any("redoing it with" in r.getMessage() for r in caplog.records)
    assert res.stats.max_stretch[1:].max() <= 1.02 + 1e-6
    # Without refinements it gives up with a clear error.
    with pytest.raises(SimulationError, match="still unstable"):
        simulate(v, f, band, gw, bv, bf, bw, _static(6), 30.0,
                 ClothParams(substeps=1, iterations=1, settle_frames=0, max_stretch=1.02, max_refinements=0,
                             gravity=(0.0, 0.0, -300.0)))


def test_deterministic_on_cpu(body):
    p = ClothParams(settle_frames=4, device="cpu")
    a = _skirt_on(body, "twirl", 5, around=16, rows=8, params=p)[0]
    b = _skirt_on(body, "twirl", 5, around=16, rows=8, params=p)[0]
    np.testing.assert_array_equal(a.frames, b.frames)


def test_torch_and_numpy_inputs_agree():
    v, f = square_cloth(6, size=0.2, height=0.3)
    bv, bf, bw = sphere_body(0.1)
    band = np.zeros(len(v), bool)
    band[:6] = True
    gw = np.zeros((len(v), 24))
    gw[:, 0] = 1
    p = ClothParams(settle_frames=0, substeps=5)
    a = simulate(v, f, band, gw, bv, bf, bw, _static(3), 30.0, p).frames
    t = torch.from_numpy
    b = simulate(t(v), t(f), t(band), t(gw), t(bv), t(bf), t(bw), t(_static(3)), 30.0, p).frames
    np.testing.assert_array_equal(a, b)


def test_bad_shapes_raise():
    v, f = square_cloth(4)
    bv, bf, bw = sphere_body(0.1)
    with pytest.raises(ValueError, match="band"):
        simulate(v, f, np.zeros(3, bool), np.zeros((len(v), 24)), bv, bf, bw, _static(2), 30.0)
    with pytest.raises(ValueError, match="body_transforms"):
        simulate(v, f, np.zeros(len(v), bool), np.zeros((len(v), 24)), bv, bf, bw, np.zeros((2, 23, 4, 4)), 30.0)


def test_fused_cpu_path_matches_per_colour_launches(body):
    # The fused serial substep (recorded launches, contact queries skipped where a clearance
    # bound proves them empty) must reproduce the per-colour launch path exactly on the CPU, and
    # that path (the one CUDA runs) gives the same frames replayed from a captured graph (default)
    # as launched kernel by kernel.
    a = _skirt_on(body, "twirl", 6, around=20, rows=10, params=ClothParams(settle_frames=4, device="cpu"))[0]
    b = _skirt_on(body, "twirl", 6, around=20, rows=10,
                  params=ClothParams(settle_frames=4, device="cpu", fused_cpu=False))[0]
    c = _skirt_on(body, "twirl", 6, around=20, rows=10,
                  params=ClothParams(settle_frames=4, device="cpu", fused_cpu=False, graph_capture=False))[0]
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.stats.max_penetration_m, b.stats.max_penetration_m)
    np.testing.assert_array_equal(b.frames, c.frames)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_graph_matches_kernel_launches(body):
    # On the GPU: the frame graph replays the per-kernel launches (same kernels, same order).
    a = _skirt_on(body, "twirl", 6, around=20, rows=10, params=ClothParams(settle_frames=4, device="cuda"))[0]
    b = _skirt_on(body, "twirl", 6, around=20, rows=10,
                  params=ClothParams(settle_frames=4, device="cuda", graph_capture=False))[0]
    np.testing.assert_allclose(a.frames, b.frames, atol=1e-6)


def test_pinned_sheet_settles_to_the_analytic_rest():
    # A sheet pinned along its top edge, released 60 degrees off vertical: its static
    # equilibrium under gravity is the vertical sheet hanging straight below the pins
    # (the limit of a catenary whose ends coincide along the whole edge). Lengths are
    # preserved up to the solver's stretch, so every vertex must come back to it.
    v, f = square_cloth(12, size=0.3, height=1.0)
    vertical = v[:, [2, 1, 0]].copy()
    vertical[:, 2] += 1.0
    band = vertical[:, 2] >= vertical[:, 2].max() - 1e-9
    bv, bf, bw = sphere_body(0.1, center=(0.0, 0.0, -3.0))
    gw = np.zeros((len(v), 24))
    gw[:, 0] = 1
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    top = vertical[band].mean(0)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    start = (vertical - top) @ R.T + top
    res = simulate(start, f, band, gw, bv, bf, bw, _static(75), 30.0, ClothParams(settle_frames=0, damping=6.0))
    end = res.frames[-1]
    err = np.linalg.norm(end - vertical, axis=1)
    depth = vertical[:, 2].max() - vertical[:, 2]  # rest distance below the pins
    # horizontal deviation from the vertical plane and vertical sag within the stretch bound
    assert np.abs(end[:, 0] - vertical[:, 0]).max() < 0.005  # measured ~1 mm after 75 frames
    assert err.max() < 0.005
    assert np.all(vertical[:, 2] - end[:, 2] <= (res.stats.max_stretch.max() - 1) * depth + 2e-3)


def test_five_times_faster_motion_is_stable(body):
    # the `run` motion played 5x faster than captured (every 5th pose at the same fps)
    m = make_motion("run", 150)
    sel = slice(0, 150, 5)
    posed = body.pose(m.poses[sel], m.Rh[sel], m.Th[sel])
    v, f, band = flared_skirt(24, 12)
    gw = nearest_weights(v, body.v_template.numpy(), body.weights.numpy())
    p = ClothParams(settle_frames=8)
    res = simulate(v, f, band, gw, body.v_template, body.faces, body.weights, posed.transforms, m.fps, p)
    assert np.isfinite(res.frames).all() and res.stats.nan_count.sum() == 0
    assert res.stats.max_stretch.max() < p.max_stretch
    pen = penetration_depth(res.frames, posed.vertices, body.faces)[:, ~band]
    assert pen.max() < 0.02


def test_body_contacts_give_the_signed_distance_to_a_sphere():
    """body_contacts: the closest point and outward normal of a closed mesh, so that
    (x - point) . normal is the signed distance (winding-number sign), inside and outside;
    points farther than max_dist are not found."""
    from anidress_core.sim.metrics import body_contacts

    sv, sf, _ = sphere_body(0.2, (0.3, -0.1, 1.0), subdivisions=4)
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    radii = torch.linspace(0.12, 0.26, 50, dtype=torch.float64)
    x = dirs * radii[:, None] + torch.tensor([0.3, -0.1, 1.0], dtype=torch.float64)
    point, normal, found = body_contacts(x, torch.as_tensor(sv), torch.as_tensor(sf), max_dist=0.05)
    inside_reach = (radii - 0.2).abs() < 0.049  # the cut-off is max_dist (facets: +-1 mm)
    assert bool(found[inside_reach].all()) and not bool(found[(radii - 0.2).abs() > 0.051].any())
    sd = ((x - point) * normal).sum(-1)
    torch.testing.assert_close(sd[found], (radii - 0.2)[found], atol=2e-3, rtol=0)  # icosphere facets: < 2 mm
    torch.testing.assert_close(normal[found].norm(dim=-1), torch.ones(int(found.sum()), dtype=torch.float64),
                               atol=1e-5, rtol=0)
    assert float((normal[found] * dirs[found]).sum(-1).min()) > 0.95  # outward, inside the sphere too
