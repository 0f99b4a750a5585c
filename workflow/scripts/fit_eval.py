# Rule fit_eval: fitted garments (full method + configured ablations) against the synthetic ground truth.
from anidress_core.stages import setup_logging
from anidress_core.stages.fit import run_fit_eval

log = setup_logging(snakemake.log[0])
try:
    fits = {"full": snakemake.input.full}
    fits.update(zip(snakemake.params.ablations, snakemake.input.ablations))
    run_fit_eval(snakemake.input.scene, snakemake.wildcards.seq, snakemake.input.rig, fits, snakemake.output[0],
                 samples=snakemake.params.eval["samples"], seed=snakemake.params.eval["seed"])
except Exception:
    log.exception("fit_eval failed")
    raise
