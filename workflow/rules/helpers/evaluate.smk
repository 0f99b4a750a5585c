# Helpers of workflow/rules/evaluate.smk: what the field's evaluation reads.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

def field_eval_renders(scene, seq, variant):
    """(kind, sequence, render folder) of everything evaluated for one trained field."""
    base = f"results/{scene}/{seq}/{variant}/renders"
    out = [("novel_view", seq, f"{base}/novel_view")]
    out += [("novel_pose", p, f"{base}/novel_pose/{p}") for p in field_sequences(scene, "novel_pose")]
    return out


def field_eval_undistorted(scene, seq, variant):
    """{sequence: undistorted folder} of the evaluated sequences whose cameras have lens distortion."""
    seqs = {r[1] for r in field_eval_renders(scene, seq, variant)}
    return {s: undistorted_dir(scene, s) for s in sorted(seqs) if undistorted_dir(scene, s)}


def field_eval_bodies(scene, seq, variant):
    """{sequence: refined body poses} of the evaluated sequences (rule refine_body; {} when it is off)."""
    seqs = {r[1] for r in field_eval_renders(scene, seq, variant)}
    return {s: body_dir(scene, s) for s in sorted(seqs) if body_dir(scene, s)}


def field_eval_masks(scene, seq, variant):
    """{sequence: masks folder} of the evaluated sequences without ground-truth masks (a captured scene's
    gt/masks): the masks the pipeline has, masks_dir() of helpers/cues.smk (shipped, or estimated by rule
    masks; in the working cameras of a distorted sequence). Synthetic scenes: {} (rule synth writes gt/)."""
    if config["scenes"][scene]["synthetic"]:
        return {}
    seqs = {r[1] for r in field_eval_renders(scene, seq, variant)}
    return {s: masks_dir(scene, s) for s in sorted(seqs) if not scene_part_files(scene, f"{s}/gt_masks")}
