# 2D cues for garment fitting (DESIGN.md §6, §7), per sequence of a scene:
#   masks   -> results/{scene}/{seq}/masks/<cam>/<frame>.png   (unless the sequence ships label masks; a human
#              parser's shipped masks are converted)
#   flows   -> results/{scene}/{seq}/flows/<cam>/<frame>.exr   (estimated; cues/flows/method files: shipped ones)
#   normals -> results/{scene}/{seq}/normals.json   (shipped normals checked, or the skip and why) and
#              results/{scene}/{seq}/normals/      (a captured sequence's normals in the pipeline's format and axes)
# The input functions masks_dir / flows_dir / normals_dir are what the fit rule uses.


rule masks:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "body", "cameras", "smpl", "images", "backgrounds", "masks", "masks_parsing")),
        template=_cue_template,
        undistorted=lambda wc: undistorted_input(wc.scene, wc.seq),
    output:
        directory("results/{scene}/{seq}/masks"),
    log:
        "logs/{scene}/{seq}/masks.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/masks.tsv"
    params:
        masks=config["cues"]["masks"],
        cameras=config["cues"]["cameras"],
        convert=lambda wc: shipped_masks_converted(wc.scene, wc.seq),
        garment=lambda wc: has_garment(wc.scene),
    threads: 2
    priority: 2  # inputs of the garment fit (the demo's longest chain, see rule simulate)
    resources:
        mem_mb=2000,
        runtime=20,
    wildcard_constraints:
        seq="|".join(_ALL_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/masks.py"


rule flows:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "body", "cameras", "smpl", "images", "masks", "flows")),
        masks=lambda wc: rule_input(masks_dir(wc.scene, wc.seq)),
        template=_cue_template,
        undistorted=lambda wc: undistorted_input(wc.scene, wc.seq),
    output:
        directory("results/{scene}/{seq}/flows"),
    log:
        "logs/{scene}/{seq}/flows.log",
    benchmark:
        "benchmarks/runs/{scene}/{seq}/flows.tsv"
    params:
        masks=lambda wc: masks_dir(wc.scene, wc.seq),
        flows=config["cues"]["flows"],
        cameras=config["cues"]["cameras"],
    threads: 2
    priority: 2  # inputs of the garment fit (the demo's longest chain, see rule simulate)
    resources:
        mem_mb=2000,
        runtime=20,
    wildcard_constraints:
        seq="|".join(_ALL_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/flows.py"


rule normals:
    input:
        scene=scene_input,
        check=ancient("results/{scene}/scene_check.json"),
        files=scene_inputs_fn(("scene", "body", "cameras", "smpl", "normals")),
        template=lambda wc: _cue_template(wc) if shipped_normals_dir(wc.scene, wc.seq) else [],  # the check's body
        undistorted=lambda wc: undistorted_input(wc.scene, wc.seq),
    output:
        record="results/{scene}/{seq}/normals.json",
        maps=directory("results/{scene}/{seq}/normals"),
    log:
        "logs/{scene}/{seq}/normals.log",
    params:
        normals=lambda wc: shipped_normals_dir(wc.scene, wc.seq),
        convert=lambda wc: normals_dir(wc.scene, wc.seq) == f"results/{wc.scene}/{wc.seq}/normals",
        reason=lambda wc: _normals_skip_reason(wc.scene, wc.seq),
        cameras=config["cues"]["cameras"],
    threads: 2
    priority: 2  # inputs of the garment fit (the demo's longest chain, see rule simulate)
    resources:
        mem_mb=2000,
        runtime=10,
    wildcard_constraints:
        seq="|".join(_ALL_SEQUENCES) or "^$",
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/normals.py"
