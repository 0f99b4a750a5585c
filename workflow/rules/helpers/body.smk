# Helpers of workflow/rules/refine_body.smk: where the stages read a sequence's body poses from.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).


def refine_body_params(scene):
    """The settings that shape refine_body's output for one scene: refine_body (scene overrides on top),
    without `enabled` (it decides whether the rule runs), and the cameras refined against (cues/cameras)."""
    s = scene_section(config, "refine_body", scene)
    return {"method": s["method"], "chunk": s["chunk"], "cameras": config["cues"]["cameras"]}


def refine_body_masks_input(scene, seq):
    """The masks refine_body reads, as an input where another job writes them (rule masks; else []). Shipped
    masks count through the scene's file manifests (helpers/scene_files.smk), as for the fit."""
    m = masks_dir(scene, seq)
    return rule_input(m) if m.startswith("results/") else []


def body_dir(scene, seq):
    """results/<scene>/<seq>/body (rule refine_body) when refine_body is enabled for the scene, else
    None: the stages that pose the body (motions, fit, train_field, render_*, evaluate_field) read the
    refined smpl/ there instead of data/<scene>/<seq>/smpl. The cue stages keep the poses as given."""
    return f"results/{scene}/{seq}/body" if scene_section(config, "refine_body", scene)["enabled"] else None


def body_input(scene, seq):
    """A rule's input for one sequence's body poses, the refined folder or nothing ([])."""
    return body_dir(scene, seq) or []
