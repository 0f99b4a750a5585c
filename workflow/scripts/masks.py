# Rule masks: body/garment label masks of one sequence (anidress_core.stages.cues.run_masks).
from anidress_core.stages import setup_logging
from anidress_core.stages.cues import run_masks

log = setup_logging(snakemake.log[0])
try:
    template = snakemake.input.get("template") or None
    run_masks(snakemake.input.scene, snakemake.wildcards.seq, snakemake.output[0], snakemake.params.masks,
              template_npz=template, cameras=snakemake.params.cameras, threads=snakemake.threads, progress=False,
              undistorted_dir=snakemake.input.get("undistorted") or None)
except Exception:
    log.exception("masks failed")
    raise
