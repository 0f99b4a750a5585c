# Configuration (validated against the JSON schema, defaults filled) and input helpers.
import os

import yaml

from anidress_core.config import scene_section, validate_config


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


with open(os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml")) as _fh:
    _SCHEMA = yaml.safe_load(_fh)
# validate_config fills nested defaults (snakemake.utils.validate fills only the top
# level) and raises one message naming every bad key.
_validated = validate_config(config, _SCHEMA)


def _canonical(obj):
    """Mappings with their keys sorted, recursively (lists keep their order): rule params are
    compared as text between runs, so the order of keys in a config file must not count."""
    if isinstance(obj, dict):
        return {k: _canonical(obj[k]) for k in sorted(obj, key=str)}
    if isinstance(obj, list):
        return [_canonical(v) for v in obj]
    return obj


config.clear()
config.update(_canonical(_validated))

_missing_lib = sorted(set(config["field"]["render"]["library"]) - set(config["simulate"]["library"]))
if _missing_lib:
    raise ValueError(f"config: field/render/library names {_missing_lib}, which simulate/library "
                     f"{config['simulate']['library']} does not simulate (the rig has no garment poses for them)")

SCENES = list(config["run_scenes"])
SYNTHETIC_SCENES = [s for s, c in config["scenes"].items() if c["synthetic"]]


wildcard_constraints:
    scene="|".join(config["scenes"]) or "^$",


def scene_cfg(wildcards):
    return config["scenes"][wildcards.scene]


# Rule params hold exactly the settings that shape the rule's outputs (DESIGN.md §1: a stage's
# setting reruns that stage and what depends on it, nothing upstream); tests/workflow/test_rerun_sets.py
# checks it section by section.
SCENE_STAGE_SECTIONS = ("fit",)
"""Parts of a scene section that override a stage's section (scenes/<scene>/fit): not the scene's data."""


def synth_params(wildcards):
    """The scene section that rule synth renders from, without the stage overrides (scenes/<scene>/fit)."""
    return {k: v for k, v in scene_cfg(wildcards).items() if k not in SCENE_STAGE_SECTIONS}


def has_garment(scene):
    """Scenes with a loose garment run template/simulate; tight ones skip them (DESIGN.md §6)."""
    return config["scenes"][scene]["kind"] != "tight"


def sim_motion_names(scene):
    """seq-<sequence> for each captured sequence, lib-<name> for the library, amass-<stem>."""
    sim = config["simulate"]
    names = [f"seq-{s['name']}" for s in config["scenes"][scene]["sequences"]]
    names += [f"lib-{m}" for m in sim["library"]]
    names += [f"amass-{os.path.splitext(os.path.basename(p))[0]}" for p in sim["amass"]]
    return names


def motion_params(wildcards):
    """Only the settings that shape this motion (a library change reruns only what it touches)."""
    sim = config["simulate"]
    if wildcards.motion.startswith("seq-"):
        return {}
    if wildcards.motion.startswith("amass-"):  # only the file(s) of this motion (its stem)
        stem = wildcards.motion[len("amass-"):]
        return {"library_fps": sim["library_fps"],
                "amass": [p for p in sim["amass"] if os.path.splitext(os.path.basename(p))[0] == stem]}
    return {"library_frames": sim["library_frames"], "library_fps": sim["library_fps"],
            "amass": []}


def motion_sequences(motion):
    """[<sequence>] for a captured sequence's motion seq-<sequence> (its smpl/ files), else []."""
    return [motion[len("seq-"):]] if motion.startswith("seq-") else []


def get_final_outputs():
    """Everything the report summarises (`rule all` adds the report itself).

    Per scene: the scene check, the dataset; for garment scenes the simulations, the rig,
    the 2D cues and the fits (with metrics on synthetic scenes); the field's metrics and
    renders of every training sequence (tight scenes: body joints only, DESIGN.md §6).
    """
    out = []
    for s in SCENES:
        # a captured scene's folder: ancient (its files count through rule scene_files, scene_files.smk)
        out += [f"data/{s}" if config["scenes"][s]["synthetic"] else ancient(f"data/{s}"), f"results/{s}/scene_check.json"]
        if has_garment(s):
            out += expand("results/{scene}/sim/{motion}.npz", scene=s, motion=sim_motion_names(s))
            out.append(f"results/{s}/rig.npz")
            out += cues_outputs(s)
            out += fit_outputs(s)
        out += field_outputs(s)
    return out
