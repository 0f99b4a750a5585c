# Configuration (validated against the JSON schema, defaults filled) and input helpers.
import os

import yaml

from anidress_core.config import validate_config


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


with open(os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml")) as _fh:
    _SCHEMA = yaml.safe_load(_fh)
# validate_config fills nested defaults (snakemake.utils.validate fills only the top
# level) and raises one message naming every bad key.
_validated = validate_config(config, _SCHEMA)
config.clear()
config.update(_validated)

SCENES = list(config["run_scenes"])
SYNTHETIC_SCENES = [s for s, c in config["scenes"].items() if c["synthetic"]]


wildcard_constraints:
    scene="|".join(config["scenes"]) or "^$",


def scene_cfg(wildcards):
    return config["scenes"][wildcards.scene]


def get_final_outputs():
    """Everything `rule all` builds: for now the scene datasets."""
    return [f"data/{s}" for s in SCENES]
