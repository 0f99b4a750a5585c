# Garment template, body motions to simulate, cloth simulation (DESIGN.md §4).
# Only scenes with a garment (kind skirt/dress) request these; a tight-clothed scene
# skips them (DESIGN.md §6).


rule template:
    input:
        scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "body", "garment")),
    output:
        ply="results/{scene}/template.ply",
        npz="results/{scene}/template.npz",
    log:
        "logs/{scene}/template.log",
    benchmark:
        "benchmarks/runs/{scene}/template.tsv"
    params:
        kind=lambda wc: config["scenes"][wc.scene]["kind"],
        vertices=config["template"]["vertices"],
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/template.py"


rule motions:
    input:
        scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=lambda wc: scene_inputs(wc.scene, ("scene", "body", "smpl"), motion_sequences(wc.motion)),
        amass=lambda wc: motion_params(wc).get("amass", []),  # the AMASS file(s) of an amass-<stem> motion
        body=lambda wc: body_input(wc.scene, motion_sequences(wc.motion)[0]) if motion_sequences(wc.motion) else [],
    output:
        "results/{scene}/motions/{motion}.npz",
    log:
        "logs/{scene}/motions/{motion}.log",
    params:
        sim=motion_params,
    threads: 1
    priority: 2  # the garment chain (cues, motions, simulate, rig, fit, then the full field) is the demo's longest: first
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/motions.py"


rule simulate:
    input:
        template="results/{scene}/template.npz",
        motion="results/{scene}/motions/{motion}.npz",
        scene=scene_input,
        files=scene_inputs_fn(("scene", "body")),
    output:
        "results/{scene}/sim/{motion}.npz",
    log:
        "logs/{scene}/simulate/{motion}.log",
    benchmark:
        "benchmarks/runs/{scene}/simulate/{motion}.tsv"
    params:
        cloth=config["simulate"]["cloth"],
    threads: 1
    priority: 2  # the garment chain (cues, motions, simulate, rig, fit, then the full field) is the demo's longest: first
    resources:
        mem_mb=2000,
        runtime=60,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/simulate.py"


rule simulate_ensemble:
    input:
        template="results/{scene}/template.npz",
        motion="results/{scene}/motions/seq-{seq}.npz",
        scene=scene_input,
        files=scene_inputs_fn(("scene", "body")),
    output:
        "results/{scene}/sim_ensemble/seq-{seq}.npz",
    log:
        "logs/{scene}/simulate_ensemble/seq-{seq}.log",
    benchmark:
        "benchmarks/runs/{scene}/simulate_ensemble/seq-{seq}.tsv"
    params:
        cloth=config["simulate"]["cloth"],
        bend_stiffness=config["simulate"]["ensemble_bend_stiffness"],
        settle_frames=config["simulate"]["ensemble_settle_frames"],
        # the arrays the file holds: files written before `spread` or `members` existed are remade (params
        # rerun trigger)
        arrays=["frames", "spread", "members"],
    threads: 1
    priority: 2  # the garment chain (cues, motions, simulate, rig, fit, then the full field) is the demo's longest: first
    resources:
        mem_mb=2000,
        runtime=120,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/simulate_ensemble.py"
