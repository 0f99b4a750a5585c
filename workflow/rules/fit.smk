# Garment dynamics fitting (paper §3.2, DESIGN.md §8) and its evaluation against ground truth:
#   fit          -> results/{scene}/{seq}/garment_poses.npz            (loss variant fit/loss)
#   fit_ablation -> results/{scene}/{seq}/fit_ablations/{ablation}/garment_poses.npz
#   fit_eval     -> results/{scene}/{seq}/fit_metrics.csv              (synthetic scenes)
# Cues: the pipeline's (rules masks / flows / normals in cues.smk, via masks_dir, flows_dir,
# normals_dir), or with fit/cues: ground_truth the synthetic scene's true masks and flows
# and its shipped (degraded) normals -- an upper bound for the fitting alone.

# The loss variants are anidress_core.fit.variants.VARIANTS (the one list). Importing it imports torch
# (~1 s), so it is imported only when a name other than the default 'pipeline' must be checked: a
# non-default fit/loss or fit/ablations here, a fit_ablation job in the DAG (check_fit_variant); the
# default config parses without torch (issue 22: a no-op rerun in a few seconds).
_DEFAULT_FIT_VARIANT = "pipeline"  # the schema's fit/loss default; tests/workflow/test_parse_time.py: a VARIANTS key


def check_fit_variant(name, where):
    """``name`` if it is a loss variant of anidress_core.fit.variants.VARIANTS, else a ValueError naming ``where``."""
    if name == _DEFAULT_FIT_VARIANT:
        return name
    from anidress_core.fit.variants import VARIANTS

    if name not in VARIANTS:
        raise ValueError(f"{where}: unknown loss variant {name!r}; choose from {list(VARIANTS)}")
    return name


for _v in [config["fit"]["loss"], *config["fit"]["ablations"]]:
    check_fit_variant(_v, "config fit")


def _fit_sequences(scene):
    return [s["name"] for s in config["scenes"][scene]["sequences"]]


_FIT_SEQUENCES = sorted({s for sc in config["scenes"] for s in _fit_sequences(sc)})


def fit_cue_dirs(scene, seq):
    """{masks, flows, normals (or None), source} folders the fit of one sequence reads."""
    if config["fit"]["cues"] == "ground_truth":
        if not config["scenes"][scene]["synthetic"]:
            raise ValueError(f"fit/cues is 'ground_truth' but scene {scene!r} is not synthetic")
        normals = None if config["cues"]["normals"] == "off" else f"data/{scene}/{seq}/normals"
        return {"masks": f"data/{scene}/{seq}/gt/masks", "flows": f"data/{scene}/{seq}/gt/flows",
                "normals": normals, "source": "ground_truth (gt/masks, gt/flows, shipped normals)"}
    return {"masks": masks_dir(scene, seq), "flows": flows_dir(scene, seq), "normals": normals_dir(scene, seq),
            "source": "pipeline (rules masks, flows, normals)"}


def fit_inputs(wildcards):
    """Rig, template, scene and (pipeline cues) the cue rule outputs of one sequence."""
    scene, seq = wildcards.scene, wildcards.seq
    if not has_garment(scene):
        raise ValueError(f"scene {scene!r} has no garment (kind tight): nothing to fit")
    inp = {"rig": f"results/{scene}/rig.npz", "template": f"results/{scene}/template.npz",
           "scene": scene_input(wildcards), "check": ancient(f"results/{scene}/scene_check.json"),
           "files": scene_inputs(scene, ("scene", "body", "garment", "cameras", "smpl", "images", "masks", "normals"),
                                [seq])}
    if config["fit"]["cues"] != "ground_truth":
        d = fit_cue_dirs(scene, seq)
        if d["masks"].startswith("results/") and rule_input(d["masks"]):
            inp["masks"] = d["masks"]
        inp["undistorted"] = undistorted_input(scene, seq)  # undistort.smk: images, cameras, shipped cues
        inp["flows"] = d["flows"]
        inp["normals"] = normals_record(scene, seq)
    return inp


def fit_params(scene):
    """The settings that shape a fit of one scene: the fit section with the scene's own overrides
    (scenes/<scene>/fit), the ablation list and eval settings excluded (no rerun when they change)."""
    return {k: v for k, v in scene_section(config, "fit", scene).items() if k not in ("ablations", "eval", "threads")}


def fit_outputs(scene):
    """Every fit target of a garment scene: poses per sequence (+ ablations) and, if synthetic, the metrics."""
    if not has_garment(scene):
        return []
    out = []
    for seq in _fit_sequences(scene):
        out.append(f"results/{scene}/{seq}/garment_poses.npz")
        out += [f"results/{scene}/{seq}/fit_ablations/{a}/garment_poses.npz" for a in config["fit"]["ablations"]]
        if config["scenes"][scene]["synthetic"]:
            out.append(f"results/{scene}/{seq}/fit_metrics.csv")
    return out


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
        ablation="full",
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=0,
    wildcard_constraints:
        seq="|".join(_FIT_SEQUENCES) or "^$",
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
        fit=lambda wc: {k: v for k, v in fit_params(wc.scene).items() if k != "loss"},  # the ablation is the loss
        cues=lambda wc: fit_cue_dirs(wc.scene, wc.seq),
        ablation=lambda wc: check_fit_variant(wc.ablation, f"target {wc.scene}/{wc.seq}/fit_ablations/{wc.ablation}"),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
        gpu=0,
    wildcard_constraints:
        seq="|".join(_FIT_SEQUENCES) or "^$",
        ablation="[A-Za-z0-9_]+",  # a variant name: checked by the params function (check_fit_variant)
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
    script:
        "../scripts/fit_eval.py"
