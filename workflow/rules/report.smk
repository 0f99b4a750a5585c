# The report (DESIGN.md §11): results/report.html from everything `rule all` builds.
# `snakemake --report results/workflow-report.html` also works (captions in reports/).
#
# Besides this run's outputs the page shows two committed reference tables that no rule of
# the run makes (benchmarks/tradeoffs.csv from `snakemake bench`, benchmarks/rig.csv from
# benchmarks/bench_rig.py). They are inputs where they exist in the working directory (a
# change to them reruns the report), and the page labels them with their commit and date.


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
    conda:
        "../../envs/anidress.yaml"
    script:
        "../scripts/report.py"
