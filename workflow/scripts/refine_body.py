# Rule refine_body: a sequence's body poses refined against its masks.
from anidress_core.stages import setup_logging

log = setup_logging(snakemake.log[0])
try:
    from anidress_core.body.refine import ADAM_SETTINGS, RefineConfig
    from anidress_core.stages.refine_body import run_refine_body

    p, inp = snakemake.params, snakemake.input
    cfg = RefineConfig(**ADAM_SETTINGS) if p.refine["method"] == "adam" else RefineConfig()
    rec = run_refine_body(inp.scene, snakemake.wildcards.seq, snakemake.output[0], masks_dir=p.masks,
                          undistorted_dir=inp.get("undistorted") or None, chunk=p.refine["chunk"], cfg=cfg,
                          threads=snakemake.threads, cameras=p.refine["cameras"])
    log.info("refine_body %s: %d frames x %d cameras in %.1f s; body silhouette IoU %.3f -> %.3f",
             snakemake.wildcards.seq, rec["frames"], len(rec["cameras"]), rec["seconds"], rec["body_iou_before"],
             rec["body_iou_after"])
except Exception:
    log.exception("refine_body failed")
    raise
