# Rule fit_eval: fitted garments (rule fit's + configured ablations) against the synthetic ground truth.
# fit_metrics.csv's method column names each fit by its loss variant (anidress_core/fit/variants.py):
# rule fit's by the variant in its garment_poses.npz header (meta 'loss'), the ablations by theirs.
from anidress_core.io.garment_poses import load_garment_poses
from anidress_core.stages import setup_logging
from anidress_core.stages.fit_eval import run_fit_eval

log = setup_logging(snakemake.log[0])
try:
    main = snakemake.input.full
    loss = load_garment_poses(main)[1].get("meta", {}).get("loss")
    if not loss:
        raise ValueError(f"{main}: header meta has no 'loss' (the loss variant of the fit); rerun rule fit")
    fits = {loss: main}
    for name, path in zip(snakemake.params.ablations, snakemake.input.ablations):
        if name in fits:  # the same variant as rule fit's: measured once, as rule fit's file
            log.warning("fit_eval: ablation %s is the loss of %s (fit/loss); measured once", name, main)
            continue
        fits[name] = path
    run_fit_eval(snakemake.input.scene, snakemake.wildcards.seq, snakemake.input.rig, fits, snakemake.output[0],
                 samples=snakemake.params.eval["samples"], seed=snakemake.params.eval["seed"])
except Exception:
    log.exception("fit_eval failed")
    raise
