# Rule synth: generate data/<scene>/ from its config.
from anidress_core.stages import setup_logging
from anidress_core.stages.synth import run_synth

log = setup_logging(snakemake.log[0])
try:
    run_synth(snakemake.params.scene, snakemake.wildcards.scene, snakemake.output[0], threads=snakemake.threads)
except Exception:
    log.exception("synth failed")
    raise
