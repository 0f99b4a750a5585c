# Rule template: garment template -> cleaned, remeshed, body-attached template.
from pathlib import Path

from anidress_core.stages import setup_logging
from anidress_core.io.scene import load_body, read_scene
from anidress_core.stages.template import run_template

log = setup_logging(snakemake.log[0])
try:
    scene_dir = Path(snakemake.input[0])
    info = read_scene(scene_dir)
    tpl = info.get("garment_template")
    run_template(scene_dir / tpl if tpl else None, snakemake.params.kind, load_body(scene_dir, info),
                 snakemake.params.vertices, snakemake.output.ply, snakemake.output.npz,
                 config={"vertices": snakemake.params.vertices})
except Exception:
    log.exception("template failed")
    raise
