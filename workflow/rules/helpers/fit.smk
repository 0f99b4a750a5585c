# Helpers of workflow/rules/fit.smk: the loss variants, the cues and the settings of a garment fit.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

from anidress_core.config import section_defaults

# The loss variants are anidress_core.fit.variants.VARIANTS (the one list). Importing it imports torch
# (~1 s), so it is imported only when a name other than the default 'pipeline' must be checked: a
# non-default fit/loss or fit/ablations here, a fit_ablation job in the DAG (check_fit_variant); the
# default config parses without torch (issue 22: a no-op rerun in a few seconds).
_DEFAULT_FIT_VARIANT = "pipeline"  # the schema's fit/loss default; tests/workflow/test_parse_time.py: a VARIANTS key


def check_fit_variant(name, where):
    """``name`` if it is a loss variant of anidress_core.fit.variants.VARIANTS, else a ValueError naming ``where``."""
    if name == _DEFAULT_FIT_VARIANT:
        return name
    from anidress_core.fit.variants import VARIANTS

    if name not in VARIANTS:
        raise ValueError(f"{where}: unknown loss variant {name!r}; choose from {list(VARIANTS)}")
    return name


for _v in [config["fit"]["loss"], *config["fit"]["ablations"]]:
    check_fit_variant(_v, "config fit")


def _fit_sequences(scene):
    return [s["name"] for s in config["scenes"][scene]["sequences"]]


_FIT_SEQUENCES = sorted({s for sc in config["scenes"] for s in _fit_sequences(sc)})


def fit_cue_dirs(scene, seq):
    """{masks, flows, normals (or None), source} folders the fit of one sequence reads."""
    if config["fit"]["cues"] == "ground_truth":
        if not config["scenes"][scene]["synthetic"]:
            raise ValueError(f"fit/cues is 'ground_truth' but scene {scene!r} is not synthetic")
        normals = None if config["cues"]["normals"] == "off" else f"data/{scene}/{seq}/normals"
        return {"masks": f"data/{scene}/{seq}/gt/masks", "flows": f"data/{scene}/{seq}/gt/flows",
                "normals": normals, "source": "ground_truth (gt/masks, gt/flows, shipped normals)"}
    return {"masks": masks_dir(scene, seq), "flows": flows_dir(scene, seq), "normals": normals_dir(scene, seq),
            "source": "pipeline (rules masks, flows, normals)"}


def fit_inputs(wildcards):
    """Rig, template, scene, the rig's simulated motions, (pipeline cues) the cue rule outputs of one sequence and
    (fit/prior_reference sim_ensemble) the ensemble's mean simulation of it."""
    scene, seq = wildcards.scene, wildcards.seq
    if not has_garment(scene):
        raise ValueError(f"scene {scene!r} has no garment (kind tight): nothing to fit")
    inp = {"rig": f"results/{scene}/rig.npz", "template": f"results/{scene}/template.npz",
           "scene": scene_input(wildcards), "check": ancient(f"results/{scene}/scene_check.json"),
           "files": scene_inputs(scene, ("scene", "body", "garment", "cameras", "smpl", "images", "masks", "normals"),
                                [seq])}
    if config["fit"]["cues"] != "ground_truth":
        d = fit_cue_dirs(scene, seq)
        if d["masks"].startswith("results/") and rule_input(d["masks"]):
            inp["masks"] = d["masks"]
        inp["undistorted"] = undistorted_input(scene, seq)  # undistort.smk: images, cameras, shipped cues
        inp["flows"] = d["flows"]
        inp["normals"] = normals_record(scene, seq)
    # the body motions of the rig's simulations: the database of the `nearest` baseline, read by the stage only
    # for that variant (the rig depends on them already, so a change of them reruns the fit either way)
    inp["motions"] = [f"results/{scene}/motions/{m}.npz" for m in sim_motion_names(scene)]
    inp["body"] = body_input(scene, seq)  # refined body poses (helpers/body.smk), or none
    if scene_section(config, "fit", scene).get("prior_reference", "sim_ensemble") == "sim_ensemble":
        # L_prior's reference (rule simulate_ensemble)
        inp["sim_ensemble"] = f"results/{scene}/sim_ensemble/seq-{seq}.npz"
    return inp


def fit_params(scene):
    """The settings that shape a fit of one scene: the fit section with the scene's own overrides
    (scenes/<scene>/fit), the ablation list and eval settings excluded (no rerun when they change)."""
    return {k: v for k, v in scene_section(config, "fit", scene).items() if k not in ("ablations", "eval", "threads")}


def fit_outputs(scene):
    """Every fit target of a garment scene: poses per sequence (+ ablations) and, if synthetic, the metrics."""
    if not has_garment(scene):
        return []
    out = []
    for seq in _fit_sequences(scene):
        out.append(f"results/{scene}/{seq}/garment_poses.npz")
        out += [f"results/{scene}/{seq}/fit_ablations/{a}/garment_poses.npz" for a in config["fit"]["ablations"]]
        if config["scenes"][scene]["synthetic"]:
            out.append(f"results/{scene}/{seq}/fit_metrics.csv")
    return out


def fit_texture_check(scene):
    """The param of rule validate_scene, {"losses", "setting"} when a fit of this captured garment scene samples the
    garment texture (L_anchor with anchor_reference 'texture' and a weight > 0, as stages/fit.py decides: rule
    fit's fit/loss and the fit/ablations) and the scene has no texture; else None (synthetic scenes: rule
    synth writes the texture). Only the outcome is the param: a fit setting changes it only when the check's
    answer changes. (A param that followed the fit settings would rerun validate_scene with each of them, and
    snakemake#4166 would then skip rule fit in that run, see scene_files.smk.)"""
    if config["scenes"][scene]["synthetic"] or not has_garment(scene):
        return None
    from anidress_core.io.scene_info import garment_texture_path  # (cv2) only for a captured scene

    if os.path.isfile(garment_texture_path(os.path.join("data", scene), _scene_yaml(scene))):
        return None
    section = fit_params(scene)
    losses = list(dict.fromkeys([section["loss"], *config["fit"]["ablations"]]))
    if losses == [_DEFAULT_FIT_VARIANT]:  # the section as written (its defaults filled), without torch
        full = section_defaults("fit", section)
        needing = losses if full["anchor_reference"] == "texture" and full["weights"]["anchor"] > 0 else []
    else:
        from anidress_core.fit.config import FitConfig

        cfgs = {loss: FitConfig.from_config(section, loss) for loss in losses}
        needing = [loss for loss, c in cfgs.items() if c.anchor_reference == "texture" and c.weights.anchor > 0]
    if not needing:
        return None
    own = "anchor_reference" in (config["scenes"][scene].get("fit") or {})
    return {"losses": needing, "setting": f"scenes/{scene}/fit/anchor_reference" if own else "fit/anchor_reference"}
