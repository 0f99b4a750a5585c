# Garment rigging model: SSDR over every simulated sequence of a scene (DESIGN.md §4,
# paper §3.1). Only scenes with a garment request it (DESIGN.md §6).


rule rig:
    input:
        template="results/{scene}/template.npz",
        sims=lambda wc: expand("results/{scene}/sim/{motion}.npz", scene=wc.scene,
                               motion=sim_motion_names(wc.scene)),
    output:
        "results/{scene}/rig.npz",
    log:
        "logs/{scene}/rig.log",
    benchmark:
        "benchmarks/runs/{scene}/rig.tsv"
    params:
        rig=config["rig"],
    threads: 2
    priority: 2  # the garment chain (cues, motions, simulate, rig, fit, then the full field) is the demo's longest: first
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/rig.py"
