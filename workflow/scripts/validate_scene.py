# Rule validate_scene: check data/<scene> -> results/<scene>/scene_check.json (or one clear error).
import sys

from anidress_core.io.files import SceneError
from anidress_core.stages import setup_logging
from anidress_core.stages.validate import run_validate

log = setup_logging(snakemake.log[0])
try:
    run_validate(snakemake.input[0], snakemake.output[0], fit_texture=snakemake.params.fit_texture,
                 mask_plates=snakemake.params.mask_plates)
except SceneError as e:
    # the message names the file and the problem; a traceback would only bury it
    log.error("invalid scene: %s", e)
    sys.exit(2)
except Exception:
    log.exception("validate_scene failed")
    raise
