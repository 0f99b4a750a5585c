# Rule flows: forward optical flow of one sequence (anidress_core.stages.cues.run_flows).
from anidress_core.stages import setup_logging
from anidress_core.stages.cues import run_flows

log = setup_logging(snakemake.log[0])
try:
    template = snakemake.input.get("template") or None
    run_flows(snakemake.input.scene, snakemake.wildcards.seq, snakemake.params.masks, snakemake.output[0],
              snakemake.params.flows, template_npz=template, cameras=snakemake.params.cameras,
              threads=snakemake.threads, progress=False, undistorted_dir=snakemake.input.get("undistorted") or None)
except Exception:
    log.exception("flows failed")
    raise
