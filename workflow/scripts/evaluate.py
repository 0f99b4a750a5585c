# Rule evaluate_field: PSNR / SSIM / IoU / LPIPS / DISTS of a field's renders -> metrics.csv (against gt/masks, or
# the pipeline's masks where a sequence has no ground truth).
from anidress_core.stages import setup_logging

log = setup_logging(snakemake.log[0])
try:
    import torch

    from anidress_core.metrics.image import load_dists, load_lpips
    from anidress_core.stages.evaluate import run_evaluate

    torch.set_num_threads(snakemake.threads)
    m = snakemake.params.metrics
    run_evaluate(snakemake.input.scene, snakemake.params.renders, snakemake.output.csv, snakemake.output.summary, m,
                 lpips=load_lpips(**m["lpips"]), dists=load_dists(**m["dists"]), progress=False,
                 undistorted=snakemake.params.undistorted,
                 masks=snakemake.params.masks, bodies=snakemake.params.bodies)
except Exception:
    log.exception("evaluate failed")
    raise
