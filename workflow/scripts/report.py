# Rule report: results/report.html from the pipeline's outputs (and benchmarks/ sweeps).
from anidress_core.stages import setup_logging
from anidress_core.stages.report import run_report

log = setup_logging(snakemake.log[0])
try:
    run_report(dict(snakemake.params.scenes), snakemake.output[0])
except Exception:
    log.exception("report failed")
    raise
