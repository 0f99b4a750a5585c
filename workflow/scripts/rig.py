# Rule rig: SSDR garment rigging model from the scene's simulated sequences.
import torch

from anidress_core.stages import setup_logging
from anidress_core.stages.rig import run_rig

log = setup_logging(snakemake.log[0])
try:
    torch.set_num_threads(snakemake.threads)
    run_rig(snakemake.input.template, list(snakemake.input.sims), snakemake.params.rig, snakemake.output[0])
except Exception:
    log.exception("rig failed")
    raise
