# Rule normals: record the sequence's shipped normal maps (checked, used as they are) or the skip and why.
from anidress_core.stages import setup_logging
from anidress_core.stages.cues import run_normals

log = setup_logging(snakemake.log[0])
try:
    run_normals(snakemake.input.scene, snakemake.wildcards.seq, snakemake.params.normals, snakemake.output[0],
                cameras=snakemake.params.cameras, reason=snakemake.params.reason,
                undistorted_dir=snakemake.input.get("undistorted") or None)
except Exception:
    log.exception("normals failed")
    raise
