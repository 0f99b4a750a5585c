import subprocess
import sys

from anidress_core.cli import build_parser, main


def test_help_lists_stages():
    text = build_parser().format_help()
    for stage in ("synth", "template", "motion", "simulate"):
        assert stage in text


def test_console_script_runs():
    res = subprocess.run([sys.executable, "-m", "anidress_core.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "synth" in res.stdout


def test_unknown_scene_is_a_clear_error(capsys, tmp_path):
    assert main(["synth", "--scene", "no_such_scene", "--out", str(tmp_path / "x")]) == 2
    assert "no_such_scene" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_cli_runs_template_motion_and_simulate_on_a_tiny_scene(tmp_path):
    """The CLI runs the same stage functions as the workflow, file in, file out."""
    import numpy as np
    import yaml

    from anidress_core.config import default_schema_path, validate_config
    from anidress_core.stages.synth import run_synth

    cfg = validate_config({"run_scenes": ["s"], "scenes": {"s": {
        "kind": "skirt", "image_size": [32, 32], "sequences": [{"name": "walk", "motion": "walk", "frames": 3}],
        "garment": {"vertices": 500, "cloth": {"settle_frames": 3}}, "render": {"texture_size": 64}}}},
        yaml.safe_load(default_schema_path().read_text()))
    scene = tmp_path / "data" / "s"
    run_synth(cfg["scenes"]["s"], "s", scene, progress=False)
    conf = tmp_path / "c.yaml"
    conf.write_text(yaml.safe_dump({"run_scenes": ["s"], "scenes": {"s": {}}, "simulate": {"cloth": {"settle_frames": 3}}}))
    assert main(["template", str(scene), "--vertices", "500", "-o", str(tmp_path / "r")]) == 0
    assert main(["motion", "seq-walk", str(scene), "--config", str(conf), "-o", str(tmp_path / "m.npz")]) == 0
    assert main(["simulate", str(tmp_path / "r" / "template.npz"), str(tmp_path / "m.npz"), str(scene),
                 "--config", str(conf), "-o", str(tmp_path / "sim.npz"), "--quiet"]) == 0
    frames = np.load(tmp_path / "sim.npz")["frames"]
    assert frames.shape == (3, 500, 3) and np.isfinite(frames).all()


def test_fit_command_applies_the_scene_overrides(monkeypatch, tmp_path):
    """`anidress fit data/<scene> ...` reads the fit section plus scenes/<scene>/fit, as rule fit does."""
    import anidress_core.stages.fit as stage

    seen = {}
    monkeypatch.setattr(stage, "run_fit", lambda *a, **k: seen.update(params=a[7], ablation=k.get("ablation"),
                                                                      ensemble=k.get("sim_ensemble_npz")))
    scene = tmp_path / "skirt"
    scene.mkdir()
    base = ["fit", str(scene), "walk", "--rig", "r.npz", "--template", "t.npz", "--masks", "m", "-o",
            str(tmp_path / "o.npz"), "--no-normals", "--config", "config/config.yaml"]
    assert main(base) in (0, None)
    assert seen["params"]["anchor_reference"] == "images"  # config.yaml: the fit section (the schema's default)
    assert main(base + ["--anchor-reference", "texture", "--sim-ensemble", "e.npz"]) in (0, None)
    assert seen["params"]["anchor_reference"] == "texture" and seen["ensemble"] == "e.npz"
    other = tmp_path / "custom"  # a scene config.yaml does not define
    other.mkdir()
    assert main(["fit", str(other)] + base[2:]) in (0, None)
    assert seen["params"]["anchor_reference"] == "images"  # the top-level fit section (the schema's default)
