# Rule normals: the sequence's shipped normal maps checked (axis convention against the posed body), a captured
# sequence's written in the pipeline's format and axes, or the skip and why.
import os

from anidress_core.stages import setup_logging
from anidress_core.stages.cues import run_normals

log = setup_logging(snakemake.log[0])
try:
    maps = snakemake.output.maps
    if not snakemake.params.convert:
        os.makedirs(maps, exist_ok=True)  # the directory output holds nothing: the fit reads the shipped maps
    run_normals(snakemake.input.scene, snakemake.wildcards.seq, snakemake.params.normals, snakemake.output.record,
                cameras=snakemake.params.cameras, reason=snakemake.params.reason,
                undistorted_dir=snakemake.input.get("undistorted") or None,
                template_npz=snakemake.input.get("template") or None,
                out_dir=maps if snakemake.params.convert else None, threads=snakemake.threads)
except Exception:
    log.exception("normals failed")
    raise
