# Lens distortion (issue 24): a captured sequence whose intri.yml has non-zero dist_<cam> is
# undistorted once, here, to pinhole working cameras; every later stage (masks, flows, normals,
# fit, train_field, render_*, evaluate_field) reads that copy instead of data/{scene}/{seq}:
#   undistort -> results/{scene}/{seq}/undistorted/  (images/, masks/, normals/, gt/masks, backgrounds/,
#                intri.yml of the working cameras, extri.yml, original_intri.yml, undistort.json)
# The decision is anidress_core.io.scene.distorted_cameras / sequence_source, taken here at DAG time
# by undistorted_dir(); pinhole sequences (all synthetic scenes) have no undistort job.
# The rule has no params: no setting reruns it, only a change of data/{scene} (computed once, reused
# by every stage and variant).

_UNDISTORT_SEQUENCES = sorted({s["name"] for sc in config["scenes"].values() for s in sc["sequences"]})


@functools.lru_cache(maxsize=None)  # read once per Snakemake run (called by many input functions)
def undistorted_dir(scene, seq):
    """results/<scene>/<seq>/undistorted when the sequence's cameras have lens distortion, else None.

    Synthetic scenes are rendered by pinhole cameras (decided from the config: their data may not
    exist yet at DAG-build time); a captured scene's intri.yml is read (no file: None, and rule
    validate_scene names what is missing).
    """
    if config["scenes"][scene]["synthetic"]:
        return None
    scene_dir = os.path.join("data", scene)
    if not os.path.isfile(os.path.join(scene_dir, seq, "intri.yml")):
        return None
    from anidress_core.io.scene_info import distorted_cameras  # torch-free; here: only a captured scene needs it

    return f"results/{scene}/{seq}/undistorted" if distorted_cameras(scene_dir, seq) else None


def undistorted_input(scene, seq):
    """The input a stage rule adds for one sequence: the undistorted folder, or nothing ([])."""
    return undistorted_dir(scene, seq) or []


def sequence_data_dir(scene, seq, sub):
    """Where a stage reads a sequence's shipped <sub> (masks, normals): data/<scene>/<seq>/<sub>, or its
    undistorted copy. A folder inside the undistorted folder is no input of its own (it lies in rule
    undistort's directory output): rules depend on undistorted_input(scene, seq) instead."""
    und = undistorted_dir(scene, seq)
    return f"{und}/{sub}" if und else f"data/{scene}/{seq}/{sub}"


rule undistort:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "cameras", "images", "masks", "normals", "backgrounds", "gt_masks")),
    output:
        directory("results/{scene}/{seq}/undistorted"),
    log:
        "logs/{scene}/{seq}/undistort.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/undistort.tsv"
    threads: 2
    resources:
        mem_mb=2000,
        runtime=20,
    wildcard_constraints:
        seq="|".join(_UNDISTORT_SEQUENCES) or "^$",
    script:
        "../scripts/undistort.py"


def rule_input(path):
    """``path`` as a rule input, or [] when it lies inside an undistorted folder (the rule depends on
    undistorted_input() for it: a path inside another rule's directory output is no input of its own)."""
    return [] if "/undistorted/" in path else path
