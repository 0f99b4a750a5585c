# Rule train_field: the pose-driven radiance field of one training sequence and variant.
from anidress_core.stages import setup_logging

log = setup_logging(snakemake.log[0])
try:
    import torch

    from anidress_core.metrics.image import load_lpips
    from anidress_core.stages.field import run_train

    torch.set_num_threads(snakemake.threads)
    p, inp, wc = snakemake.params, snakemake.input, snakemake.wildcards
    lpips = load_lpips(**p.lpips) if p.field["train"]["lpips_weight"] > 0 else None
    # field/train/checkpoint_every is not a param (a rerun trigger): a resumed training ends with the same field
    field = dict(p.field, train=dict(p.field["train"], checkpoint_every=snakemake.config["field"]["train"]["checkpoint_every"]))
    run_train(inp.scene, wc.seq, wc.variant, p.masks, snakemake.output[0], field,
              template_npz=inp.get("template"), rig_npz=inp.get("rig"), garment_poses_npz=inp.get("poses"),
              lpips=lpips, device=p.field["device"], progress=False, undistorted_dir=inp.get("undistorted") or None,
              body_dir=inp.get("body") or None)
except Exception:
    log.exception("train_field failed")
    raise
