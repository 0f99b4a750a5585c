# The report (DESIGN.md §11): results/report.html from everything `rule all` builds.
# `snakemake --report results/workflow-report.html` also works (captions in reports/).
#
# Besides this run's outputs the page shows two committed reference tables that no rule of
# the run makes (benchmarks/tradeoffs.csv from `snakemake bench`, benchmarks/rig.csv from
# benchmarks/bench_rig.py). They are inputs where they exist in the working directory (a
# change to them reruns the report), and the page labels them with their commit and date.


# (from the light module, not stages.report: parsing the workflow imports no torch; issue 22)
from anidress_core.stages.references import REFERENCE_TABLES


def report_reference(key):
    """Input function: [path] of a committed reference table if present here, else []."""
    path = REFERENCE_TABLES[key]
    return lambda wildcards: [path] if os.path.isfile(path) else []


def report_scenes():
    """What the page takes from the config: the scenes run, their kind and sequences (names, roles, frames)."""
    return {"run_scenes": config["run_scenes"],
            "scenes": {s: {k: config["scenes"][s][k] for k in ("kind", "sequences")} for s in config["run_scenes"]}}


rule report:
    input:
        outputs=get_final_outputs(),
        tradeoffs=report_reference("tradeoffs"),
        rig_sweep=report_reference("rig_sweep"),
    output:
        report("results/report.html", caption="../../reports/captions/report.rst", category="Report"),
    log:
        "logs/report.log",
    params:
        scenes=report_scenes(),
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/report.py"
