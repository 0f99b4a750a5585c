"""fit.plan_fit: frame 0's start, the simulation L_prior follows, the settings as used; artifacts loaded only where
the settings need them."""
from __future__ import annotations

import pytest
import torch

from anidress_core import fit


def _never():
    raise AssertionError("loaded although the settings do not use it")


def _sim(value: float, note: str):
    return lambda: (torch.full((3, 2, 4, 4), value, dtype=torch.float64), note)


def test_the_pipeline_follows_the_ensemble_and_weights_by_its_spread():
    cfg = fit.FitConfig.from_config({"anchor_reference": "texture"})
    scales = torch.ones(3, 5, dtype=torch.float64)
    p = fit.plan_fit(cfg, "auto", _sim(1.0, "ensemble"), _sim(2.0, "rig"), _never, lambda: scales,
                     texture=lambda G0: (G0, "texture at the start"))  # L_anchor's references at frame 0's start
    assert p.anchor_init is p.init and p.anchor_note == "texture at the start"
    assert p.cfg == cfg and float(p.init[0, 0, 0]) == 1.0 and p.start_note == "ensemble, frame 0"
    assert float(p.sim_transforms[2, 1, 3, 3]) == 1.0 and p.prior_scales is scales
    assert p.followed_note == "ensemble; L_prior's weight per vertex from the members' spread (prior_spread_floor 1)"


def test_without_a_simulation_prior_frame_0_starts_from_the_body_and_the_ensemble_is_not_read():
    cfg = fit.FitConfig.from_config({}, "pipeline_no_sim_prior")
    body = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    p = fit.plan_fit(cfg, "body", _never, _sim(2.0, "rig"), lambda: body, _never, normals=False)
    assert p.init is body and p.sim_transforms is None and p.prior_scales is None and p.followed_note is None
    assert p.anchor_init is None and p.anchor_note.startswith("images")  # the default references: the images'
    assert p.cfg.weights.normal == 0.0 and p.cfg.replace(weights={"normal": cfg.weights.normal}) == cfg
    starts = torch.rand(3, 2, 4, 4, dtype=torch.float64)
    assert torch.equal(fit.plan_fit(cfg, "auto", _never, None, _never, _never, starts).init, starts[0])  # an oracle


def test_a_missing_simulation_is_named():
    cfg = fit.FitConfig.from_config({"prior_reference": "sim"})
    with pytest.raises(ValueError, match="rig.npz: fit/prior_reference 'sim' needs"):
        fit.plan_fit(cfg, "body", _never, None, lambda: torch.zeros(2, 4, 4), _never, rig_name="rig.npz")
    with pytest.raises(ValueError, match="first_frame_init is 'sim'"):
        fit.plan_fit(cfg.replace(weights={"prior": 0.0}), "sim", _never, None, _never, _never)
