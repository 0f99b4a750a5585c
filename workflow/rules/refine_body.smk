# Body poses refined against the masks (issue 24 item 5; anidress_core.body.refine): where a scene has
# refine_body enabled (config section refine_body, per scene scenes/<scene>/refine_body), every sequence's
# EasyMocap poses (Rh, Th, joint rotations) are refined against its masks (masks_dir() of
# helpers/cues.smk: shipped or rule masks, in the cameras of cues/cameras) before anything poses the body:
#   refine_body -> results/{scene}/{seq}/body/  (smpl/<frame>.json, refine_body.json: settings, body IoU)
# body_input() (helpers/body.smk) adds it to rules motions, fit, fit_ablation, train_field, render_* and
# evaluate_field, which read it instead of data/{scene}/{seq}/smpl. Rule masks uses the poses as given
# (it runs before: the refinement needs its masks).


rule refine_body:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "body", "cameras", "smpl", "masks")),
        masks=lambda wc: refine_body_masks_input(wc.scene, wc.seq),
        undistorted=lambda wc: undistorted_input(wc.scene, wc.seq),
    output:
        directory("results/{scene}/{seq}/body"),
    log:
        "logs/{scene}/{seq}/refine_body.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/refine_body.tsv"
    params:
        refine=lambda wc: refine_body_params(wc.scene),
        masks=lambda wc: masks_dir(wc.scene, wc.seq),
    threads: 1
    priority: 2  # before the garment chain (motions, simulate, rig, fit)
    resources:
        mem_mb=4000,
        runtime=30,
    wildcard_constraints:
        seq="|".join(_ALL_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/refine_body.py"
