"""Stress tests of the cloth solver and the template stage (issue 8 §3).

Extreme and fast motions in simulation; near-degenerate triangles and duplicated vertices in
templates; wrong scales. Each case either runs finite or stops with a clear error.
"""
import numpy as np
import pytest
import torch

from anidress_core import garment as G
from anidress_core.body import make_motion, mannequin_model
from anidress_core.sim import ClothParams, SimulationError, penetration_depth, simulate

from tests.sim.skirt import flared_skirt, nearest_weights


@pytest.fixture(scope="module")
def body():
    return mannequin_model()


def _run(body, transforms, fps=30.0, params=None):
    v, f, band = flared_skirt(20, 10)
    gw = nearest_weights(v, body.v_template.numpy(), body.weights.numpy())
    return simulate(v, f, band, gw, body.v_template, body.faces, body.weights, transforms, fps,
                    params or ClothParams(settle_frames=4)), band


def test_ten_times_faster_spin_is_finite(body):
    m = make_motion("twirl", 200)
    sel = slice(0, 200, 10)  # a full spin in 20 frames: ~10x the captured speed
    posed = body.pose(m.poses[sel], m.Rh[sel], m.Th[sel])
    p = ClothParams(settle_frames=4)
    res, band = _run(body, posed.transforms, params=p)
    assert np.isfinite(res.frames).all() and res.stats.nan_count.sum() == 0
    assert res.stats.max_stretch.max() < p.max_stretch
    pen = penetration_depth(res.frames, posed.vertices, body.faces)[:, ~band]
    assert pen.max() < 0.02


def test_teleporting_body_recovers_or_stops_clearly(body):
    # the body jumps 3 m sideways between two frames (a capture glitch)
    m = make_motion("walk", 12)
    Th = m.Th.clone()
    Th[6:, 0] += 3.0
    posed = body.pose(m.poses, m.Rh, Th)
    try:
        res, band = _run(body, posed.transforms, params=ClothParams(settle_frames=2, max_refinements=2))
    except SimulationError as e:
        assert "frame" in str(e)  # the message says where it failed
    else:
        assert np.isfinite(res.frames).all()
        # the band is attached to the body: it followed the jump exactly
        assert np.abs(res.frames[-1, band].mean(0)[0] - res.frames[0, band].mean(0)[0]) > 2.5


def test_static_body_hundreds_of_frames_settles(body):
    # nothing moves for 150 frames: the skirt released from its flared rest shape swings
    # down and settles -- damping removes energy, it never grows; no drift, no NaN
    T = 150
    posed = body.pose(torch.zeros(T, 72), torch.zeros(T, 3), torch.zeros(T, 3))
    res, band = _run(body, posed.transforms, params=ClothParams(settle_frames=10))
    assert np.isfinite(res.frames).all()
    speed = np.linalg.norm(np.diff(res.frames, axis=0), axis=-1).mean(1)  # (T-1,) mean vertex speed / frame
    assert speed[-30:].mean() < 0.3 * speed[5:35].mean()
    assert speed[-30:].max() < 5e-3


@pytest.mark.parametrize("scale,word", [(1000.0, "millimetres"), (1e-3, "kilometres")])
def test_template_in_wrong_units_is_a_clear_error(body, scale, word):
    v, f, uv = G.skirt_surface(body)
    with pytest.raises(ValueError, match=word):
        G.prepare_template(v * scale, f, None, "skirt", body, 600)


def test_slivers_and_duplicates_are_cleaned(body):
    v, f, uv = G.skirt_surface(body)
    v = np.asarray(v, np.float64)
    f = np.asarray(f, np.int64)
    rng = np.random.default_rng(0)
    # every vertex duplicated (an unwelded export), faces spread over both copies
    V = len(v)
    v2 = np.concatenate([v, v + rng.normal(0, 1e-8, v.shape)])
    pick = rng.random(f.shape) < 0.5
    f2 = np.where(pick, f + V, f)
    # near-degenerate slivers: a vertex nudged 1e-9 m off the middle of an edge
    e = f[: len(f) // 10]
    mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]]) + 1e-9
    sliver_v = np.arange(len(v2), len(v2) + len(mid))
    v3 = np.concatenate([v2, mid])
    f3 = np.concatenate([f2, np.stack([e[:, 0], e[:, 1], sliver_v], 1)])
    rv, rf = G.clean_and_remesh(v3, f3, 800)
    t = rv[rf]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    assert np.isfinite(rv).all()
    assert area.min() > 1e-3 * np.median(area)  # no slivers survive the remesh
    assert abs(len(rv) - 800) <= 40
    # and it is still the skirt: same bounding box within a centimetre
    np.testing.assert_allclose(rv.min(0), v.min(0), atol=0.01)
    np.testing.assert_allclose(rv.max(0), v.max(0), atol=0.01)
