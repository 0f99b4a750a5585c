# Scene validation (issue 8, bad input): a malformed scene stops here with one message
# naming the file and the problem, before any long computation; nothing is written
# unless the scene passes. Downstream rules that read data/{scene} take
# results/{scene}/scene_check.json as an input (wired in the rules that read the scene).


rule validate_scene:
    input:
        "data/{scene}",
    output:
        "results/{scene}/scene_check.json",
    log:
        "logs/{scene}/validate_scene.log",
    benchmark:
        "benchmarks/runs/{scene}/validate_scene.tsv"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    script:
        "../scripts/validate_scene.py"
