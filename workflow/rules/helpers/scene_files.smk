# Helpers of workflow/rules/scene_files.smk: which files of a captured scene each part holds, and the
# manifests the rules take.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

import bisect
import functools
import re

import yaml

SCENE_PARTS = ("scene", "body", "garment")
"""scene.yaml; the body model file (scene.yaml body_model/file); the garment template's folder and texture."""
SEQUENCE_PARTS = {"cameras": None, "smpl": "smpl", "images": "images", "masks": "masks",
                  "masks_parsing": "masks-parsing", "normals": "normals", "flows": "flows",
                  "backgrounds": "backgrounds", "gt_masks": os.path.join("gt", "masks")}
"""Parts of a sequence <seq>/: intri.yml + extri.yml, and the files under each folder."""
ALL_PARTS = SCENE_PARTS + tuple(SEQUENCE_PARTS)


@functools.lru_cache(maxsize=None)
def _scene_yaml(scene):
    """data/<scene>/scene.yaml as a dict ({} when missing or malformed: rule validate_scene says why)."""
    try:
        with open(os.path.join("data", scene, "scene.yaml")) as fh:
            info = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError):
        return {}
    return info if isinstance(info, dict) else {}


@functools.lru_cache(maxsize=None)
def _scene_listing(scene):
    """Every file under data/<scene>, relative to it and sorted (hidden names skipped; symlinks followed)."""
    root = os.path.join("data", scene)
    out = []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        rel = os.path.relpath(dirpath, root)
        out += [os.path.normpath(os.path.join(rel, f)) for f in filenames if not f.startswith(".")]
    return tuple(sorted(out))


def _under(listing, folder):
    """The files of ``listing`` under ``folder`` (relative paths)."""
    prefix = folder.rstrip("/") + os.sep
    i = bisect.bisect_left(listing, prefix)  # listing is sorted: the folder's files are one run
    j = i
    while j < len(listing) and listing[j].startswith(prefix):
        j += 1
    return list(listing[i:j])


def scene_sequences(scene):
    """The sequences of a scene: the config's, then any other scene.yaml names (validate_scene checks them all)."""
    names = [s["name"] for s in config["scenes"][scene]["sequences"]]
    for s in _scene_yaml(scene).get("sequences") or []:
        name = s.get("name") if isinstance(s, dict) else s
        if isinstance(name, str) and name not in names:
            names.append(name)
    return names


def scene_part_files(scene, part):
    """data/<scene>/... files of one part ("scene", "body", "garment" or "<seq>/<sequence part>") that exist."""
    listing, info, rel = _scene_listing(scene), _scene_yaml(scene), []
    if part == "scene":
        rel.append("scene.yaml")
    elif part == "body":
        if isinstance(info.get("body_model"), dict) and info["body_model"].get("file"):
            rel.append(os.path.normpath(str(info["body_model"]["file"])))
    elif part == "garment":
        tpl = info.get("garment_template")
        if tpl:
            folder = os.path.dirname(os.path.normpath(str(tpl)))
            rel += _under(listing, folder) if folder else [os.path.normpath(str(tpl))]
        if info.get("garment_texture"):
            rel.append(os.path.normpath(str(info["garment_texture"])))
    else:
        seq, sub = part.split("/")
        rel += [f"{seq}/intri.yml", f"{seq}/extri.yml"] if sub == "cameras" else \
            _under(listing, os.path.join(seq, SEQUENCE_PARTS[sub]))
    present = set(listing)
    return [os.path.join("data", scene, f) for f in dict.fromkeys(rel) if f in present]


def scene_inputs(scene, parts, seqs=()):
    """The manifests (rule scene_files) of ``parts`` (SCENE_PARTS for the scene, SEQUENCE_PARTS for each of
    ``seqs``) as rule inputs; [] for a synthetic scene (its folder is rule synth's output)."""
    if config["scenes"][scene]["synthetic"]:
        return []
    unknown = set(parts) - set(ALL_PARTS)
    if unknown:
        raise ValueError(f"scene_inputs: unknown parts {sorted(unknown)}; known: {ALL_PARTS}")
    names = [p for p in SCENE_PARTS if p in parts]
    names += [f"{seq}/{p}" for seq in seqs for p in SEQUENCE_PARTS if p in parts]
    # a part without files (no shipped masks, no garment) has no manifest: files added later change the
    # DAG or the set of inputs (rerun trigger `input`)
    return [f"results/{scene}/inputs/{n}.json" for n in names if n == "scene" or scene_part_files(scene, n)]


def scene_input(wildcards):
    """The scene folder as a rule's `scene` input: synth's output (synthetic), else ancient() (the manifests count)."""
    path = f"data/{wildcards.scene}"
    return path if config["scenes"][wildcards.scene]["synthetic"] else ancient(path)


def scene_inputs_fn(parts, seqs=None):
    """Input function: scene_inputs() of the job's scene for ``parts`` and the sequences ``seqs(wildcards)``
    (default: the job's {seq}, else none)."""
    def fn(wildcards):
        s = seqs(wildcards) if seqs else ([wildcards.seq] if hasattr(wildcards, "seq") else [])
        return scene_inputs(wildcards.scene, parts, s)
    return fn


_CAPTURED_SEQUENCES = sorted({q for s, c in config["scenes"].items() if not c["synthetic"] for q in scene_sequences(s)})
_PART_NAMES = "|".join(SCENE_PARTS) + "|(" + ("|".join(re.escape(q) for q in _CAPTURED_SEQUENCES) or "^$") + \
    ")/(" + "|".join(SEQUENCE_PARTS) + ")"
