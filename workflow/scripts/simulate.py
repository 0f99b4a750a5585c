# Rule simulate: cloth simulation of the garment template on one body motion.
from anidress_core.stages import setup_logging
from anidress_core.stages.simulate import run_simulate

log = setup_logging(snakemake.log[0])
try:
    run_simulate(snakemake.input.template, snakemake.input.motion, snakemake.input.scene, snakemake.params.cloth,
                 snakemake.output[0])
except Exception:
    log.exception("simulate failed")
    raise
