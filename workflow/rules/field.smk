# Pose-driven radiance field (paper §3.3, DESIGN.md §9), per training sequence and variant:
#   train_field       -> results/{scene}/{seq}/{variant}/field.pt
#   render_novel_view -> results/{scene}/{seq}/{variant}/renders/novel_view/          (test cameras, training frames)
#   render_novel_pose -> results/{scene}/{seq}/{variant}/renders/novel_pose/{pose_seq}/  (all cameras, held-out sequence)
#   render_library    -> results/{scene}/{seq}/{variant}/renders/library/{motion}/    (lib-<name>: simulated garment poses)
# Variants: full (body joints + garment bones) and body_only (the paper's "w/o G"); a
# tight-clothed scene has no garment and trains `full` only (body joints, no rig).


wildcard_constraints:
    variant="|".join(FIELD_VARIANTS),


rule train_field:
    input:
        unpack(field_train_inputs),
    output:
        "results/{scene}/{seq,[^/]+}/{variant}/field.pt",
    log:
        "logs/{scene}/{seq}/{variant}/train.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/{variant}/train.tsv"
    params:
        field=lambda wc: field_train_params(wc.variant),
        lpips=field_lpips_params(),
        masks=lambda wc: field_masks(wc.scene, wc.seq),
    threads: 1
    priority: 1  # the trainings before the renders and scores of another scene
    resources:
        mem_mb=6000,
        runtime=30,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/train.py"


rule render_novel_view:
    input:
        unpack(field_render_inputs),
    output:
        directory("results/{scene}/{seq,[^/]+}/{variant}/renders/novel_view"),
    log:
        "logs/{scene}/{seq}/{variant}/render_novel_view.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/{variant}/render_novel_view.tsv"
    params:
        field=lambda wc: field_render_params("novel_view", wc.variant),
        kind="novel_view",
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/render.py"


rule render_novel_pose:
    input:
        unpack(field_render_inputs),
    output:
        directory("results/{scene}/{seq,[^/]+}/{variant}/renders/novel_pose/{pose_seq,[^/]+}"),
    log:
        "logs/{scene}/{seq}/{variant}/render_novel_pose_{pose_seq}.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/{variant}/render_novel_pose_{pose_seq}.tsv"
    params:
        field=lambda wc: field_render_params("novel_pose", wc.variant),
        kind="novel_pose",
    threads: 1
    priority: 1  # the longest renders (every camera of the held-out sequence) before the shorter ones
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/render.py"


rule render_library:
    input:
        unpack(field_render_inputs),
    output:
        directory("results/{scene}/{seq,[^/]+}/{variant}/renders/library/{motion,lib-[^/]+}"),
    log:
        "logs/{scene}/{seq}/{variant}/render_library_{motion}.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/{variant}/render_library_{motion}.tsv"
    params:
        field=lambda wc: field_render_params("library", wc.variant),
        kind="library",
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/render.py"
