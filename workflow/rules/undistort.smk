# Lens distortion (issue 24): a captured sequence whose intri.yml has non-zero dist_<cam> is
# undistorted once, here, to pinhole working cameras; every later stage (masks, flows, normals,
# fit, train_field, render_*, evaluate_field) reads that copy instead of data/{scene}/{seq}:
#   undistort -> results/{scene}/{seq}/undistorted/  (images/, masks/, normals/, flows/, gt/masks, backgrounds/,
#                intri.yml of the working cameras, extri.yml, original_intri.yml, undistort.json)
# The decision is anidress_core.io.scene_info.distorted_cameras / io.scene.sequence_source, taken at
# DAG time by undistorted_dir() (helpers/undistort.smk); pinhole sequences (all synthetic scenes) have
# no undistort job. The rule has no params: no setting reruns it, only a change of the sequence's files
# (rule scene_files; computed once, reused by every stage and variant).


rule undistort:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "cameras", "images", "masks", "masks_parsing", "normals", "flows", "backgrounds",
                               "gt_masks")),
    output:
        directory("results/{scene}/{seq}/undistorted"),
    log:
        "logs/{scene}/{seq}/undistort.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/undistort.tsv"
    threads: 2
    resources:
        mem_mb=lambda wc: undistort_mem_mb(*config["scenes"][wc.scene]["image_size"]),  # from the image size
        runtime=20,
    wildcard_constraints:
        seq="|".join(_UNDISTORT_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/undistort.py"
