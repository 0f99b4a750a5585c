"""Configuration: JSON-schema validation with defaults filled at every depth.

The schema is ``workflow/schemas/config.schema.yaml`` (an installed package carries it
as package data, see :mod:`anidress_core.resources`); the workflow (``common.smk``)
and the ``anidress`` command line both validate through :func:`validate_config`, so
a config accepted by one is accepted by the other. Snakemake's own ``validate``
fills defaults only where the parent object already exists; this fills them depth
first, so ``cameras: {}`` (or no ``cameras`` key at all) gets every camera default.
"""
from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any

import yaml

__all__ = ["ConfigError", "validate_config", "load_config", "default_schema_path", "scene_config", "section_defaults",
           "scene_section"]


class ConfigError(ValueError):
    """The configuration does not satisfy the schema."""


def default_schema_path() -> Path:
    """The schema: ``<repo>/workflow/schemas/config.schema.yaml`` in a source checkout, else the
    copy an installed package carries (:func:`anidress_core.resources.schema_path`)."""
    from .resources import schema_path

    return schema_path()


def _resolve(schema: dict, root: dict) -> dict:
    ref = schema.get("$ref")
    if ref is None:
        return schema
    if not ref.startswith("#/"):
        raise ConfigError(f"only local $ref are supported, got {ref}")
    node: Any = root
    for part in ref[2:].split("/"):
        node = node[part]
    return _resolve(node, root)


def _fill(instance: Any, schema: dict, root: dict) -> Any:
    schema = _resolve(schema, root)
    if isinstance(instance, dict) and schema.get("type") == "object":
        for key, sub in schema.get("properties", {}).items():
            sub_r = _resolve(sub, root)
            if key not in instance and "default" in sub_r:
                instance[key] = copy.deepcopy(sub_r["default"])
            if key in instance:
                instance[key] = _fill(instance[key], sub_r, root)
        extra = schema.get("additionalProperties")
        if isinstance(extra, dict):
            for key in list(instance):
                if key not in schema.get("properties", {}):
                    instance[key] = _fill(instance[key], extra, root)
    elif isinstance(instance, list) and isinstance(schema.get("items"), dict):
        return [_fill(item, schema["items"], root) for item in instance]
    return instance


def validate_config(config: dict, schema: dict) -> dict:
    """Return a deep copy of ``config`` with defaults filled, validated against ``schema``.

    Raises :class:`ConfigError` naming the offending key path and the reason.
    """
    import jsonschema

    filled = _fill(copy.deepcopy(dict(config)), schema, schema)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(filled), key=lambda e: list(e.absolute_path))
    if errors:
        lines = [f"  {'/'.join(str(p) for p in e.absolute_path) or '<root>'}: {e.message}" for e in errors]
        raise ConfigError("invalid configuration:\n" + "\n".join(lines))
    for name in filled.get("run_scenes", []):
        if name not in filled.get("scenes", {}):
            raise ConfigError(f"invalid configuration:\n  run_scenes: {name!r} is not a key of scenes")
    for name, scene in filled.get("scenes", {}).items():
        cams = scene.get("cameras", {})
        if cams.get("train", 0) >= cams.get("count", 0):
            raise ConfigError(
                f"invalid configuration:\n  scenes/{name}/cameras: train ({cams.get('train')}) must be "
                f"smaller than count ({cams.get('count')}) so test views remain"
            )
        names = [s["name"] for s in scene.get("sequences", [])]
        if len(set(names)) != len(names):
            raise ConfigError(f"invalid configuration:\n  scenes/{name}/sequences: duplicate names {names}")
    return filled


@functools.lru_cache(maxsize=4)
def _schema(path: str) -> dict:
    return yaml.safe_load(Path(path).read_text())


def section_defaults(name: str, params: dict | None = None, schema_path: str | Path | None = None) -> dict:
    """A deep copy of the config section ``name`` (``params``, e.g. a raw dict of a caller)
    with the schema's defaults filled at every depth, so code reading a section has one
    source for its defaults, the schema. Fills only, does not validate (callers add keys of
    their own, e.g. ``frames``); :func:`validate_config` validates whole configs."""
    schema_path = Path(schema_path) if schema_path else default_schema_path()
    if not schema_path.is_file():
        raise FileNotFoundError(f"{schema_path}: config schema not found")
    schema = _schema(str(schema_path))
    if name not in schema.get("properties", {}):
        raise ConfigError(f"{schema_path}: no config section {name!r}")
    return _fill(copy.deepcopy(dict(params or {})), schema["properties"][name], schema)


def load_config(path: str | Path, schema_path: str | Path | None = None) -> dict:
    """Read a YAML config file and validate it (see :func:`validate_config`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: config file not found")
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from e
    schema_path = Path(schema_path) if schema_path else default_schema_path()
    if not schema_path.is_file():
        raise FileNotFoundError(f"{schema_path}: config schema not found")
    schema = yaml.safe_load(schema_path.read_text())
    try:
        return validate_config(cfg, schema)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def scene_config(config: dict, scene: str) -> dict:
    """The validated sub-config of one scene, with a clear error for unknown names."""
    scenes = config.get("scenes", {})
    if scene not in scenes:
        raise ConfigError(f"unknown scene {scene!r}; the config defines {sorted(scenes)}")
    return scenes[scene]


def scene_section(config: dict, section: str, scene: str) -> dict:
    """A copy of the top-level section ``section`` (e.g. ``fit``) with the scene's own
    overrides (``scenes/<scene>/<section>``) on top; a scene the config does not define gets
    the top-level section as it is. The workflow's rules and the CLI read a scene's settings
    through this one function."""
    out = dict(config.get(section) or {})
    out.update(((config.get("scenes") or {}).get(scene) or {}).get(section) or {})
    return out
