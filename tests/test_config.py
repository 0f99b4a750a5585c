from pathlib import Path

import pytest
import yaml

from anidress_core.config import ConfigError, default_schema_path, load_config, validate_config

REPO = Path(__file__).resolve().parents[1]
SCHEMA = yaml.safe_load(default_schema_path().read_text())


def test_repo_config_is_valid_and_complete():
    cfg = load_config(REPO / "config" / "config.yaml")
    tight = cfg["scenes"]["tight"]
    assert tight["cameras"]["count"] >= 12 and tight["cameras"]["train"] == 8
    assert len(tight["sequences"]) >= 2


def test_nested_defaults_are_filled():
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": {}}}, SCHEMA)
    s = cfg["scenes"]["s"]
    assert s["cameras"]["count"] == 12 and s["cameras"]["vfov_deg"] == 38.0
    assert s["render"]["texture_size"] == 1024 and s["body"]["model"] == "mannequin"
    assert s["sequences"][0]["role"] == "train"
    # defaults inside list items are filled too
    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": {"sequences": [{"name": "a", "motion": "walk", "frames": 3}]}}}, SCHEMA)
    assert cfg["scenes"]["s"]["sequences"][0]["role"] == "train"


@pytest.mark.parametrize(
    "patch, message",
    [
        ({"cameras": {"count": 1}}, "cameras/count"),
        ({"image_size": [10, 256]}, "image_size/0"),
        ({"sequences": [{"name": "a", "motion": "moonwalk", "frames": 5}]}, "sequences/0/motion"),
        ({"cameras": {"count": 8, "train": 8}}, "train (8) must be smaller"),
        ({"unknown_key": 1}, "unknown_key"),
    ],
)
def test_errors_name_the_key(patch, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        validate_config({"run_scenes": ["s"], "scenes": {"s": patch}}, SCHEMA)


def test_unknown_run_scene_and_bad_file(tmp_path):
    with pytest.raises(ConfigError, match="not a key of scenes"):
        validate_config({"run_scenes": ["nope"], "scenes": {"s": {}}}, SCHEMA)
    bad = tmp_path / "c.yaml"
    bad.write_text("run_scenes: [s\n")
    with pytest.raises(ConfigError, match="c.yaml"):
        load_config(bad)
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        load_config(tmp_path / "missing.yaml")


def test_section_defaults_are_the_validated_configs():
    from anidress_core.config import section_defaults
    from anidress_core.stages.fit import fit_config

    full = validate_config({"run_scenes": ["s"], "scenes": {"s": {}}}, SCHEMA)
    assert section_defaults("fit") == full["fit"]
    assert section_defaults("fit", {"weights": {"flow": 1.5}, "frames": 7})["weights"] == \
        {**full["fit"]["weights"], "flow": 1.5}  # nested keys filled, the caller's kept
    # a caller with a raw dict gets the same fit settings as the workflow (one source of defaults)
    assert fit_config({}) == fit_config(full["fit"])
    assert fit_config({}).w_prior_first == SCHEMA["properties"]["fit"]["properties"]["first_frame_prior"]["default"]
    with pytest.raises(ConfigError, match="no config section 'nope'"):
        section_defaults("nope")


def test_fit_config_normal_texture_anchor_is_lambda_n_only_with_texture_references():
    from anidress_core.stages.fit import anchor_reference, fit_config

    w = {"normal": 0.1, "anchor": 1e5, "normal_texture_anchor": 100.0}
    tex = {"weights": w, "anchor_reference": "texture"}
    assert fit_config(tex).w_normal == 100.0  # the pipeline's full method on the skirt (L_an, texture references)
    for abl in ("anchor_texture", "collision"):  # these variants always take texture references
        assert anchor_reference({"anchor_reference": "images"}, abl) == "texture"
        assert fit_config({"weights": w}, abl).w_normal == 100.0
    # first-seen image references keep the paper's lambda_N (a larger one is worse there: fit_normal_weight.md)
    assert fit_config({"weights": w, "anchor_reference": "images"}).w_normal == 0.1
    for abl in ("anchor", "anchor_smooth"):
        assert anchor_reference(tex, abl) == "images" and fit_config(tex, abl).w_normal == 0.1
    # the paper's ablations drop L_an and keep the paper's lambda_N; (b) has no normal term at all
    assert fit_config(tex, "no_flow").w_normal == 0.1
    assert fit_config(tex, "vertex").w_normal == 0.1
    assert fit_config(tex, "no_normal_flow").w_normal == 0.0
    # without L_an, or with normal_texture_anchor 0 (the schema's default), weights/normal everywhere
    assert fit_config(dict(tex, weights=dict(w, anchor=0.0))).w_normal == 0.1
    assert fit_config(dict(tex, weights=dict(w, normal_texture_anchor=0.0))).w_normal == 0.1
    # normals off (weight 0) stay off
    assert fit_config(dict(tex, weights=dict(w, normal=0.0))).w_normal == 0.0


def test_scene_section_puts_the_scene_overrides_on_top():
    from anidress_core.config import scene_section

    cfg = {"fit": {"views": 0, "anchor_reference": "images"},
           "scenes": {"skirt": {"fit": {"anchor_reference": "texture"}}, "dress": {"fit": {}}}}
    assert scene_section(cfg, "fit", "skirt") == {"views": 0, "anchor_reference": "texture"}
    assert scene_section(cfg, "fit", "dress") == cfg["fit"]
    assert scene_section(cfg, "fit", "not_configured") == cfg["fit"]
    scene_section(cfg, "fit", "skirt")["views"] = 3  # a copy
    assert cfg["fit"]["views"] == 0
