# Synthetic scenes with full ground truth (DESIGN.md §5).


rule synth:
    output:
        directory("data/{scene}"),
    log:
        "logs/{scene}/synth.log",
    benchmark:
        "benchmarks/runs/{scene}/synth.tsv"
    params:
        scene=synth_params,
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    wildcard_constraints:
        scene="|".join(SYNTHETIC_SCENES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/synth.py"
