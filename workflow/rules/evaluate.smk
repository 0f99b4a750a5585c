# Image metrics of the field's renders (DESIGN.md §10): per training sequence and variant
#   evaluate_field -> results/{scene}/{seq}/{variant}/metrics.csv (one row per kind, sequence, camera, frame)
#                     results/{scene}/{seq}/{variant}/metrics_summary.json (means per kind and sequence)
# Novel view: the test cameras on the training frames; novel pose: all cameras of every
# held-out sequence. Library-motion renders have no ground truth and are not evaluated. A captured scene
# without gt/masks is compared with its images under the pipeline's masks (mask_source "pipeline" in the
# csv; images without any mask are not scored: NaN, mask_source "none").


rule evaluate_field:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=lambda wc: scene_inputs(wc.scene, ("scene", "body", "cameras", "smpl", "images", "masks", "gt_masks"),
                                     sorted({r[1] for r in field_eval_renders(wc.scene, wc.seq, wc.variant)})),
        renders=lambda wc: [r[2] for r in field_eval_renders(wc.scene, wc.seq, wc.variant)],
        undistorted=lambda wc: list(field_eval_undistorted(wc.scene, wc.seq, wc.variant).values()),
        body=lambda wc: list(field_eval_bodies(wc.scene, wc.seq, wc.variant).values()),
        masks=lambda wc: [rule_input(m) for m in field_eval_masks(wc.scene, wc.seq, wc.variant).values()
                          if m.startswith("results/")],  # estimated by rule masks (shipped: the `files` manifests)
    output:
        csv="results/{scene}/{seq,[^/]+}/{variant}/metrics.csv",
        summary="results/{scene}/{seq,[^/]+}/{variant}/metrics_summary.json",
    log:
        "logs/{scene}/{seq}/{variant}/evaluate.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/{variant}/evaluate.tsv"
    params:
        metrics=config["metrics"],
        renders=lambda wc: field_eval_renders(wc.scene, wc.seq, wc.variant),
        undistorted=lambda wc: field_eval_undistorted(wc.scene, wc.seq, wc.variant),
        masks=lambda wc: field_eval_masks(wc.scene, wc.seq, wc.variant),
        bodies=lambda wc: field_eval_bodies(wc.scene, wc.seq, wc.variant),
    threads: 1
    resources:
        mem_mb=3000,
        runtime=20,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/evaluate.py"
