# Rules fit / fit_ablation: garment poses of one sequence from its 2D cues.
from pathlib import Path

from anidress_core.stages import setup_logging
from anidress_core.stages.fit import run_fit

log = setup_logging(snakemake.log[0])
try:
    cues = snakemake.params.cues
    params = dict(snakemake.params.fit, threads=snakemake.threads)
    run_fit(snakemake.input.scene, snakemake.wildcards.seq, snakemake.input.rig, snakemake.input.template,
            cues["masks"], cues["flows"], cues["normals"], params, snakemake.output[0],
            cue_source=cues["source"], undistorted_dir=snakemake.input.get("undistorted") or None,
            motions_dir=Path(snakemake.input.motions[0]).parent if snakemake.input.get("motions") else None,
            body_dir=snakemake.input.get("body") or None, sim_ensemble_npz=snakemake.input.get("sim_ensemble") or None)
except Exception:
    log.exception("fit failed")
    raise
