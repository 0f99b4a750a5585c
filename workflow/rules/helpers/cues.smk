# Helpers of workflow/rules/cues.smk: the folders of the 2D cues (masks, flows, normals) of a sequence.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

def _cue_sequences(scene):
    return [s["name"] for s in config["scenes"][scene]["sequences"]]


_ALL_SEQUENCES = sorted({s for sc in config["scenes"] for s in _cue_sequences(sc)})


def _shipped(scene, seq, what):
    """A captured (non-synthetic) sequence ships data/<scene>/<seq>/<what>/ when the folder exists.

    Synthetic scenes are decided from the config (their data may not exist yet at
    DAG-build time): they ship predicted normals and no masks (gt/ is evaluation only).
    """
    if config["scenes"][scene]["synthetic"]:
        return what == "normals"
    return os.path.isdir(os.path.join("data", scene, seq, what))


def cue_format(scene, kind):
    """scene.yaml's cues/<kind>/format of a captured scene (the pipeline's own format for a synthetic scene, or a
    scene.yaml that does not parse: rule validate_scene says why)."""
    from anidress_core.io.scene_info import SHIPPED_CUE_FORMATS, cue_formats  # torch-free

    if config["scenes"][scene]["synthetic"]:
        return SHIPPED_CUE_FORMATS[kind][0]
    try:
        return cue_formats(_scene_yaml(scene))[kind]["format"]
    except Exception:
        return SHIPPED_CUE_FORMATS[kind][0]


def shipped_masks_converted(scene, seq):
    """A sequence ships masks in a human parser's format (scene.yaml cues/masks/format schp): rule masks
    converts them to labels instead of estimating."""
    return _shipped(scene, seq, "masks") and cue_format(scene, "masks") != "labels"


def masks_dir(scene, seq):
    """The masks the fitting uses: shipped label masks data/<scene>/<seq>/masks (or their undistorted copy) as
    they are, else rule masks' (a human parser's masks converted, or estimated ones)."""
    if _shipped(scene, seq, "masks") and not shipped_masks_converted(scene, seq):
        return sequence_data_dir(scene, seq, "masks")  # undistort.smk: data/ or its undistorted copy
    return f"results/{scene}/{seq}/masks"


def flows_dir(scene, seq):
    """Forward optical flow t-1 -> t of a sequence, by rule flows (estimated, or shipped ones converted)."""
    return f"results/{scene}/{seq}/flows"


def shipped_normals_dir(scene, seq):
    """The shipped normal maps rule normals reads (data/<scene>/<seq>/normals or the undistorted copy), or None
    (no normals, or cues/normals: off): normal weight 0.

    Pass it to a rule as a param, not an input, since for a synthetic scene the folder lies
    inside the directory output data/<scene> of rule synth, Snakemake's ChildIOException;
    the input to depend on is normals_record(scene, seq).
    """
    if config["cues"]["normals"] == "off" or not _shipped(scene, seq, "normals"):
        return None
    return sequence_data_dir(scene, seq, "normals")  # undistort.smk: data/ or its undistorted copy


def normals_dir(scene, seq):
    """The normal maps the fit reads, or None (normal weight 0): a synthetic scene's own (pipeline format and
    axes) as they are; a captured sequence's as rule normals wrote them in results/<scene>/<seq>/normals (any
    shipped format, axis convention checked against the body and applied)."""
    shipped = shipped_normals_dir(scene, seq)
    if shipped is None or config["scenes"][scene]["synthetic"]:
        return shipped
    return f"results/{scene}/{seq}/normals"


def normals_record(scene, seq):
    """results/<scene>/<seq>/normals.json (rule normals), the folder used or the skip and its reason."""
    return f"results/{scene}/{seq}/normals.json"


def _normals_skip_reason(scene, seq):
    if config["cues"]["normals"] == "off":
        return "cues/normals is 'off' in the config"
    return f"data/{scene}/{seq}/normals does not exist: the sequence ships no normal maps"


def cues_outputs(scene):
    """Every cue target of a scene (for rule all), masks where estimated, flows and normals.json per sequence."""
    out = []
    for seq in _cue_sequences(scene):
        if masks_dir(scene, seq) == f"results/{scene}/{seq}/masks":  # estimated (not shipped, maybe undistorted)
            out.append(masks_dir(scene, seq))
        out += [flows_dir(scene, seq), normals_record(scene, seq)]
    return out


def _cue_template(wildcards):
    """The garment template: shape prior of the masks and flow prior of the flows (none: tight clothes)."""
    if has_garment(wildcards.scene):
        return f"results/{wildcards.scene}/template.npz"
    return []


def mask_plates_check(scene):
    """The param of rule validate_scene, {"sequences", "setting"} when rule masks would estimate masks of this
    captured scene against background plates (cues/masks/background: plate) for sequences that ship neither
    masks nor plates (data/<scene>/<seq>/backgrounds); else None (synthetic scenes: rule synth writes the
    plates; temporal_median needs none). Only the outcome is the param, as fit_texture_check's: a scene with
    its plates keeps None whatever the setting, so switching it reruns rule masks, not validate_scene (whose
    rerun would make snakemake#4166 skip rule masks in that run, see scene_files.smk)."""
    if config["scenes"][scene]["synthetic"] or config["cues"]["masks"]["background"] != "plate":
        return None
    seqs = [q for q in _cue_sequences(scene) if not _shipped(scene, q, "masks") and not _shipped(scene, q, "backgrounds")]
    return {"sequences": seqs, "setting": "cues/masks/background"} if seqs else None
