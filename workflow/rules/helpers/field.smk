# Helpers of workflow/rules/field.smk: the variants, inputs and settings of the radiance field's training and renders.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

FIELD_VARIANTS = ["full", "body_only"]


def field_variants(scene):
    """Variants trained for a scene: the configured ones; only `full` without a garment."""
    return [v for v in config["field"]["variants"] if has_garment(scene) or v == "full"]


def field_sequences(scene, role):
    return [s["name"] for s in config["scenes"][scene]["sequences"] if s["role"] == role]


def field_masks(scene, seq):
    """Masks the field trains on: masks_dir() of workflow/rules/helpers/cues.smk (estimated or shipped)."""
    if "masks_dir" not in globals():
        raise WorkflowError("rule train_field needs masks_dir() from workflow/rules/helpers/cues.smk (include it in the Snakefile)")
    return masks_dir(scene, seq)


def field_train_inputs(wildcards):
    """Scene, masks (when a rule makes them), template; rig and fitted garment poses for `full`."""
    scene, seq, variant = wildcards.scene, wildcards.seq, wildcards.variant
    inp = {"scene": scene_input(wildcards), "check": ancient(f"results/{scene}/scene_check.json"),
           "files": scene_inputs(scene, ("scene", "body", "cameras", "smpl", "images", "masks", "backgrounds"), [seq])}
    m = field_masks(scene, seq)
    if m.startswith("results/") and rule_input(m):
        inp["masks"] = m
    inp["undistorted"] = undistorted_input(scene, seq)  # undistort.smk: images and cameras
    inp["body"] = body_input(scene, seq)  # refined body poses (helpers/body.smk), or none
    if has_garment(scene):
        inp["template"] = f"results/{scene}/template.npz"
        if variant == "full":
            inp["rig"] = f"results/{scene}/rig.npz"
            inp["poses"] = f"results/{scene}/{seq}/garment_poses.npz"
    return inp


def field_render_inputs(wildcards):
    """Field, scene, template; for `full` the rig and the garment poses of the rendered sequence."""
    scene, variant = wildcards.scene, wildcards.variant
    inp = {"field": f"results/{scene}/{wildcards.seq}/{variant}/field.pt", "scene": scene_input(wildcards)}
    pose_seq = getattr(wildcards, "pose_seq", wildcards.seq)
    inp["files"] = scene_inputs(scene, ("scene", "body", "cameras", "smpl"), [pose_seq])  # cameras and body motion
    inp["undistorted"] = undistorted_input(scene, pose_seq)  # the cameras rendered (library: the training seq's)
    motion = getattr(wildcards, "motion", None)
    if motion is not None:
        inp["motion"] = f"results/{scene}/motions/{motion}.npz"
    else:
        inp["body"] = body_input(scene, pose_seq)  # refined body poses (helpers/body.smk), or none
    if has_garment(scene):
        inp["template"] = f"results/{scene}/template.npz"
        if variant == "full":
            inp["rig"] = f"results/{scene}/rig.npz"
            if motion is None:
                inp["poses"] = f"results/{scene}/{pose_seq}/garment_poses.npz"
    return inp


def _field_sampler(variant, training):
    """field/sampler as a variant uses it: the body_only garment margin only for body_only, the
    training-ray mask margin only when training."""
    s = dict(config["field"]["sampler"])
    if variant != "body_only":
        s.pop("body_only_garment_dilate_m")
    if not training:
        s.pop("mask_dilate_px")
    return s


def field_train_params(variant):
    """The settings that shape a trained field: model, priors, sampler, train (not checkpoint_every: a
    resumed training ends with the same field), the background of the training targets, device."""
    f = config["field"]
    train = {k: v for k, v in f["train"].items() if k != "checkpoint_every"}
    return {"model": f["model"], "priors": f["priors"], "sampler": _field_sampler(variant, True), "train": train,
            "render": {"background": f["render"]["background"]}, "device": f["device"]}


def field_lpips_params():
    """metrics/lpips: the weights of the LPIPS loss term, only where the term is on (field/train/lpips_weight > 0)."""
    return config["metrics"]["lpips"] if config["field"]["train"]["lpips_weight"] > 0 else None


def field_render_params(kind, variant):
    """Settings that shape the renders of one kind: the sampler, field/render (frame_stride for the
    sequences, library_frame_stride for the library motions; not the library list: one job per
    motion), device."""
    f = config["field"]
    drop = ("library", "frame_stride") if kind == "library" else ("library", "library_frame_stride")
    render = {k: v for k, v in f["render"].items() if k not in drop}
    return {"sampler": _field_sampler(variant, False), "render": render, "device": f["device"]}


def field_outputs(scene):
    """Every field target of a scene (for rule all), metrics per training sequence and variant,
    and the library-motion renders (no ground truth: rendered, not evaluated)."""
    out = []
    for seq in field_sequences(scene, "train"):
        for v in field_variants(scene):
            out.append(f"results/{scene}/{seq}/{v}/metrics.csv")
            if has_garment(scene):
                out += [f"results/{scene}/{seq}/{v}/renders/library/lib-{m}" for m in config["field"]["render"]["library"]]
    return out
