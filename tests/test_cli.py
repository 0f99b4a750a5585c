import subprocess
import sys

from anidress_core.cli import build_parser, main


def test_help_lists_stages():
    text = build_parser().format_help()
    assert "synth" in text


def test_console_script_runs():
    res = subprocess.run([sys.executable, "-m", "anidress_core.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "synth" in res.stdout


def test_unknown_scene_is_a_clear_error(capsys, tmp_path):
    assert main(["synth", "--scene", "no_such_scene", "--out", str(tmp_path / "x")]) == 2
    assert "no_such_scene" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
