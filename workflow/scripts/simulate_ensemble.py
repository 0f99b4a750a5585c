# Rule simulate_ensemble: a captured sequence's motion simulated at several bending stiffnesses and settle lengths,
# their mean.
from anidress_core.stages import setup_logging
from anidress_core.stages.simulate import run_simulate_ensemble

log = setup_logging(snakemake.log[0])
try:
    run_simulate_ensemble(snakemake.input.template, snakemake.input.motion, snakemake.input.scene,
                          snakemake.params.cloth, snakemake.params.bend_stiffness, snakemake.output[0],
                          settle_frames=snakemake.params.settle_frames)
except Exception:
    log.exception("simulate_ensemble failed")
    raise
