"""fit.plan_fit: frame 0's start, the simulation L_prior follows, L_anchor's references, the nearest baseline's
candidates, the settings as used and the header's notes; artifacts loaded only where the settings need them."""
from __future__ import annotations

import pytest
import torch

from anidress_core import fit
from anidress_core.fit import nearest as P
from anidress_core.geometry import lbs
from tests.fit.scenes import toy

T = 3
RIG, VIEWS = toy(C=2, H=16, W=16, n_theta=12, n_h=4)  # 48 vertices, 6 bones
EYE = torch.eye(4, dtype=torch.float64).expand(T, 6, 4, 4)


def _never():
    raise AssertionError("loaded although the settings do not use it")


def _sim(value: float, note: str):
    return lambda: (torch.full((T, 6, 4, 4), value, dtype=torch.float64), note)


def _plan(cfg, first="auto", **kw):
    loaders = dict(body_start=_never, ensemble=_never, rig_sim=None, spread=_never)
    return fit.plan_fit(cfg, RIG, VIEWS, T, first, **{**loaders, **kw})


def test_the_pipeline_follows_the_ensemble_and_weights_by_its_spread():
    cfg = fit.FitConfig.from_config({})
    scales = torch.ones(T, 5, dtype=torch.float64)
    p = _plan(cfg, ensemble=_sim(1.0, "ensemble"), rig_sim=_sim(2.0, "rig"), spread=lambda: scales)
    assert p.cfg == cfg and float(p.init[0, 0, 0]) == 1.0 and p.notes["first_frame_start"] == "ensemble, frame 0"
    assert float(p.sim_transforms[2, 1, 3, 3]) == 1.0 and p.prior_scales is scales and p.frames == T
    assert p.notes["followed_simulation"] == ("ensemble; L_prior's weight per vertex from the members' spread "
                                              "(prior_spread_floor 1)")
    assert p.anchor_init is None and p.notes["anchor_reference"].startswith("images")  # the default references
    assert p.candidates_of is None and p.notes["simulation_database"] is None and p.notes["starts"] is None
    assert p.notes["transforms_note"].startswith("fitted bone transforms, then smooth_transforms (1 passes)")


def test_the_texture_gives_every_vertex_a_reference_at_frame_0():
    cfg = fit.FitConfig.from_config({}, "pipeline_texture_anchor")
    face_uv = torch.rand(RIG.faces.shape[0], 3, 2, dtype=torch.float64)
    tex = torch.rand(8, 8, 3, dtype=torch.float64)
    p = _plan(cfg, ensemble=lambda: (EYE, "ensemble"), spread=lambda: torch.ones(T, 48),
              texture=lambda: (face_uv, tex, "tex.png"))
    assert bool(p.anchor_init.seen.all()) and p.notes["anchor_reference"].startswith("tex.png, blurred by ")


def test_without_a_simulation_prior_frame_0_starts_from_the_body_and_the_ensemble_is_not_read():
    cfg = fit.FitConfig.from_config({}, "pipeline_no_sim_prior")
    G = EYE[0].clone()
    G[:, 0, 3] = 0.1
    p = _plan(cfg, "body", rig_sim=_sim(2.0, "rig"), body_start=lambda: lbs(RIG.rest, RIG.weights, G)[None],
              normals=False)
    torch.testing.assert_close(p.init, G)  # the rig's pose closest to the skinned template
    assert p.sim_transforms is None and p.prior_scales is None and p.notes["followed_simulation"] is None
    assert p.cfg.weights.normal == 0.0 and p.cfg.replace(weights={"normal": cfg.weights.normal}) == cfg
    starts = torch.rand(T, 6, 4, 4, dtype=torch.float64)
    o = _plan(cfg, starts=starts)  # an oracle
    assert torch.equal(o.init, starts[0]) and o.starts is starts and o.notes["starts"] == "given per frame (oracle)"


def test_the_nearest_baseline_gets_its_candidates_from_the_database():
    cfg = fit.FitConfig.from_config({}, "nearest")
    joints = torch.eye(4, dtype=torch.float64).expand(T, 3, 4, 4).clone()
    db = P.make_database({"seq-walk": (EYE, joints, 30.0)})
    p = _plan(cfg, ensemble=_sim(1.0, "ensemble"), database=lambda: (db, joints, 30.0), own="seq-walk")
    assert p.candidates_of(0).labels == ["seq-walk:+0", "seq-walk:+1", "seq-walk:+2"]
    assert p.notes["simulation_database"] == "3 simulated frames of ['seq-walk']"


def test_a_missing_simulation_is_named():
    cfg = fit.FitConfig.from_config({"prior_reference": "sim"})
    with pytest.raises(ValueError, match="rig.npz: fit/prior_reference 'sim' needs"):
        _plan(cfg, "body", body_start=lambda: RIG.rest[None], rig_name="rig.npz")
    with pytest.raises(ValueError, match="first_frame_init is 'sim'"):
        _plan(cfg.replace(weights={"prior": 0.0}), "sim")
