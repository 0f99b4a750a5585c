# Rule undistort: data/<scene>/<seq> with lens distortion -> results/<scene>/<seq>/undistorted (pinhole working cameras).
from anidress_core.stages import setup_logging
from anidress_core.stages.undistort import run_undistort

log = setup_logging(snakemake.log[0])
try:
    run_undistort(snakemake.input.scene, snakemake.wildcards.seq, snakemake.output[0], threads=snakemake.threads,
                  progress=False)
except Exception:
    log.exception("undistort failed")
    raise
