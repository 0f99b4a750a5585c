# Rule motions: one body motion to simulate (captured sequence, library motion or AMASS file).
from anidress_core.stages import setup_logging
from anidress_core.stages.simulate import run_motion

log = setup_logging(snakemake.log[0])
try:
    run_motion(snakemake.wildcards.motion, snakemake.input[0], snakemake.params.sim, snakemake.output[0],
               body_dir=snakemake.input.get("body") or None)
except Exception:
    log.exception("motions failed")
    raise
