# Rule masks: body/garment label masks of one sequence: estimated (anidress_core.stages.cues.run_masks), or a human
# parser's shipped masks converted to labels (run_convert_masks).
from anidress_core.stages import setup_logging
from anidress_core.stages.cues import run_convert_masks, run_masks

log = setup_logging(snakemake.log[0])
try:
    undistorted = snakemake.input.get("undistorted") or None
    if snakemake.params.convert:
        run_convert_masks(snakemake.input.scene, snakemake.wildcards.seq, snakemake.output[0],
                          garment=snakemake.params.garment, threads=snakemake.threads, progress=False,
                          undistorted_dir=undistorted)
    else:
        template = snakemake.input.get("template") or None
        run_masks(snakemake.input.scene, snakemake.wildcards.seq, snakemake.output[0], snakemake.params.masks,
                  template_npz=template, cameras=snakemake.params.cameras, threads=snakemake.threads,
                  progress=False, undistorted_dir=undistorted)
except Exception:
    log.exception("masks failed")
    raise
