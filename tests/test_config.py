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


def test_motion_is_required_in_synthetic_scenes_only():
    seqs = [{"name": "cap", "frames": 5}]
    # a captured scene: its motion is its smpl/ folder, no procedural motion name needed
    cfg = validate_config({"run_scenes": ["c"], "scenes": {"c": {"synthetic": False, "sequences": seqs}}}, SCHEMA)
    assert "motion" not in cfg["scenes"]["c"]["sequences"][0] and cfg["scenes"]["c"]["sequences"][0]["role"] == "train"
    # a captured scene may still name one, which must then be a known motion
    with pytest.raises(ConfigError, match="sequences/0/motion"):
        validate_config({"run_scenes": ["c"], "scenes": {"c": {"synthetic": False, "sequences": [
            dict(seqs[0], motion="moonwalk")]}}}, SCHEMA)
    # a synthetic scene (explicit, or by default) needs it, and the error names the sequence
    for scene in ({"synthetic": True, "sequences": seqs}, {"sequences": seqs}):
        with pytest.raises(ConfigError, match=r"scenes/s/sequences/0: 'motion' is a required property"):
            validate_config({"run_scenes": ["s"], "scenes": {"s": scene}}, SCHEMA)


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
    from anidress_core.fit import FitConfig

    full = validate_config({"run_scenes": ["s"], "scenes": {"s": {}}}, SCHEMA)
    assert section_defaults("fit") == full["fit"]
    assert section_defaults("fit", {"weights": {"flow": 1.5}, "frames": 7})["weights"] == \
        {**full["fit"]["weights"], "flow": 1.5}  # nested keys filled, the caller's kept
    # a caller with a raw dict gets the same fit settings as the workflow (one source of defaults)
    assert FitConfig.from_config({}) == FitConfig.from_config(full["fit"])
    fit_schema = SCHEMA["properties"]["fit"]["properties"]
    assert FitConfig.from_config({}).weights.prior == fit_schema["weights"]["properties"]["prior"]["default"]
    with pytest.raises(ConfigError, match="no config section 'nope'"):
        section_defaults("nope")


def test_fit_config_keys_are_the_schema_keys_and_the_weights_are_stored_as_used():
    import dataclasses

    from anidress_core.fit import FitConfig, LossWeights
    from anidress_core.fit.config import STAGE_KEYS

    fit_schema = SCHEMA["properties"]["fit"]["properties"]
    fields = {f.name for f in dataclasses.fields(FitConfig)}
    assert fields | set(STAGE_KEYS) - {"frames"} == set(fit_schema)  # no renamed key, none missing
    assert {f.name for f in dataclasses.fields(LossWeights)} == set(fit_schema["weights"]["properties"])
    # the pipeline's defaults: lambda_N 300 with image references, no swap hidden anywhere
    cfg = FitConfig.from_config({})
    assert cfg.loss == "pipeline" and cfg.anchor_reference == "images" and cfg.weights.normal == 300.0
    assert FitConfig.from_config({"anchor_reference": "texture"}).weights.normal == 300.0
    assert FitConfig.from_config({"weights": {"normal": 0.1}}).weights.normal == 0.1
    # fit/loss switches the loss; an explicit variant wins over it
    assert FitConfig.from_config({"loss": "paper"}) == FitConfig.from_config({}, "paper")
    assert FitConfig.from_config({"loss": "paper"}, "pipeline").weights == cfg.weights
    with pytest.raises(ValueError, match="unknown keys"):
        FitConfig.from_config({"first_frame_prior": 10.0})
    with pytest.raises(ValueError, match="unknown fit loss variant"):
        FitConfig.from_config({"loss": "nope"})


def test_scene_section_puts_the_scene_overrides_on_top():
    from anidress_core.config import scene_section

    cfg = {"fit": {"views": 0, "anchor_reference": "images"},
           "scenes": {"skirt": {"fit": {"anchor_reference": "texture"}}, "dress": {"fit": {}}}}
    assert scene_section(cfg, "fit", "skirt") == {"views": 0, "anchor_reference": "texture"}
    assert scene_section(cfg, "fit", "dress") == cfg["fit"]
    assert scene_section(cfg, "fit", "not_configured") == cfg["fit"]
    scene_section(cfg, "fit", "skirt")["views"] = 3  # a copy
    assert cfg["fit"]["views"] == 0


@pytest.mark.slow
def test_installed_wheel_carries_the_one_schema_and_the_report_templates(tmp_path):
    """A regular (non-editable) install finds the schema and the report templates (issue 24
    item 7): the wheel maps workflow/schemas and reports/ into anidress_core/_data, byte for byte."""
    import shutil
    import subprocess
    import sys
    import zipfile

    src = tmp_path / "src"  # build from a copy: an in-tree build would write build/ into the checkout
    src.mkdir()
    for rel in ("pyproject.toml", "setup.py", "README.md", "anidress_core", "workflow/schemas", "reports"):
        (shutil.copytree if (REPO / rel).is_dir() else shutil.copy2)(REPO / rel, src / rel)
    for junk in src.rglob("__pycache__"):
        shutil.rmtree(junk)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp_path / "whl"), str(src)], check=True, cwd=tmp_path)
    (wheel,) = (tmp_path / "whl").glob("anidress_core-*.whl")
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
        requires = z.read(next(n for n in z.namelist() if n.endswith("METADATA"))).decode()
    assert "Requires-Dist: jsonschema" in requires and "Requires-Dist: Jinja2" in requires
    for rel, packaged in (("workflow/schemas/config.schema.yaml", "schemas/config.schema.yaml"),
                          ("reports/report.html.j2", "reports/report.html.j2")):
        assert (site / "anidress_core" / "_data" / packaged).read_bytes() == (REPO / rel).read_bytes()
    code = ("import anidress_core, sys; from anidress_core.config import default_schema_path, load_config; "
            "from anidress_core.resources import report_template_dir; "
            f"assert anidress_core.__file__.startswith({str(site)!r}), anidress_core.__file__; "
            "print(default_schema_path()); print(report_template_dir()); "
            f"load_config({str(REPO / 'config' / 'config.yaml')!r})")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr
    schema, tdir = out.stdout.split()
    assert Path(schema) == site / "anidress_core" / "_data" / "schemas" / "config.schema.yaml"
    assert (Path(tdir) / "report.html.j2").is_file() and Path(tdir).is_relative_to(site)


def test_fit_defaults_quoted_in_config_yaml_comments_are_the_schema_defaults():
    """config.yaml lists the fit section's defaults in a comment (the schema holds them): each
    quoted `key: value` must be the schema's default, so the comment cannot drift."""
    import re

    text = (Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text()
    block = text[text.index("# Stages `fit`"):text.index("\nfit:")]
    from anidress_core.config import section_defaults

    defaults = section_defaults("fit")
    flat = dict(defaults, **defaults["weights"])
    quoted = re.findall(r"(?:#\s+|,\s+)([a-z_]+): ([0-9][0-9.e+-]*|[a-z_]+)\b", block)
    assert len(quoted) >= 20, quoted
    for key, value in quoted:
        assert key in flat, f"config.yaml's fit comment quotes {key!r}, which is not a fit key"
        want = flat[key]
        got = yaml.safe_load(value)
        assert got == want, f"config.yaml's fit comment says {key}: {value}, the schema's default is {want!r}"
