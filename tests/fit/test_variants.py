"""anidress_core.fit.variants: the loss variants in one place, used by the workflow, the schema and the CLI."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
import yaml

from anidress_core import fit
from anidress_core.cli import build_parser
from tests.fit.scenes import PAPER

ROOT = Path(__file__).resolve().parents[2]


def test_variant_names_come_from_one_place():
    """rule fit_ablation's wildcard and fit/loss check read VARIANTS; the CLI offers exactly them; the
    schema lists no copy of them."""
    smk = (ROOT / "workflow/rules/helpers/fit.smk").read_text()
    # imported inside check_fit_variant (only where a non-default name is checked: no torch at parse, issue 22)
    assert re.search(r"^ +from anidress_core\.fit\.variants import VARIANTS$", smk, re.M)
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())["properties"]["fit"]
    assert "enum" not in schema["properties"]["ablations"]["items"] and "enum" not in schema["properties"]["loss"]
    assert schema["properties"]["loss"]["default"] in fit.VARIANTS
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    opt = next(a for a in sub.choices["fit"]._actions if "--ablation" in a.option_strings)
    assert sorted(opt.choices) == sorted(fit.VARIANTS)


def test_variant_configs():
    base = fit.FitConfig.from_config({})
    assert base.loss == "pipeline" and fit.apply_variant(base, "pipeline") == base
    for term in ("normal", "flow", "anchor", "collision", "prior"):  # leave-one-out of the pipeline
        c = fit.FitConfig.from_config({}, f"pipeline_no_{term}")
        assert getattr(c.weights, term) == 0 and c.loss == f"pipeline_no_{term}"
        others = {k: getattr(c.weights, k) for k in fit.TERM_NAMES if k != term}
        assert others == {k: getattr(base.weights, k) for k in others}
    assert fit.FitConfig.from_config({}, "pipeline_no_smooth").smooth_passes == 0
    assert base.window > 1 and fit.FitConfig.from_config({}, "pipeline_no_window").window == 0
    assert fit.FitConfig.from_config({}, "nearest").window == 0
    paper = fit.FitConfig.from_config({"weights": {"anchor": 7.0, "normal": 300.0}}, "paper")
    assert paper.weights == fit.LossWeights(**fit.PAPER_WEIGHTS) and paper.smooth_passes == 0 and paper.window == 0
    assert paper.method == "rig"
    assert {k: getattr(paper.weights, k) for k in fit.TERM_NAMES} == PAPER
    assert paper.max_iters == base.max_iters  # the solver is the section's
    assert fit.FitConfig.from_config({}, "paper_vertex").method == "vertex"
    nf = fit.FitConfig.from_config({}, "paper_no_normal_flow").weights
    assert nf.flow == 0 and nf.normal == 0 and nf.silhouette == 2.0
    c = fit.FitConfig.from_config({}, "paper_no_flow").weights
    assert c.flow == 0 and c.normal == 0.1 and c.anchor == 0 and c.collision == 0 and c.prior == 0
    with pytest.raises(ValueError, match="unknown fit loss variant"):
        fit.FitConfig.from_config({}, "nope")
    # leave-one-out of the simulation prior and of its spread weighting
    nsp = fit.FitConfig.from_config({}, "pipeline_no_sim_prior")
    assert nsp.prior_reference == "start" and not nsp.prior_tangential and nsp.weights.prior == 10.0
    assert base.prior_spread_floor == 1.0
    assert fit.FitConfig.from_config({}, "pipeline_uniform_prior").prior_spread_floor is None
    assert fit.FitConfig.from_config({}, "pipeline_texture_anchor").anchor_reference == "texture"


def test_the_variants_kept():
    """The pipeline, its leave-one-out ablations, the texture/images anchor pair, the paper's loss and its
    (a)(b)(c), the nearest baseline (issue 48); the variants of the experiments left off by default left with
    their code, and their settings left the schema (a config that names one is refused)."""
    assert list(fit.VARIANTS) == [
        "pipeline", "pipeline_no_normal", "pipeline_no_flow", "pipeline_no_anchor", "pipeline_no_collision",
        "pipeline_no_stretch", "pipeline_no_prior", "pipeline_no_smooth", "pipeline_no_window",
        "pipeline_no_sim_prior", "pipeline_uniform_prior", "pipeline_texture_anchor", "nearest", "paper",
        "paper_vertex", "paper_no_normal_flow", "paper_no_flow"]
    fit_schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())["properties"]["fit"]
    for key in ("proposal_every", "proposal_nearest", "proposal_offsets", "proposal_refine",
                "proposal_velocity_weight", "backward", "prior_member_temperature", "prior_member_window",
                "prior_information", "start"):
        assert key not in fit_schema["properties"], key
        with pytest.raises(ValueError, match="unknown keys"):
            fit.FitConfig.from_config({key: 0})
    with pytest.raises(ValueError, match="prior_reference: 'other' is not one of"):
        fit.FitConfig.from_config({"prior_reference": "other"})
    with pytest.raises(ValueError, match="weights/prior: -1 is less than the minimum of 0"):
        fit.FitConfig.from_config({"weights": {"prior": -1}})


def test_which_settings_read_the_simulation_of_the_observed_motion():
    """One property says whether L_prior follows the rig's ``seq-<sequence>`` or the ensemble's mean (rule fit's
    error, fit_sequence's check)."""
    from anidress_core.fit import FitConfig

    base = FitConfig.from_config({})
    assert base.prior_follows_simulation  # the default: L_prior follows it
    assert not base.replace(prior_reference="start").prior_follows_simulation
    assert not base.replace(weights={"prior": 0.0}).prior_follows_simulation
    assert not base.replace(method="nearest").prior_follows_simulation  # not optimised: no L_prior
    assert not base.replace(method="vertex").prior_follows_simulation
    assert not FitConfig.from_config({}, loss="pipeline_no_sim_prior").prior_follows_simulation
