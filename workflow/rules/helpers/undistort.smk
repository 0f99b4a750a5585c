# Helpers of workflow/rules/undistort.smk: which sequences rule undistort undistorts, and where the
# stages read a sequence from.
# Functions and settings only, no rules (the Snakefile includes every helper file before the rules).

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


def undistort_mem_mb(height, width):
    """rule undistort's memory in MB for images of this size (anidress_core.io.scene_info.undistort_mem_mb)."""
    from anidress_core.io.scene_info import undistort_mem_mb as mem_mb  # torch-free

    return mem_mb(height, width)


def undistorted_input(scene, seq):
    """The input a stage rule adds for one sequence, the undistorted folder or nothing ([])."""
    return undistorted_dir(scene, seq) or []


def sequence_data_dir(scene, seq, sub):
    """Where a stage reads a sequence's shipped <sub> (masks, normals): data/<scene>/<seq>/<sub>, or its
    undistorted copy. A folder inside the undistorted folder is no input of its own (it lies in rule
    undistort's directory output): rules depend on undistorted_input(scene, seq) instead."""
    und = undistorted_dir(scene, seq)
    return f"{und}/{sub}" if und else f"data/{scene}/{seq}/{sub}"


def rule_input(path):
    """``path`` as a rule input, or [] when it lies inside an undistorted folder (the rule depends on
    undistorted_input() for it: a path inside another rule's directory output is no input of its own)."""
    return [] if "/undistorted/" in path else path
