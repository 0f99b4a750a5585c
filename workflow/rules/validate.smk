# Scene validation (issue 8, bad input): a malformed scene stops here with one message
# naming the file and the problem, before any long computation; nothing is written
# unless the scene passes. Downstream rules that read data/{scene} take
# ancient(results/{scene}/scene_check.json) as an input (they run after it; its rerun does not rerun
# them). A captured scene's files reach it and the stage rules through rule scene_files (scene_files.smk).


rule validate_scene:
    input:
        scene_input,
        files=lambda wc: scene_inputs(wc.scene, ALL_PARTS, scene_sequences(wc.scene)),  # every file it checks
    output:
        "results/{scene}/scene_check.json",
    log:
        "logs/{scene}/validate_scene.log",
    benchmark:
        "benchmarks/runs/{scene}/validate_scene.tsv"
    params:
        fit_texture=lambda wc: fit_texture_check(wc.scene),  # a fit's garment texture the scene lacks, or None
        mask_plates=lambda wc: mask_plates_check(wc.scene),  # sequences rule masks needs plates for, or None
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/validate_scene.py"
