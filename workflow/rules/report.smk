# The report (DESIGN.md §11): results/report.html from everything `rule all` builds.
# `snakemake --report results/workflow-report.html` also works (captions in reports/).


rule report:
    input:
        get_final_outputs(),
    output:
        report("results/report.html", caption="../../reports/captions/report.rst", category="Report"),
    log:
        "logs/report.log",
    params:
        scenes={"run_scenes": config["run_scenes"], "scenes": config["scenes"]},
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/report.py"
