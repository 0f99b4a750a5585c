# Garment dynamics fitting (paper §3.2, DESIGN.md §8) and its evaluation against ground truth:
#   fit          -> results/{scene}/{seq}/garment_poses.npz            (loss variant fit/loss)
#   fit_ablation -> results/{scene}/{seq}/fit_ablations/{ablation}/garment_poses.npz
#   fit_eval     -> results/{scene}/{seq}/fit_metrics.csv              (synthetic scenes)
# Cues: the pipeline's (rules masks / flows / normals in cues.smk, via masks_dir, flows_dir,
# normals_dir), or with fit/cues: ground_truth the synthetic scene's true masks and flows
# and its shipped (degraded) normals -- an upper bound for the fitting alone.


rule fit:
    input:
        unpack(fit_inputs),
    output:
        "results/{scene}/{seq}/garment_poses.npz",
    log:
        "logs/{scene}/{seq}/fit.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/fit.tsv"
    params:
        fit=lambda wc: fit_params(wc.scene),
        cues=lambda wc: fit_cue_dirs(wc.scene, wc.seq),
    threads: 2
    priority: 2  # the garment chain (cues, motions, simulate, rig, fit, the full field): the demo's longest, so first
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    wildcard_constraints:
        seq="|".join(_FIT_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/fit.py"


rule fit_ablation:
    input:
        unpack(fit_inputs),
    output:
        "results/{scene}/{seq}/fit_ablations/{ablation}/garment_poses.npz",
    log:
        "logs/{scene}/{seq}/fit_ablations/{ablation}.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/fit_ablations/{ablation}.tsv"
    params:
        fit=lambda wc: {**fit_params(wc.scene),  # the ablation is the loss
                        "loss": check_fit_variant(wc.ablation, f"target {wc.scene}/{wc.seq}/fit_ablations/"
                                                               f"{wc.ablation}")},
        cues=lambda wc: fit_cue_dirs(wc.scene, wc.seq),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
        gpu=0,
    wildcard_constraints:
        seq="|".join(_FIT_SEQUENCES) or "^$",
        ablation="[A-Za-z0-9_]+",  # a variant name: checked by the params function (check_fit_variant)
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/fit.py"


rule fit_eval:
    input:
        scene="data/{scene}",  # synthetic scenes only (ground truth): rule synth's folder
        check=ancient("results/{scene}/scene_check.json"),
        rig="results/{scene}/rig.npz",
        full="results/{scene}/{seq}/garment_poses.npz",
        ablations=lambda wc: [f"results/{wc.scene}/{wc.seq}/fit_ablations/{a}/garment_poses.npz"
                              for a in config["fit"]["ablations"]],
    output:
        "results/{scene}/{seq}/fit_metrics.csv",
    log:
        "logs/{scene}/{seq}/fit_eval.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/fit_eval.tsv"
    params:
        ablations=config["fit"]["ablations"],
        eval=config["fit"]["eval"],
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    wildcard_constraints:
        seq="|".join(_FIT_SEQUENCES) or "^$",
        scene="|".join(SYNTHETIC_SCENES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/fit_eval.py"
