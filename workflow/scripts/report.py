# Rule report: results/report.html from the pipeline's outputs (+ the committed reference
# tables the rule names as inputs, labelled as such on the page).
from anidress_core.stages import setup_logging
from anidress_core.stages.report import REFERENCE_TABLES, run_report

log = setup_logging(snakemake.log[0])
try:
    references = {key: paths[0] for key in REFERENCE_TABLES if (paths := list(getattr(snakemake.input, key)))}
    run_report(dict(snakemake.params.scenes), snakemake.output[0], references=references)
except Exception:
    log.exception("report failed")
    raise
