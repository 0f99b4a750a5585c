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
    assert paper.weights == fit.PAPER_WEIGHTS and paper.smooth_passes == 0 and paper.window == 0 and paper.method == "rig"
    assert {k: getattr(paper.weights, k) for k in fit.TERM_NAMES} == PAPER
    assert paper.max_iters == base.max_iters  # the solver is the section's
    assert fit.FitConfig.from_config({}, "paper_vertex").method == "vertex"
    nf = fit.FitConfig.from_config({}, "paper_no_normal_flow").weights
    assert nf.flow == 0 and nf.normal == 0 and nf.silhouette == 2.0
    c = fit.FitConfig.from_config({}, "paper_no_flow").weights
    assert c.flow == 0 and c.normal == 0.1 and c.anchor == 0 and c.collision == 0 and c.prior == 0
    with pytest.raises(ValueError, match="unknown fit loss variant"):
        fit.FitConfig.from_config({}, "nope")
    # the ensemble's members weighted by the images: a setting of L_prior's ensemble reference only
    assert base.prior_member_temperature is None and base.prior_member_window == 5
    assert fit.FitConfig.from_config({}, "pipeline_image_weights").prior_member_temperature == 1.0
    assert fit.FitConfig.from_config({"prior_member_temperature": 1, "prior_reference": "sim"}).prior_member_temperature \
        is None  # unused: recorded as None, as it ran
    for bad in ({"prior_member_temperature": -1.0}, {"prior_member_window": 1.5}):
        with pytest.raises(ValueError, match="prior_member"):
            base.replace(**bad)


def test_which_settings_read_the_simulation_of_the_observed_motion():
    """One property says whether the fit needs the rig's ``seq-<sequence>`` (rule fit's error, fit_sequence's check)."""
    from anidress_core.fit import FitConfig

    base = FitConfig.from_config({})
    assert base.prior_follows_simulation and base.needs_simulation  # the default: L_prior follows it
    assert not base.replace(prior_reference="start").needs_simulation
    assert not base.replace(weights={"prior": 0.0}).needs_simulation
    assert not base.replace(method="nearest").needs_simulation  # not optimised: no L_prior
    assert not base.replace(method="vertex").prior_follows_simulation
    assert base.replace(prior_reference="start", start="sim_delta").needs_simulation
    assert not FitConfig.from_config({}, loss="pipeline_no_sim_prior").needs_simulation


def test_prior_information_values_come_from_one_place():
    """The schema's enum of fit/prior_information is config.PRIOR_INFORMATION_TERMS's keys; others are refused."""
    from anidress_core.fit import FitConfig
    from anidress_core.fit.config import PRIOR_INFORMATION_TERMS

    fit_schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())["properties"]["fit"]
    schema = fit_schema["properties"]["prior_information"]
    assert sorted(schema["enum"]) == sorted(PRIOR_INFORMATION_TERMS) and schema["default"] == "uniform"
    for v in PRIOR_INFORMATION_TERMS:
        assert FitConfig.from_config({"prior_information": v}).prior_information == v
    with pytest.raises(ValueError, match="prior_information"):
        FitConfig.from_config({}).replace(prior_information="hessian")
